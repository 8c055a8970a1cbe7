"""What each part of the learner is worth: runs that differ in one setting, side by side.

Each run is a folder written by ``python -m regrasp_mjx.train`` (``log.jsonl``, and
``final_eval.json`` when it finished). ``report`` writes ``NAME.md``/``NAME.json`` (a table: the
bare test success at the last epoch, the mean of the last ten, the best epoch and the gap between
last and best, the exported policy bare and shielded, its student when the run distilled one, the
first epoch at 0.97 and 0.99, the critic's over-estimation at the starts) and ``NAME.png`` (test
success and over-estimation against epochs, mean and range over seeds).

    python experiments/ablation.py --run "ours=runs/ab/ours" --run "no noise=runs/ab/no_noise" \\
        --run "paper learner=runs/c1/fast_v0:60" --out experiments/results/ablation --name ablation

``FOLDER:EPOCHS`` reads only the first EPOCHS epochs of a longer run (its exported policies are then
not comparable and are left out).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from regrasp_mjx import analysis
from regrasp_mjx.atomic import write_figure, write_results


def first_epoch(epochs: np.ndarray, values: np.ndarray, level: float) -> list[float | None]:
    """Per seed, the first epoch whose value reaches ``level`` (None if none does)."""
    out = []
    for row in values:
        hit = np.flatnonzero(row >= level - 1e-9)
        out.append(float(epochs[hit[0]]) if len(hit) else None)
    return out


def summarize_run(folder: Path, epochs: int | None = None) -> dict:
    log = analysis.read_log(folder / "log.jsonl")
    if epochs is not None:
        log = {s: {k: v[:epochs] for k, v in cols.items()} for s, cols in log.items()}
    ep, test = analysis.seed_band(log, "test.success_rate")
    _, val = analysis.seed_band(log, "validation.success_rate")
    _, bias = (
        analysis.seed_band(log, "validation.q_bias")
        if "validation.q_bias" in next(iter(log.values()))
        else (None, None)
    )
    row = {
        "seeds": sorted(log),
        "epochs": int(ep[-1]),
        "last": test[:, -1].tolist(),
        "last10": test[:, -10:].mean(1).tolist(),
        "best": test.max(1).tolist(),
        "val_last": val[:, -1].tolist(),
        "val_best": val.max(1).tolist(),
        "epoch_097": first_epoch(ep, test, 0.97),
        "epoch_099": first_epoch(ep, test, 0.99),
        "q_bias_last": None if bias is None else bias[:, -1].tolist(),
    }
    final_path = folder / "final_eval.json"
    if epochs is None and final_path.exists():
        final = json.loads(final_path.read_text())
        row["exported"] = [m["test"]["bare"]["success_rate"] for m in final["seeds"]]
        row["exported_shielded"] = [m["test"]["shielded"]["success_rate"] for m in final["seeds"]]
        if "students" in final:
            row["student"] = [s["test"]["bare"]["success_rate"] for s in final["students"]]
            row["student_shielded"] = [s["test"]["shielded"]["success_rate"] for s in final["students"]]
    return row


def _ms(xs) -> str:
    xs = [x for x in (xs or []) if x is not None]
    if not xs:
        return "-"
    return f"{np.mean(xs):.3f} ± {np.std(xs):.3f}" if len(xs) > 1 else f"{xs[0]:.3f}"


def _epochs(xs) -> str:
    return "/".join("-" if x is None else f"{x:.0f}" for x in xs)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="append", required=True, metavar="NAME=FOLDER[:EPOCHS]")
    p.add_argument("--out", required=True)
    p.add_argument("--name", default="ablation")
    args = p.parse_args(argv)
    rows = {}
    for item in args.run:
        name, _, spec = item.rpartition("=")
        folder, _, epochs = spec.partition(":")
        rows[name] = summarize_run(Path(folder), int(epochs) if epochs else None)
    lines = [
        "Test success on paper300 of the bare policy (no shield); mean ± std over seeds; exported = epoch best "
        "on validation, planned again through Policy.plan.",
        "",
        "| run | epochs | last epoch | last 10 epochs | best epoch | last - best | exported | exported, shielded "
        "| student | student, shielded | first epoch at 0.97 / 0.99 (per seed) | Q - return at the starts, last |",
        "| --- | ---: | --- | --- | --- | ---: | --- | --- | --- | --- | --- | --- |",
    ]
    for name, r in rows.items():
        gap = np.mean(np.array(r["last"]) - np.array(r["best"]))
        lines.append(
            f"| {name} | {r['epochs']} | {_ms(r['last'])} | {_ms(r['last10'])} | {_ms(r['best'])} | {gap:+.3f} | "
            f"{_ms(r.get('exported'))} | {_ms(r.get('exported_shielded'))} | {_ms(r.get('student'))} | "
            f"{_ms(r.get('student_shielded'))} | {_epochs(r['epoch_097'])} ; {_epochs(r['epoch_099'])} | "
            f"{_ms(r['q_bias_last'])} |"
        )
    print("\n".join(lines))
    write_results(args.out, args.name, lines, rows)
    figure(args.run, Path(args.out) / f"{args.name}.png")


def figure(runs: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    for item in runs:
        name, _, spec = item.rpartition("=")
        folder, _, epochs = spec.partition(":")
        log = analysis.read_log(Path(folder) / "log.jsonl")
        if epochs:
            log = {s: {k: v[: int(epochs)] for k, v in cols.items()} for s, cols in log.items()}
        ep, test = analysis.seed_band(log, "test.success_rate")
        (line,) = axes[0].plot(ep, test.mean(0), label=f"{name} ({len(log)} seeds)")
        axes[0].fill_between(ep, test.min(0), test.max(0), color=line.get_color(), alpha=0.15)
        if "validation.q_bias" in next(iter(log.values())):
            _, bias = analysis.seed_band(log, "validation.q_bias")
            axes[1].plot(ep, bias.mean(0), color=line.get_color(), label=name)
    axes[0].set_ylim(0.7, 1.0)
    axes[0].axhline(0.99, color="grey", ls=":", lw=0.8)
    axes[0].axhline(0.97, color="grey", ls="--", lw=0.8)
    axes[0].set_xlabel("epoch")
    axes[0].set_ylabel("test success (bare)")
    axes[1].axhline(0.0, color="black", lw=0.6)
    axes[1].set_xlabel("epoch")
    axes[1].set_ylabel("critic over-estimation at the starts (Q - return)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    write_figure(path, fig, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
