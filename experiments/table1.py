"""The paper's Table I and Fig. 3: DDPG+BC with the three exploration settings, several seeds each.

All settings and seeds train as one program (``--exploration ddpg_bc,targeted,mixed``: members are
settings x seeds, vmapped; seed s of each setting starts from the same networks and problems), from
one shared set of demonstrations. A run folder that holds ``final_eval.json`` is not trained again;
one with a checkpoint resumes.

    python experiments/table1.py train --demos runs/demos --out runs/table1 --preset paper --set epochs=250
    python experiments/table1.py report --runs runs/table1 --out experiments/results/table1_paper

One setting per run works too (``--settings mixed``; each device call then holds one program of three
learners), and ``report`` merges such runs: ``--runs runs/t1_mixed --runs runs/t1_ddpg_bc ...``.

``report`` reads the run's ``log.jsonl`` and ``final_eval.json`` and writes ``table1.md``,
``table1.csv``, ``table1.json`` and ``fig3.png``. Every success rate is of the bare policy (the
network alone, no collision shield), as the paper counts: at the last epoch, the mean of the last
ten epochs, the best epoch, and the exported policy (epoch best on validation problems of its own
seed, planned again through ``Policy.plan``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path

from regrasp_mjx import analysis
from regrasp_mjx.atomic import write_csv, write_figure, write_json, write_text

SETTINGS = ("ddpg_bc", "targeted", "mixed")
LABEL = {"ddpg_bc": "DDPG+BC", "targeted": "DDPG+BC (targeted)", "mixed": "DDPG+BC (mixed)"}
PAPER = {"ddpg_bc": (0.71, 0.0262, 4.2), "targeted": (0.64, 0.0233, 4.2), "mixed": (0.97, 0.0212, 4.2)}  # Table I


def train(args: argparse.Namespace) -> None:
    from regrasp_mjx.agents.ddpg_bc.config import make_config
    from regrasp_mjx.config import parse_overrides
    from regrasp_mjx.trainer import DEFAULT_TESTSET, Run

    out = Path(args.out)
    if (out / "final_eval.json").exists():
        print(f"done already ({out})", flush=True)
        return
    cfg = make_config(
        args.preset, args.settings, args.learner, seed=args.seed, num_seeds=args.seeds, **parse_overrides(args.set)
    )
    if not cfg.settings:  # one setting: still named in the log, so reports can merge runs
        cfg = dataclasses.replace(cfg, settings=((args.settings.strip(), cfg.exploration),))
    out.mkdir(parents=True, exist_ok=True)
    resume = (out / "checkpoint" / "meta.json").exists()
    print(f"training {args.settings} x {args.seeds} seeds in {out}{' (resumed)' if resume else ''}", flush=True)
    Run(cfg, out, Path(args.demos), Path(args.testset or DEFAULT_TESTSET), quiet=args.quiet).train(resume=resume)


def report(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    where: dict[str, Path] = {}  # setting -> the run folder holding it (runs of one setting each merge)
    finals = []
    for runs in map(Path, args.runs):
        final_path = runs / "final_eval.json"
        finals += json.loads(final_path.read_text())["seeds"] if final_path.exists() else []
        present = analysis.settings_in_log(runs / "log.jsonl")
        if not present:
            sys.exit(f"error: {runs}/log.jsonl names no setting; train with experiments/table1.py train")
        for setting in present:
            if setting in where:
                sys.exit(f"error: setting {setting} is in both {where[setting]} and {runs}")
            where[setting] = runs
    rows = {}
    for setting in [s for s in SETTINGS if s in where]:
        log = analysis.read_log(where[setting] / "log.jsonl", setting)
        rows[setting] = analysis.summarize_setting(log, [m for m in finals if m["setting"] == setting])
    lines = [
        f"Bare policy (no shield) on paper300; {len(next(iter(rows.values()))['seeds'])} seeds per setting; "
        f"{next(iter(rows.values()))['epochs']} epochs; mean ± std over seeds.",
        "",
        "| setting | last epoch | mean of last 10 epochs | best epoch | exported (best on validation) | "
        "exported, shielded | collision, last epoch | path (mm), last epoch | paper |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for setting, r in rows.items():
        lines.append(
            f"| {LABEL[setting]} | {analysis.mean_std(r['last'])} | {analysis.mean_std(r['last10'])} | {analysis.mean_std(r['best'])} | "
            f"{analysis.mean_std(r['exported'])} | {analysis.mean_std(r['exported_shielded'])} | {analysis.mean_std(r['collision_last'])} | "
            f"{analysis.mean_std(r['path_last'])} | {PAPER[setting][0]} |"
        )
    lines += ["", "Per seed (last epoch / exported, bare):", ""]
    for setting, r in rows.items():
        each = ", ".join(
            f"seed {s}: {a:.3f} / {e:.3f} (epoch {b})"
            for s, a, e, b in zip(r["seeds"], r["last"], r["exported"], r["best_epoch"])
        )
        lines.append(f"- {LABEL[setting]}: {each}")
    lines.append(
        f"\nTraining wall-clock (all settings and seeds in one program): {max(r['wall_s'] for r in rows.values()) / 60:.1f} min (the log's clock, compilation included)."
    )
    write_text(out / "table1.md", "\n".join(lines) + "\n")
    write_json(out / "table1.json", {"rows": rows})
    header = ["setting", "seed", "last", "last10", "best", "exported", "exported_shielded", "best_epoch"]
    fields = ("seeds", "last", "last10", "best", "exported", "exported_shielded", "best_epoch")
    write_csv(out / "table1.csv", header, [[s, *row] for s, r in rows.items() for row in zip(*(r[k] for k in fields))])
    for k, runs in enumerate(dict.fromkeys(where.values())):  # ship the logs the table is made from
        dest = out if len(args.runs) == 1 else out / f"run{k}"
        dest.mkdir(exist_ok=True)
        for name in ("log.jsonl", "final_eval.json"):
            if (runs / name).exists() and runs.resolve() != dest.resolve():
                shutil.copyfile(runs / name, dest / name)
    figure({s: where[s] / "log.jsonl" for s in rows}, out / "fig3.png")
    print("\n".join(lines))


def figure(logs: dict[str, Path], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for setting, log_path in logs.items():
        log = analysis.read_log(log_path, setting)
        epochs, succ = analysis.seed_band(log, "test.success_rate")
        _, bias = analysis.seed_band(log, "validation.q_bias")
        minutes = analysis.seed_band(log, "wall_s")[1][0] / 60
        for ax, x in zip(axes[:2], (epochs, minutes)):
            ax.plot(x, succ.mean(0), label=f"{LABEL[setting]} ({len(log)} seeds)")
            ax.fill_between(x, succ.min(0), succ.max(0), alpha=0.2)
        axes[2].plot(epochs, bias.mean(0), label=LABEL[setting])
        axes[2].fill_between(epochs, bias.min(0), bias.max(0), alpha=0.2)
    axes[0].set_xlabel("epoch (10 iterations)")
    axes[1].set_xlabel("training wall-clock (min, all settings and seeds in one program)")
    axes[0].set_ylabel("test success rate (bare)")
    axes[2].set_ylabel("critic over-estimation at the start, Q - return")
    axes[2].set_xlabel("epoch")
    for ax in axes[:2]:
        ax.axhline(0.97, color="grey", ls="--", lw=0.8)
        ax.set_ylim(0, 1)
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(loc="lower right")
    fig.suptitle("Fig. 3: test success during training (mean, range over seeds); dashed: paper's mixed 0.97")
    fig.tight_layout()
    write_figure(path, fig, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train the settings side by side (resumable)")
    t.add_argument("--demos", required=True, help="demonstration folder (python -m regrasp_mjx.demos)")
    t.add_argument("--out", required=True, help="run folder")
    t.add_argument("--settings", default=",".join(SETTINGS))
    t.add_argument("--preset", default="paper")
    t.add_argument("--learner", default="ours", choices=("ours", "paper"))
    t.add_argument("--seeds", type=int, default=3)
    t.add_argument("--seed", type=int, default=0, help="first seed")
    t.add_argument("--testset", default=None)
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    t.add_argument("--quiet", action="store_true")
    r = sub.add_parser("report", help="tables and figure from a finished run")
    r.add_argument(
        "--runs", action="append", required=True, help="a run folder (repeatable: runs of one setting each merge)"
    )
    r.add_argument("--out", required=True)
    args = p.parse_args(argv)
    train(args) if args.cmd == "train" else report(args)


if __name__ == "__main__":
    main()
