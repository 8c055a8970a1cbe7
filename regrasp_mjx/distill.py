"""``python -m regrasp_mjx.distill``: DAgger-distil a trained policy (improved by lookahead) into one network.

    python -m regrasp_mjx.distill --teacher runs/fast/policy --out runs/fast/student
    python -m regrasp_mjx.distill --teacher regrasp_mjx/policies/ensemble3 --out runs/student --set hidden=(256,256)

The command line of :func:`regrasp_mjx.workflows.distillation.distill` (its module says what each
iteration prints and logs and what ``OUT`` holds at the end).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from regrasp_mjx.agents.dagger import DistillConfig
from regrasp_mjx.core.atomic import dumps, output_folder_problem
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.config_text import parse_overrides, replace
from regrasp_mjx.core.host_loop import FolderInUse, folder_lock, run_command
from regrasp_mjx.inference.policy import PolicyError, load_policy
from regrasp_mjx.workflows.distillation import DISTILL_OUTPUTS, distill
from regrasp_mjx.world.sampling import DEFAULT_TESTSET, TestsetError, load_testset


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.distill", description=__doc__.splitlines()[0])
    p.add_argument("--teacher", required=True, help="policy folder of the teacher (one network or an ensemble)")
    p.add_argument("--out", required=True, help="output folder (policy, policy_last, distill_log.jsonl, ...)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed (problems, student initialisation)")
    p.add_argument("--testset", default=str(DEFAULT_TESTSET), help="test set .npz reported each iteration")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a DistillConfig field")
    p.add_argument(
        "--clearance-mm",
        type=float,
        default=None,
        help="train the student at this clearance margin (the teacher's shield and lookahead keep it; "
        "default: the teacher's own, usually 0)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace an earlier distillation's outputs in OUT (default: refuse)"
    )
    p.add_argument(
        "--precompile",
        action="store_true",
        help="run one iteration, export and test that student, and stop: every program of this distillation is "
        "then in the compilation cache (an untrained teacher of the teacher's shape will do; writes "
        "precompile.json, not distill_eval.json)",
    )
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    if problem := output_folder_problem(args.out):  # the string as given: Path("") would be "."
        p.error(problem)
    out = Path(args.out)
    if problem := output_folder_problem(out):
        p.error(problem)
    earlier = [name for name in DISTILL_OUTPUTS if (out / name).exists()]
    if earlier and not args.overwrite:
        p.error(
            f"--out {out} holds an earlier distillation ({', '.join(earlier)}); accepted: another --out, or "
            "--overwrite to replace it"
        )
    try:
        cfg = replace(DistillConfig(), seed=args.seed, **parse_overrides(args.set))
        teacher = load_policy(args.teacher)
        if args.clearance_mm is not None:
            teacher = teacher.with_env(clearance_mm=args.clearance_mm)
        testset, _ = load_testset(args.testset)
        with folder_lock(out):
            final = distill(
                teacher, out, cfg, testset, teacher_name=args.teacher, quiet=args.quiet, precompile=args.precompile
            )
    except (ConfigError, PolicyError, TestsetError, FolderInUse) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(dumps({"out": args.out, "test": final["test"]}))
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "a distillation starts anew: run the same command with --overwrite (or another --out)"))
