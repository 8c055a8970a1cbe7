"""Success against training wall-clock: the shipped recipe (one seed alone on the GPU: our learner,
then distillation) beside the earlier ``fast`` preset (the paper's learner; its Table I runs).

    python experiments/wallclock.py --recipe experiments/results/shipping/one_seed \\
        --old experiments/results/table1_fast_paper_learner/mixed --out experiments/results/shipping

Clocks are the logs' own: seconds since the training loop started (compilation included; the
demonstrations are built before it). The student's clock starts where the learner's ends. Writes
``wallclock.png`` and ``wallclock.md`` (the first time each seed's bare test success reached 0.97
and 0.99).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from regrasp_mjx import analysis
from regrasp_mjx.atomic import write_figure, write_results


def first_time(times: np.ndarray, values: np.ndarray, level: float) -> float | None:
    hit = np.flatnonzero(values >= level - 1e-9)
    return float(times[hit[0]]) if len(hit) else None


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--recipe", required=True, help="folder with the recipe's log.jsonl and distill_log.jsonl")
    p.add_argument("--old", required=True, help="folder with the earlier fast preset's log.jsonl")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    recipe = analysis.read_log(Path(args.recipe) / "log.jsonl")
    old = analysis.read_log(Path(args.old) / "log.jsonl")
    rows = [json.loads(x) for x in (Path(args.recipe) / "distill_log.jsonl").read_text().splitlines() if x.strip()]
    rl_end = max(float(c["wall_s"][-1]) for c in recipe.values())
    d_t = np.array([rl_end + r["wall_s"] for r in rows])
    d_s = np.array([r["test"]["success_rate"] for r in rows])
    fmt = lambda v: "-" if v is None else f"{v:.0f}"  # noqa: E731
    lines = [
        "Seconds since the training loop started (compilation included), first epoch or iteration whose bare test "
        "success reached the level.",
        "",
        "| run | seed | 0.97 | 0.99 |",
        "| --- | ---: | ---: | ---: |",
    ]
    data = {}
    for name, log in (
        ("recipe: our learner (alone on the GPU)", recipe),
        ("earlier fast preset (3 programs sharing the GPU)", old),
    ):
        for seed, cols in log.items():
            t, s = cols["wall_s"], cols["test.success_rate"]
            hit = (first_time(t, s, 0.97), first_time(t, s, 0.99))
            data[f"{name} seed {seed}"] = hit
            lines.append(f"| {name} | {seed} | {fmt(hit[0])} | {fmt(hit[1])} |")
    hit = (first_time(d_t, d_s, 0.97), first_time(d_t, d_s, 0.99))
    data["recipe: student"] = hit
    lines.append(f"| recipe: its student (distillation after the learner) | 0 | {fmt(hit[0])} | {fmt(hit[1])} |")
    write_results(args.out, "wallclock", lines, data)
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for seed, cols in old.items():
        ax.plot(
            cols["wall_s"] / 60,
            cols["test.success_rate"],
            color="tab:red",
            alpha=0.7,
            lw=1,
            label="earlier fast preset, paper's learner (3 seeds; 3 programs shared the H100)"
            if seed == min(old)
            else None,
        )
    for cols in recipe.values():
        ax.plot(
            cols["wall_s"] / 60,
            cols["test.success_rate"],
            color="tab:blue",
            label="recipe: our learner, one seed alone",
        )
    ax.plot(d_t / 60, d_s, color="tab:green", marker=".", label="recipe: distilled 3x256 student (after the learner)")
    for level, ls in ((0.97, "--"), (0.99, ":")):
        ax.axhline(level, color="grey", ls=ls, lw=0.8)
    ax.set_ylim(0.85, 1.0)
    ax.set_xlabel("minutes since the training loop started (one H100)")
    ax.set_ylabel("test success (bare)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    write_figure(Path(args.out) / "wallclock.png", fig, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
