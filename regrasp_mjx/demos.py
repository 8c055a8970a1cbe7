"""``python -m regrasp_mjx.demos``: a demonstration set from an OMPL planner, on all cores.

The command line of :func:`regrasp_mjx.planning.demonstrations.build` (its module says how problems
are drawn, planned, resumed and replayed, and what ``DIR`` holds).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from regrasp_mjx.core.atomic import output_folder_problem
from regrasp_mjx.core.config import TASKS, ConfigError, EnvConfig, SceneConfig
from regrasp_mjx.core.config_text import parse_overrides, replace
from regrasp_mjx.core.host_loop import FolderInUse, folder_lock, run_command
from regrasp_mjx.planning.demonstrations import build, build_settings
from regrasp_mjx.planning.episodes import DemosError
from regrasp_mjx.planning.ompl_planner import CHECKERS, PLANNERS


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.demos", description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=9900, help="demonstrations wanted (default 9900, the paper's)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="planner processes (default: all cores)")
    p.add_argument("--out", required=True, help="output folder (resumed when it exists)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--planner", default="BITstar", choices=PLANNERS)
    p.add_argument("--direction", default="reverse", choices=("forward", "reverse"))
    p.add_argument("--budget-s", type=float, default=10.0, help="planning time limit per problem")
    p.add_argument(
        "--checker",
        default="mujoco",
        choices=CHECKERS,
        help="collision checker: mujoco (CPU MuJoCo) or lean (the same capsule pairs compiled, a motion per call; "
        "the same verdicts, faster)",
    )
    p.add_argument("--timeout-s", type=float, default=None, help="kill a plan after this long (default 3x budget + 30)")
    p.add_argument("--jaw-angle-deg", type=float, default=20.0)
    p.add_argument(
        "--task",
        default="paper",
        choices=sorted(TASKS),
        help="problem distribution: paper (the paper's goal grasp and needle) or general (any goal grasp in "
        "range, needles of 4-12 mm radius)",
    )
    p.add_argument(
        "--env",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an EnvConfig field for the problems and the replay, e.g. scene.needle_radius_mm=4.0 (repeatable; "
        "a run trained on these demonstrations must use the same scene and task)",
    )
    p.add_argument("--replay-batch", type=int, default=256)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if args.n < 1 or args.workers < 1:
        p.error("--n and --workers must be >= 1")
    if problem := output_folder_problem(args.out):
        p.error(problem)
    try:
        base = EnvConfig(scene=SceneConfig(jaw_angle_deg=args.jaw_angle_deg), task=TASKS[args.task])
        env = replace(base, **parse_overrides(args.env))
        build_settings(  # before the folder is made: a refusal leaves nothing behind
            args.n,
            args.workers,
            args.planner,
            args.direction,
            args.budget_s,
            args.checker,
            args.timeout_s,
            args.replay_batch,
        )
        with folder_lock(Path(args.out)):  # one build per folder
            build(
                args.n,
                args.out,
                seed=args.seed,
                workers=args.workers,
                planner=args.planner,
                direction=args.direction,
                budget_s=args.budget_s,
                checker=args.checker,
                timeout_s=args.timeout_s,
                replay_batch=args.replay_batch,
                quiet=args.quiet,
                env=env,
            )
    except (ConfigError, DemosError, ValueError, FolderInUse) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "run the same command again to resume: the plans made so far are kept"))
