"""``python -m regrasp_mjx.testset``: writes a test set of regrasping problems.

Row i is the problem that ``RegraspEnv.reset`` draws from key i of ``jax.random.split(PRNGKey(seed),
n)``, so a test set is the environment's own start distribution, colliding starts and goals
redrawn. The file's keys, shapes and units are listed in docs/environment.md and in its ``meta`` JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from regrasp_mjx.core.atomic import dumps, output_file_problem
from regrasp_mjx.core.config import TASKS, ConfigError, EnvConfig, SceneConfig
from regrasp_mjx.core.host_loop import run_command
from regrasp_mjx.world.sampling import load_testset, save_testset
from regrasp_mjx.world.testsets import MAX_PROBLEMS, make_testset, versions


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m regrasp_mjx.testset", description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=300, help=f"number of problems (default 300, at most {MAX_PROBLEMS})")
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed (default 0)")
    parser.add_argument("--out", required=True, help="output .npz path (written atomically)")
    parser.add_argument(
        "--jaw-angle-deg",
        type=float,
        default=SceneConfig.jaw_angle_deg,
        help="angle between the open regrasping jaws, degrees (default 20)",
    )
    parser.add_argument(
        "--task",
        default="paper",
        choices=sorted(TASKS),
        help="problem distribution: paper (default) or general (any goal grasp in range, needles of 4-12 mm)",
    )
    args = parser.parse_args(argv)
    if not 1 <= args.n <= MAX_PROBLEMS:
        parser.error(f"--n {args.n} is not accepted: an integer >= 1 and at most {MAX_PROBLEMS}")
    problem = output_file_problem(args.out, ".npz")
    if problem:
        parser.error(problem)
    try:
        config = EnvConfig(scene=SceneConfig(jaw_angle_deg=args.jaw_angle_deg), task=TASKS[args.task])
        t0 = time.perf_counter()
        episodes = make_testset(args.n, args.seed, config)
    except ConfigError as err:
        parser.error(str(err))
    meta = {
        "seed": args.seed,
        "scene": dataclasses.asdict(config.scene),
        "task": dataclasses.asdict(config.task),
        "versions": versions(),
        "units": "metres, radians, quaternions wxyz; every pose in the grasping end-effector frame",
    }
    path = save_testset(args.out, episodes, meta)
    load_testset(path)  # read back: what we wrote must pass our own validation
    gap = np.linalg.norm(episodes.goal_pos - episodes.start_pos, axis=-1) * 1e3
    print(
        dumps(
            {
                "out": str(path),
                "n": args.n,
                "seed": args.seed,
                "seconds": round(time.perf_counter() - t0, 2),
                "start_to_goal_mm": {
                    "mean": round(float(gap.mean()), 3),
                    "min": round(float(gap.min()), 3),
                    "max": round(float(gap.max()), 3),
                },
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "nothing was written: run the same command again"))
