"""``python -m regrasp_mjx.train``: DDPG+BC with mixed exploration, evaluation, checkpoints, export.

    python -m regrasp_mjx.train --preset smoke --out runs/smoke
    python -m regrasp_mjx.train --preset fast --exploration mixed --out runs/fast --seed 1
    python -m regrasp_mjx.train --preset paper --out runs/paper --set batch_size=512 --set env.horizon=80
    python -m regrasp_mjx.train --preset fast --out runs/fast --resume
    python -m regrasp_mjx.train --preset fast --exploration targeted --seeds 3 --out runs/targeted

The command line of :class:`regrasp_mjx.workflows.trainer.Run` (the host loop; the jitted learner is
:mod:`regrasp_mjx.agents.ddpg_bc.learner`). Python runs only between iterations: the planner exchange
(failed episodes out with probability E_T, demonstrations in when they are ready), and per epoch the
test-set evaluation, the log line, TensorBoard and JSONL logs and an atomic checkpoint. At the end the
policy is exported (``OUT/policy/policy.npz`` + ``policy.json``) and evaluated on the test set
(``OUT/final_eval.json``).
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import sys
import warnings
from pathlib import Path
from typing import Any

import jax

from regrasp_mjx.agents.ddpg_bc.config import EXPLORATION, LEARNERS, PRESETS, grow_with_devices, make_config
from regrasp_mjx.agents.ddpg_bc.placement import Placement
from regrasp_mjx.core import distributed, gpu_memory
from regrasp_mjx.core.atomic import dumps, output_folder_problem
from regrasp_mjx.core.config import TASKS, ConfigError
from regrasp_mjx.core.config_text import parse_overrides
from regrasp_mjx.core.host_loop import FolderInUse, folder_in_use, folder_lock, run_command
from regrasp_mjx.planning.episodes import DemosError
from regrasp_mjx.workflows.preflight import before_the_work, run_outputs
from regrasp_mjx.workflows.trainer import Run
from regrasp_mjx.world.sampling import DEFAULT_TESTSET, TestsetError


def check_out(out: Path, resume: bool, overwrite: bool) -> str | None:
    """Why ``out`` cannot take this run (None when it can); checked before any work."""
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file; accepted: a folder (new, empty or an earlier run's with --resume)"
    if problem := output_folder_problem(out) or folder_in_use(out):  # a live run's folder: said first
        return problem
    if resume and overwrite:
        return "--resume and --overwrite are not accepted together: continue the run or clear it"
    earlier = run_outputs(out)
    if resume and not earlier:
        return (
            f"--resume: {out} holds no run to continue; accepted: an earlier run's folder (drop --resume to start anew)"
        )
    if earlier and not resume and not overwrite:
        names = ", ".join(e.name for e in earlier[:5]) + (", ..." if len(earlier) > 5 else "")
        return (
            f"--out {out} holds an earlier run ({names}); accepted: --resume to continue it, --overwrite to clear "
            "it and start anew, or another --out"
        )
    return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.train", description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="smoke", choices=sorted(PRESETS), help="scale preset (default smoke)")
    p.add_argument(
        "--exploration",
        default="mixed",
        help=f"Table I setting, one of {', '.join(sorted(EXPLORATION))} (default mixed); several, comma-separated, "
        "train side by side in one program (OUT/SETTING/seedS)",
    )
    p.add_argument(
        "--learner",
        default="ours",
        choices=LEARNERS,
        help="ours (default: Gaussian exploration floor, twin critics, target smoothing, actor EMA, cosine LR) "
        "or paper (SPEC's DDPG+BC as the paper ran it)",
    )
    p.add_argument(
        "--task",
        default=None,
        choices=sorted(TASKS),
        help="problem distribution: paper (one goal grasp and needle) or general (any goal grasp in range, needles "
        "of 4-12 mm; the observation holds both); default: the preset's (general for --preset general, else paper)",
    )
    p.add_argument("--out", required=True, help="run folder: logs, checkpoint, demos, exported policy")
    p.add_argument("--seed", type=int, default=None, help="PRNG seed (default: the preset's, 0)")
    p.add_argument("--seeds", type=int, default=None, help="train seeds SEED..SEED+N-1 together as one vmapped program")
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        help="use this many local GPUs (0 = all; default 1), shared as --shard says",
    )
    p.add_argument(
        "--shard",
        default=None,
        choices=("auto", "members", "envs"),
        help="members: whole seeds/settings per GPU, no communication; envs: data parallel (environments, "
        "buffer and batches split, gradients averaged); auto (default): members when they divide evenly",
    )
    p.add_argument(
        "--grow-batch",
        action="store_true",
        help="data parallel with weak scaling: the preset's environments, batch, buffer and demo chunk are "
        "each GPU's share (global sizes grow with --devices) and both learning rates scale by sqrt(devices)",
    )
    p.add_argument(
        "--gpu-memory",
        default=None,
        metavar="FRACTION|grow",
        help="share of the GPU to pre-allocate (e.g. 0.45 for each of two runs on one GPU) or 'grow' "
        "(allocate as needed); default: JAX's 75 %%, or 'grow' when another process runs on the GPU",
    )
    p.add_argument(
        "--distributed",
        action="store_true",
        help="join a run of several processes (hosts) through jax.distributed: the coordinator, process "
        "count and index come from the flags below or are detected (SLURM, Open MPI, JAX_COORDINATOR_ADDRESS)",
    )
    p.add_argument(
        "--coordinator", default=None, metavar="HOST:PORT", help="process 0's address (implies --distributed)"
    )
    p.add_argument("--num-processes", type=int, default=None, help="processes in the run (with --coordinator)")
    p.add_argument("--process-id", type=int, default=None, help="this process's index, 0..N-1 (with --coordinator)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint")
    p.add_argument(
        "--overwrite", action="store_true", help="clear an earlier run's outputs in OUT first (default: refuse them)"
    )
    p.add_argument("--demos", default=None, help="a demonstration folder (default: build OUT/demos)")
    p.add_argument(
        "--testset", default=str(DEFAULT_TESTSET), help="evaluation test set: paper300, general1000 or an .npz file"
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field, dotted for nested ones (repeatable)",
    )
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    if problem := output_folder_problem(args.out):  # the string as given: Path("") would be "."
        p.error(problem)
    out = Path(args.out)
    problem = check_out(out, args.resume, args.overwrite)
    if problem:
        p.error(problem)
    if problem := distributed.options_problem(args.distributed, args.coordinator, args.num_processes, args.process_id):
        p.error(problem)
    try:
        overrides = parse_overrides(args.set)
        if args.seed is not None:
            overrides["seed"] = args.seed
        if args.seeds is not None:
            overrides["num_seeds"] = args.seeds
        if args.devices is not None:
            overrides["devices"] = args.devices
        if args.shard is not None:
            overrides["shard"] = args.shard
        if args.task is not None:
            overrides["env.task"] = TASKS[args.task]
        cfg = make_config(args.preset, args.exploration, args.learner, **overrides)
        if problem := before_the_work(cfg, args.testset, args.demos):
            p.error(problem)
        gpu_memory.configure(gpu_memory.parse_setting(args.gpu_memory))  # before JAX starts a GPU client
        if args.distributed or args.coordinator:
            distributed.initialize(args.coordinator, args.num_processes, args.process_id)
        if args.grow_batch:
            cfg = grow_with_devices(cfg, cfg.devices or len(jax.devices()))
        Placement.check_devices(cfg)  # before the demonstrations: --devices more than JAX sees is refused
        with contextlib.ExitStack() as held:
            if distributed.is_main():  # one run per folder: held from before an --overwrite clears it
                held.enter_context(folder_lock(out))
            if args.overwrite and distributed.is_main():
                for entry in run_outputs(out):
                    shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
            out.mkdir(parents=True, exist_ok=True)
            if jax.default_backend() == "cpu" and args.preset != "smoke":
                warnings.warn("training on the CPU: no GPU is visible to JAX; this preset expects one", stacklevel=1)
            run = Run(cfg, out, Path(args.demos) if args.demos else None, Path(args.testset), args.quiet)
            final = run.train(resume=args.resume)
    except (ConfigError, DemosError, TestsetError, FolderInUse) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except jax.errors.JaxRuntimeError as err:
        if not gpu_memory.is_out_of_memory(err):
            raise
        print(f"error: {gpu_memory.out_of_memory_message(cfg)}\n({str(err).splitlines()[0]})", file=sys.stderr)
        return 3

    def summary(g: dict[str, Any]) -> dict[str, Any]:
        out = {"policy": g["policy"], "test": g["test"]}
        if "student" in g:
            out["student"] = {"policy": g["student"]["student"], "test": g["student"]["test"]}
        return out

    if not distributed.is_main():
        return 0  # process 0 reports
    if "settings" in final:
        print(dumps({"out": str(out), "settings": {k: summary(g) for k, g in final["settings"].items()}}))
    else:
        print(dumps({"out": str(out), **summary(final)}))
    return 0


if __name__ == "__main__":
    sys.exit(
        run_command(
            main,
            "run the same command with --resume to continue from the last checkpoint (or its demonstrations)",
        )
    )
