"""Why our learner drifts down at the paper's scale: the same run with one change at a time.

Each ``--run NAME=LOG`` is a run's ``log.jsonl`` (or ``.jsonl.gz``) of three seeds trained with
``--preset paper --seeds 3 --set epochs=500`` and one change (the baseline: none). Runs stopped by a
device call's deadline are compared at the epochs they reached. Writes ``drift.md``/``.json``: per
run and epoch, validation success, collision and time-out rates, steps per successful episode and
test path length (each the mean over the 5 epochs up to the named one, then mean +- std over the
seeds), and per run the best validation epoch and the last epoch minus the best; and ``drift.png``.

    python experiments/drift.py --out experiments/results/drift \\
        --run "baseline=experiments/results/table1_paper500/mixed.log.jsonl.gz" \\
        --run "BC off by epoch 100=experiments/results/drift/bcdecay.log.jsonl.gz"
"""

from __future__ import annotations

import argparse
import gzip
import json
from collections import Counter
from pathlib import Path

import numpy as np

from regrasp_mjx.atomic import write_figure, write_results  # noqa: E402

EPOCHS = (50, 100, 150, 200, 250, 300, 400)
COLUMNS = (
    ("validation success", ("validation", "success_rate"), "{:.3f}"),
    ("collision", ("validation", "collision_rate"), "{:.3f}"),
    ("time-out", ("validation", "time_out_rate"), "{:.3f}"),
    ("steps", ("validation", "steps"), "{:.1f}"),
    ("test path (mm)", ("test", "path_length_mm"), "{:.2f}"),
)


def read(path: Path) -> dict[str, np.ndarray]:
    """``{"epoch": [E], column: [seeds, E]}`` from a run's log (one row per seed and epoch)."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        rows = [json.loads(line) for line in f if line.strip()]
    if not rows:
        raise SystemExit(f"error: {path} holds no log rows")
    seeds = sorted({r["seed"] for r in rows})
    logged = Counter(r["epoch"] for r in rows)
    epochs = sorted(e for e, n in logged.items() if n == len(seeds))  # epochs every seed logged
    at = {(r["seed"], r["epoch"]): r for r in rows}
    out = {"epoch": np.array(epochs)}
    for name, (a, b), _ in COLUMNS:
        out[name] = np.array(
            [[at[s, e][a][b] if at[s, e][a][b] is not None else np.nan for e in epochs] for s in seeds]
        )
    return out


def window(run: dict[str, np.ndarray], column: str, upto: int, width: int = 5) -> np.ndarray:
    """Per seed, the mean of ``column`` over the ``width`` epochs up to ``upto``."""
    sel = (run["epoch"] > upto - width) & (run["epoch"] <= upto)
    return np.nanmean(run[column][:, sel], axis=1) if sel.any() else np.full(run[column].shape[0], np.nan)


def summarize(run: dict[str, np.ndarray], epochs: tuple[int, ...] = EPOCHS) -> dict:
    val = run["validation success"]
    best = val.max(axis=1)
    last = int(run["epoch"][-1])
    rows = {}
    for e in sorted({e for e in epochs if e <= last} | {last}):
        rows[e] = {c: [float(x) for x in window(run, c, e)] for c, _, _ in COLUMNS}
    return {
        "last_epoch": last,
        "best_validation": [float(b) for b in best],
        "best_epoch": [int(run["epoch"][i]) for i in val.argmax(axis=1)],
        "last_minus_best": [float(x) for x in val[:, -1] - best],
        "at": rows,
    }


def fmt(values: list[float], spec: str) -> str:
    v = np.array(values, float)
    return f"{spec.format(np.nanmean(v))} ± {spec.format(np.nanstd(v))}"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="append", required=True, metavar="NAME=LOG")
    p.add_argument("--out", required=True)
    p.add_argument("--epochs", default=",".join(map(str, EPOCHS)), help="epochs tabled (and each run's last)")
    p.add_argument("--name", default="drift", help="the output files' stem")
    args = p.parse_args(argv)
    epochs = tuple(int(e) for e in args.epochs.split(","))
    runs = {}
    for item in args.run:
        name, sep, path = item.partition("=")
        if not sep:
            raise SystemExit(f"error: --run {item!r} is not accepted: NAME=LOG")
        runs[name] = read(Path(path))
    summary = {name: summarize(run, epochs) for name, run in runs.items()}
    lines = [
        "| run | epoch | " + " | ".join(c for c, _, _ in COLUMNS) + " |",
        "| --- | ---: |" + " --- |" * len(COLUMNS),
    ]
    for name, s in summary.items():
        for e, cols in s["at"].items():
            cells = " | ".join(fmt(cols[c], spec) for c, _, spec in COLUMNS)
            lines.append(f"| {name} | {e} | {cells} |")
    lines += [
        "",
        "| run | epochs reached | best validation (epoch) | last - best, validation |",
        "| --- | ---: | --- | --- |",
    ]
    for name, s in summary.items():
        lines.append(
            f"| {name} | {s['last_epoch']} | {fmt(s['best_validation'], '{:.3f}')} "
            f"({', '.join(map(str, s['best_epoch']))}) | {fmt(s['last_minus_best'], '{:+.3f}')} |"
        )
    write_results(args.out, args.name, lines, summary)
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = ("validation success", "collision", "time-out", "steps")
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4))
    for name, run in runs.items():
        for ax, col in zip(axes, panels):
            # 5-epoch running mean per seed, then the seeds' mean and range
            k = np.ones(5) / 5
            smooth = np.array([np.convolve(np.nan_to_num(s), k, mode="valid") for s in run[col]])
            x = run["epoch"][4:]
            (line,) = ax.plot(x, smooth.mean(0), label=name, lw=1.2)
            ax.fill_between(x, smooth.min(0), smooth.max(0), color=line.get_color(), alpha=0.2, lw=0)
    for ax, col in zip(axes, panels):
        ax.set_title(("steps per success" if col == "steps" else col) + ", validation", fontsize=9)
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes[0].set_ylim(0.6, 1.0)
    axes[1].set_ylim(0.0, 0.08)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    write_figure(Path(args.out) / f"{args.name}.png", fig, dpi=120)


if __name__ == "__main__":
    main()
