"""Builds the library of valid initial grasps that a noisy needle pose is checked against.

What the library holds and its distance: :mod:`regrasp_mjx.inference.grasps`.

    python -m regrasp_mjx.grasps --n 1000 --seed 7 --out regrasp_mjx/data/grasps1000.npz
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from regrasp_mjx.core.atomic import dumps, output_file_problem
from regrasp_mjx.core.host_loop import run_command
from regrasp_mjx.inference.grasps import DEFAULT_LIBRARY, GraspLibrary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.grasps", description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1000, help="needle poses of valid grasps (default 1000)")
    p.add_argument("--seed", type=int, default=7, help="PRNG seed (the shipped library: 7)")
    p.add_argument(
        "--out",
        required=True,
        help=f"output .npz (the shipped library is {DEFAULT_LIBRARY.relative_to(DEFAULT_LIBRARY.parents[2])}; "
        "name it to replace it)",
    )
    args = p.parse_args(argv)
    if args.n < 1:
        p.error(f"--n {args.n} is not accepted: an integer >= 1")
    problem = output_file_problem(args.out, ".npz")
    if problem:
        p.error(problem)
    lib = GraspLibrary.make(args.n, args.seed)
    lib.save(args.out)
    fresh = GraspLibrary.make(1000, args.seed + 1)  # how far new draws lie from the library
    d = lib.nearest(fresh.needle)[1]
    print(
        dumps(
            {
                "out": args.out,
                "n": args.n,
                "fresh_nearest_median": float(np.median(d)),
                "fresh_nearest_p99": float(np.percentile(d, 99)),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "nothing was written: run the same command again"))
