"""Why training decayed: the paper's learner against ours, at the paper's scale and at ours.

Reads four runs (``log.jsonl`` each; the mixed setting, 3 seeds) and draws, against epochs, the bare
test success and the critic's over-estimation on validation starts (``Q(s_0, pi(s_0))`` minus the
discounted return the rollout got), on all starts and on the starts whose rollout failed. Writes
``decay.png`` and ``decay.md`` (the numbers at a few epochs).

    python experiments/decay.py --dir experiments/results/decay --out experiments/results/decay
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from regrasp_mjx import analysis
from regrasp_mjx.atomic import write_figure, write_results

RUNS = {
    "paper_learner_paper_scale": ("paper's learner", "paper scale (5 envs)"),
    "ours_paper_scale": ("our learner", "paper scale (5 envs)"),
    "paper_learner_fast": ("paper's learner", "fast (512 envs)"),
    "ours_fast": ("our learner", "fast (512 envs)"),
}
COLUMNS = (
    ("test.success_rate", "test success (bare)"),
    ("validation.q_bias", "Q - return at the starts"),
    ("validation.q_bias_failed", "Q - return, failed starts"),
)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dir", required=True, help="folder holding the four run folders")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    logs = {name: analysis.read_log(Path(args.dir) / name / "log.jsonl") for name in RUNS}
    lines = [
        "Mixed exploration, 3 seeds; mean over seeds (test: paper300, bare; Q - return: 1000 validation starts).",
        "",
        "| run | epoch | test success | Q - return | Q - return, failed starts |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    data = {}
    for name, log in logs.items():
        ep, _ = analysis.seed_band(log, "test.success_rate")
        cols = {c: np.nanmean(analysis.seed_band(log, c)[1], axis=0) for c, _ in COLUMNS}
        data[name] = {"epoch": ep.tolist(), **{c: v.tolist() for c, v in cols.items()}}
        for e in sorted({e for e in (10, 30, 50, 80, 100) if e <= ep[-1]} | {int(ep[-1])}):
            i = int(np.flatnonzero(ep == e)[0])
            lines.append(
                f"| {' / '.join(RUNS[name])} | {e} | {cols['test.success_rate'][i]:.3f} | "
                f"{cols['validation.q_bias'][i]:+.3f} | {cols['validation.q_bias_failed'][i]:+.3f} |"
            )
    write_results(args.out, "decay", lines, data)
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(16, 8), sharex="row")
    for row, scale in enumerate(("paper scale (5 envs)", "fast (512 envs)")):
        for name, log in logs.items():
            learner, s = RUNS[name]
            if s != scale:
                continue
            colour = "tab:red" if learner == "paper's learner" else "tab:blue"
            for ax, (column, title) in zip(axes[row], COLUMNS):
                ep, values = analysis.seed_band(log, column)
                ax.plot(ep, np.nanmean(values, 0), color=colour, label=learner)
                ax.fill_between(ep, np.nanmin(values, 0), np.nanmax(values, 0), color=colour, alpha=0.15)
                ax.set_title(f"{title}: {scale}")
        axes[row, 0].axhline(0.97, color="grey", ls="--", lw=0.8)
        axes[row, 0].set_ylim(0.6, 1.0)
        for ax in axes[row, 1:]:
            ax.axhline(0.0, color="black", lw=0.6)
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
        ax.set_xlabel("epoch")
    axes[0, 0].legend(loc="lower right")
    fig.suptitle(
        "The paper's learner over-estimates (Q above the return it gets, most on the starts it fails) and decays; "
        "ours (clipped double Q, target smoothing, exploration floor, actor EMA, cosine LR) does not"
    )
    fig.tight_layout()
    write_figure(Path(args.out) / "decay.png", fig, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
