"""Table I's settings over the paper's full 500 epochs: where each setting peaks and where it ends.

Each setting trains as its own run (one device call each, ``experiments/table1.py train --settings
S --set epochs=500``); this script reads each run's ``log.jsonl`` or, where the log did not come back
from the GPU machine, the run's printed progress (``epoch E/N  val success a/b/c  test success
d/e/f (collision ...``, the same numbers to three decimals), and writes ``long_run.md``/``.json``
(per setting: bare test success at epochs 50 ... the last as the mean of the 10 epochs up to it, the
best validation epoch, the last epoch's validation minus the best) and ``long_run.png``.

    python experiments/long_run.py --run mixed=runs/t1_mixed --run ddpg_bc=runs/t1_ddpg_bc/stdout.txt \\
        --out experiments/results/table1_paper500
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from regrasp_mjx import analysis  # noqa: E402
from regrasp_mjx.atomic import write_figure, write_results  # noqa: E402

LABEL = {"ddpg_bc": "DDPG+BC", "targeted": "DDPG+BC (targeted)", "mixed": "DDPG+BC (mixed)"}
CHECKPOINTS = (50, 100, 200, 300, 400)
_PROGRESS = re.compile(r"epoch (\d+)/\d+\s+val success ([\d./]+)\s+test success ([\d./]+) \(collision ([\d./]+)")


def read_progress(path: Path) -> dict[str, np.ndarray]:
    """``{"epoch": [E], "val"/"test"/"collision": [seeds, E]}`` from a run's printed progress lines."""
    rows = {}
    for line in path.read_text().splitlines():
        m = _PROGRESS.match(line)
        if m:
            rows[int(m[1])] = [np.array(m[i].split("/"), float) for i in (2, 3, 4)]
    if not rows:
        raise SystemExit(f"error: {path} has no progress lines ('epoch E/N  val success ...')")
    epochs = np.array(sorted(rows))
    val, test, coll = (np.stack([rows[e][i] for e in epochs], 1) for i in range(3))
    return {"epoch": epochs, "val": val, "test": test, "collision": coll}


def read_run(path: Path, setting: str) -> dict[str, np.ndarray]:
    if path.is_file():
        return read_progress(path)
    log = analysis.read_log(path / "log.jsonl", setting)
    epochs, test = analysis.seed_band(log, "test.success_rate")
    _, val = analysis.seed_band(log, "validation.success_rate")
    _, coll = analysis.seed_band(log, "test.collision_rate")
    return {"epoch": epochs, "val": val, "test": test, "collision": coll}


def summarize(run: dict[str, np.ndarray]) -> dict:
    epochs, test, val = run["epoch"], run["test"], run["val"]

    def last10(upto: int) -> list[float]:
        sel = (epochs > upto - 10) & (epochs <= upto)
        return test[:, sel].mean(1).tolist()

    best = val.argmax(1)
    return {
        "epochs": int(epochs[-1]),
        "at": {str(e): last10(e) for e in CHECKPOINTS if e <= epochs[-1]},
        "last10": last10(int(epochs[-1])),
        "last_collision10": run["collision"][:, -10:].mean(1).tolist(),
        "best_val_epoch": [int(epochs[i]) for i in best],
        "best_val": val.max(1).tolist(),
        "last_minus_best_val": (val[:, -1] - val.max(1)).tolist(),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="append", required=True, metavar="SETTING=RUN_FOLDER_OR_PROGRESS_FILE")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    runs = {}
    for item in args.run:
        setting, sep, path = item.partition("=")
        if not sep or setting not in LABEL:
            raise SystemExit(f"error: --run {item!r} is not accepted: SETTING=PATH with SETTING in {sorted(LABEL)}")
        runs[setting] = read_run(Path(path), setting)
    data = {s: summarize(r) for s, r in runs.items()}
    ms = lambda xs: f"{np.mean(xs):.3f} ± {np.std(xs):.3f}"  # noqa: E731
    head = " | ".join(f"epoch {e}" for e in CHECKPOINTS)
    lines = [
        "Bare test success on paper300, mean of the 10 epochs up to the named one (mean ± std over 3 seeds).",
        "",
        f"| setting | {head} | last (epoch) | collision, last 10 | best validation (epoch) | last - best, validation |",
        "| --- |" + " --- |" * len(CHECKPOINTS) + " --- | --- | --- | --- |",
    ]
    for s, d in data.items():
        cells = " | ".join(ms(d["at"][str(e)]) if str(e) in d["at"] else "-" for e in CHECKPOINTS)
        lines.append(
            f"| {LABEL[s]} | {cells} | {ms(d['last10'])} ({d['epochs']}) | {ms(d['last_collision10'])} | "
            f"{ms(d['best_val'])} ({', '.join(map(str, d['best_val_epoch']))}) | {ms(d['last_minus_best_val'])} |"
        )
    print("\n".join(lines))
    write_results(args.out, "long_run", lines, data)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for (s, r), colour in zip(runs.items(), ("tab:green", "tab:blue", "tab:orange")):
        ax.plot(r["epoch"], r["test"].mean(0), color=colour, lw=1, label=LABEL[s])
        ax.fill_between(r["epoch"], r["test"].min(0), r["test"].max(0), color=colour, alpha=0.2)
    ax.axhline(0.97, color="grey", ls="--", lw=0.8, label="paper: mixed 0.97")
    ax.set_ylim(0.9, 1.0)
    ax.set_xlabel("epoch (5 environments, 2000 updates per epoch)")
    ax.set_ylabel("test success on paper300 (bare)")
    ax.legend(loc="lower left")
    fig.tight_layout()
    write_figure(Path(args.out) / "long_run.png", fig, dpi=120)


if __name__ == "__main__":
    main()
