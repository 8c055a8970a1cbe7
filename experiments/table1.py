"""The paper's Table I and Fig. 3: DDPG+BC with the three exploration settings, several seeds each.

Each setting is one training program with a seed axis (``--seeds`` learners vmapped together, see
``regrasp_mjx.agents.ddpg_bc.train``), from one shared set of demonstrations. A setting whose run
folder already holds ``final_eval.json`` is not trained again; one with a checkpoint resumes, so a
device call that ends mid-run loses at most an epoch.

    python experiments/table1.py train --demos runs/demos --out runs/table1 [--settings mixed,ddpg_bc,targeted]
    python experiments/table1.py report --runs runs/table1 --out experiments/results/table1

``report`` reads the runs' ``log.jsonl`` and ``final_eval.json`` (which the repository ships under
``experiments/results/table1/``), and writes ``table1.md``, ``table1.csv`` and ``fig3.png`` (test
success against epoch and against training wall-clock, mean and range over seeds). Planning time
comes from ``planning_time.json`` beside them when present (``regrasp_mjx.evaluate``).
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import shutil
import sys
from pathlib import Path

import numpy as np

from regrasp_mjx import analysis

SETTINGS = ("ddpg_bc", "targeted", "mixed")
LABEL = {"ddpg_bc": "DDPG+BC", "targeted": "DDPG+BC (targeted)", "mixed": "DDPG+BC (mixed)"}
PAPER = {"ddpg_bc": (0.71, 0.0262, 4.2), "targeted": (0.64, 0.0233, 4.2), "mixed": (0.97, 0.0212, 4.2)}  # Table I


def train(args: argparse.Namespace) -> None:
    from regrasp_mjx.agents.ddpg_bc.config import make_config
    from regrasp_mjx.train import DEFAULT_TESTSET, Run, _parse_overrides

    out = Path(args.out)
    for setting in args.settings.split(","):
        folder = out / setting
        if (folder / "final_eval.json").exists():
            print(f"{setting}: done already ({folder})", flush=True)
            continue
        overrides = _parse_overrides(args.set)
        cfg = make_config(args.preset, setting, seed=args.seed, num_seeds=args.seeds, **overrides)
        folder.mkdir(parents=True, exist_ok=True)
        resume = (folder / "checkpoint" / "meta.json").exists()
        print(f"{setting}: training {args.seeds} seeds in {folder}{' (resumed)' if resume else ''}", flush=True)
        run = Run(cfg, folder, Path(args.demos), Path(args.testset or DEFAULT_TESTSET), quiet=args.quiet)
        final = run.train(resume=resume)
        print(json.dumps({"setting": setting, "test": [m["test"] for m in final["seeds"]]}), flush=True)


def _load(runs: Path) -> dict[str, dict]:
    found = {}
    for setting in SETTINGS:
        final, log = runs / setting / "final_eval.json", runs / setting / "log.jsonl"
        if final.exists() and log.exists():
            found[setting] = {
                "final": json.loads(final.read_text()),
                "log": analysis.read_log(log),  # {seed: {column: array over epochs}}
            }
    if not found:
        sys.exit(f"error: no finished runs under {runs} (expected {', '.join(SETTINGS)} with final_eval.json)")
    return found


def _mean_std(xs: list[float | None]) -> str:
    xs = [x for x in xs if x is not None]
    if not xs:
        return "-"
    return f"{np.mean(xs):.3f} ± {np.std(xs):.3f}" if len(xs) > 1 else f"{xs[0]:.3f}"


def report(args: argparse.Namespace) -> None:
    runs, out = Path(args.runs), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    found = _load(runs)
    timing_path = runs / "planning_time.json"
    timing = json.loads(timing_path.read_text()) if timing_path.exists() else {}
    rows = []
    for setting, run in found.items():
        seeds = run["final"]["seeds"]
        tm = timing.get(setting, {})
        wall = max(float(cols["wall_s"].max()) for cols in run["log"].values())
        rows.append(
            {
                "setting": setting,
                "seeds": [m["seed"] for m in seeds],
                "success": [m["test"]["success_rate"] for m in seeds],
                "collision": [m["test"]["collision_rate"] for m in seeds],
                "path_mm": [m["test"]["path_length_mm"] for m in seeds],
                "best_epoch": [m["best_epoch"] for m in seeds],
                "plan_ms_median": tm.get("median_ms"),
                "plan_ms_mean": tm.get("mean_ms"),
                "wall_s": wall,
                "epochs": int(max(cols["epoch"].max() for cols in run["log"].values())),
            }
        )
    lines = [
        "| setting | seeds | success rate | collision rate | path length (mm) | planning time mean / median (ms) "
        "| paper: success, time (s), path (mm) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        plan = f"{r['plan_ms_mean']:.2f} / {r['plan_ms_median']:.2f}" if r["plan_ms_median"] is not None else "-"
        paper = PAPER[r["setting"]]
        lines.append(
            f"| {LABEL[r['setting']]} | {len(r['seeds'])} | {_mean_std(r['success'])} | {_mean_std(r['collision'])} "
            f"| {_mean_std(r['path_mm'])} | {plan} | {paper[0]}, {paper[1]}, {paper[2]} |"
        )
    lines.append("")
    lines.append("Per seed (success / collision / path mm, best epoch by validation):")
    lines.append("")
    for r in rows:
        each = ", ".join(
            f"seed {s}: {a:.3f} / {c:.3f} / {p:.2f} (epoch {e})"
            for s, a, c, p, e in zip(r["seeds"], r["success"], r["collision"], r["path_mm"], r["best_epoch"])
        )
        lines.append(f"- {LABEL[r['setting']]}: {each}; training {r['wall_s'] / 60:.1f} min for {r['epochs']} epochs")
    (out / "table1.md").write_text("\n".join(lines) + "\n")
    with open(out / "table1.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["setting", "seed", "success_rate", "collision_rate", "path_length_mm", "best_epoch"])
        for r in rows:
            for row in zip(r["seeds"], r["success"], r["collision"], r["path_mm"], r["best_epoch"]):
                w.writerow([r["setting"], *row])
    if runs.resolve() != out.resolve():  # ship the logs the figure is made from
        for setting in found:
            (out / setting).mkdir(exist_ok=True)
            for name in ("log.jsonl", "final_eval.json"):
                shutil.copyfile(runs / setting / name, out / setting / name)
    _figure(found, out / "fig3.png")
    print("\n".join(lines))
    print(f"wrote {out / 'table1.md'}, {out / 'table1.csv'}, {out / 'fig3.png'} ({platform.node()})")


def _figure(found: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for setting, run in found.items():
        epochs, succ = analysis.seed_band(run["log"], "test.success_rate")
        minutes = analysis.seed_band(run["log"], "wall_s")[1][0] / 60  # the first seed's clock
        for ax, x in zip(axes, (epochs, minutes)):
            ax.plot(x, succ.mean(0), label=f"{LABEL[setting]} ({len(run['log'])} seeds)")
            ax.fill_between(x, succ.min(0), succ.max(0), alpha=0.2)
    axes[0].set_xlabel("epoch (10 iterations)")
    axes[1].set_xlabel("training wall-clock (min, all seeds together)")
    axes[0].set_ylabel("test-set success rate")
    for ax in axes:
        ax.axhline(0.97, color="grey", ls="--", lw=0.8)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="lower right")
    fig.suptitle("Fig. 3: test-set success during training (mean, range over seeds); dashed: paper's 0.97")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train the settings (resumable)")
    t.add_argument("--demos", required=True, help="demonstration folder (python -m regrasp_mjx.demos)")
    t.add_argument("--out", required=True, help="runs folder, one subfolder per setting")
    t.add_argument("--settings", default=",".join(SETTINGS))
    t.add_argument("--preset", default="fast")
    t.add_argument("--seeds", type=int, default=3)
    t.add_argument("--seed", type=int, default=0, help="first seed")
    t.add_argument("--testset", default=None)
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    t.add_argument("--quiet", action="store_true")
    r = sub.add_parser("report", help="tables and figure from finished runs")
    r.add_argument("--runs", required=True)
    r.add_argument("--out", required=True)
    args = p.parse_args(argv)
    train(args) if args.cmd == "train" else report(args)


if __name__ == "__main__":
    main()
