"""Chooses the closed loop's settings (warm-up frames, stop tolerance) on validation problems of
their own seed, never on paper300: fused closed loop of the shipped policy at frame noise 0.1, 0.25
and 0.5 mm; the setting with the best mean success over the three is ``Policy.execute``'s default.

    python experiments/closed_loop_select.py --n 1000 --seed 7000017 --out experiments/results/closed_loop
"""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np

from regrasp_mjx.atomic import write_results  # noqa: E402
from regrasp_mjx.closed_loop import NeedleNoise  # noqa: E402
from regrasp_mjx.evaluate import episode_poses  # noqa: E402
from regrasp_mjx.policy import load_policy  # noqa: E402
from regrasp_mjx.testset import make_testset  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1000)
    p.add_argument("--seed", type=int, default=7000017)
    p.add_argument("--sigmas", default="0.1,0.25,0.5")
    p.add_argument("--warmups", default="1,5,10")
    p.add_argument("--stops", default="1,0.7,0.5")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    policy = load_policy()
    needle, start, goal = episode_poses(make_testset(args.n, args.seed, policy.env_config))
    sigmas = [float(s) for s in args.sigmas.split(",")]
    rows = []
    for warmup, stop in itertools.product(
        (int(w) for w in args.warmups.split(",")), (float(s) for s in args.stops.split(","))
    ):
        success = [
            float(
                policy.execute(needle, start, goal, NeedleNoise(s), warmup_frames=warmup, stop_tolerance=stop, seed=1)[
                    "success"
                ].mean()
            )
            for s in sigmas
        ]
        rows.append(
            {"warmup_frames": warmup, "stop_tolerance": stop, "success": success, "mean": float(np.mean(success))}
        )
        print(json.dumps(rows[-1]), flush=True)
    best = max(rows, key=lambda r: r["mean"])
    lines = [
        f"Fused closed loop, shipped policy, {args.n} validation problems (seed {args.seed}); success at frame "
        f"noise {', '.join(map(str, sigmas))} mm.",
        "",
        "| warm-up frames | stop tolerance | " + " | ".join(f"sigma {s}" for s in sigmas) + " | mean |",
        "| ---: | ---: |" + " ---: |" * (len(sigmas) + 1),
    ]
    for r in rows:
        mark = "**" if r is best else ""
        lines.append(
            f"| {r['warmup_frames']} | {r['stop_tolerance']:g} | "
            + " | ".join(f"{v:.3f}" for v in r["success"])
            + f" | {mark}{r['mean']:.3f}{mark} |"
        )
    print("\n".join(lines))
    write_results(args.out, "select", lines, {"rows": rows, "best": best})


if __name__ == "__main__":
    main()
