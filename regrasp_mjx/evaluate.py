"""``python -m regrasp_mjx.evaluate``: a policy on a test set, as the paper's Tables I and II count.

    python -m regrasp_mjx.evaluate                                  # the shipped policy, paper300
    python -m regrasp_mjx.evaluate --policy runs/fast/policy --testset my.npz --json

Plans go through the collision shield (``Policy.plan``'s default; ``--no-shield`` rolls the bare
policy out, as training evaluates it). Success, collision and time-out rates of one pass over the
test set (no retries); planning time of
one query at a time (compiled and warmed up first; the wall time from the poses to the whole
trajectory, numpy in and out; on the CPU ``Policy.plan``'s lean numba path, on a GPU the JAX
program), mean and median; batched throughput (``batch_size`` queries in one call, or
in equal chunks of at most
:data:`~regrasp_mjx.inference.testset_plans.BATCH_CHUNK` one after the other, repeated, plans/s);
path length in mm over the successes; starts that collide before any step
(``invalid_starts``) and starts implausibly far from their needle (``far_starts``: beyond
``policy.START_WARN_MM``, usually poses in millimetres or another frame), counted and warned about.
Planning runs on JAX's default device:
``JAX_PLATFORMS=cpu taskset -c 0 python -m regrasp_mjx.evaluate`` times one CPU core.
``--agreement`` instead checks the two engines of ``Policy.plan`` against each other on every
problem (:func:`~regrasp_mjx.inference.testset_plans.engine_agreement`).
"""

from __future__ import annotations

import argparse
import sys

import jax

from regrasp_mjx.core.atomic import dumps
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.host_loop import run_command
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_presets import PRESETS
from regrasp_mjx.inference import robustness, robustness_report, testset_report
from regrasp_mjx.inference.closed_loop import MAX_LOOK
from regrasp_mjx.inference.policy import DEFAULT_POLICY, PolicyError, load_policy, shipped_policies
from regrasp_mjx.inference.queries import PoseError
from regrasp_mjx.inference.robustness import check_condition
from regrasp_mjx.inference.testset_plans import BATCH_CHUNK, engine_agreement, evaluate
from regrasp_mjx.robot.robot_errors import (
    MAX_CALIBRATION_DEG,
    MAX_CALIBRATION_MM,
    MAX_JOINT_OFFSET,
    MAX_TOOL_NOISE_MM,
    OBSERVE,
    RobotErrors,
)
from regrasp_mjx.world.sampling import TESTSETS, TestsetError, load_testset


def _agreement(policy, episodes, name: str, args: argparse.Namespace) -> int:
    """``--agreement``: :func:`engine_agreement` on the test set, printed; 1 when a verdict differs."""
    r = engine_agreement(policy, episodes, shield=not args.no_shield)
    out = testset_report.agreement_row(r, name, args.testset, not args.no_shield)
    print(dumps(out) if args.json else testset_report.agreement_text(out))
    return 1 if out["verdicts_differ"] else 0


def _check_args(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Every numeric option checked before any work: ``p.error`` (one line, exit 2) names the bad value."""
    for name, lo in (("queries", 0), ("repeats", 0), ("batch_size", 1)):
        v = getattr(args, name)
        if v is not None and v < lo:
            p.error(f"--{name.replace('_', '-')} {v} is not accepted: an integer >= {lo}")
    try:
        check_condition(args.noise_mm, args.bias_mm, args.clearance_mm or 0.0)
    except ConfigError as err:
        p.error(
            str(err)
            .replace("noise_mm=", "--noise-mm ")
            .replace("bias_mm=", "--bias-mm ")
            .replace("clearance_mm=", "--clearance-mm ")
        )
    try:
        args.robot = RobotErrors(args.calibration_mm, args.calibration_deg, args.joint_offset, args.tool_noise_mm)
    except ConfigError as err:
        message = str(err).replace("=", " ", 1).replace("calibration_", "--calibration-")
        p.error(message.replace("joint_", "--joint-").replace("tool_noise_", "--tool-noise-"))
    robot = args.robot != RobotErrors() or args.camera is not None
    if args.camera is not None and (args.noise_mm or args.bias_mm or args.tool_noise_mm):
        p.error(f"--camera {args.camera} is not accepted with --noise-mm, --bias-mm or --tool-noise-mm: it sets them")
    if args.camera is not None:  # a fitted preset's file read now: a missing one says how to make it
        try:
            args.camera_errors = camera_presets.preset(args.camera)
        except ConfigError as err:
            p.error(f"--camera {args.camera}: {err}")
    if args.look_frames is not None and (
        not args.closed_loop or args.per_frame or not 0 <= args.look_frames <= MAX_LOOK
    ):
        p.error(
            f"--look-frames {args.look_frames} is not accepted: an integer in [0, {MAX_LOOK}], with --closed-loop "
            "(fused frames, not --per-frame)"
        )
    if (args.jaw_deg is not None or args.jaw_sigmas is not None) and not args.closed_loop:
        p.error("--jaw-deg and --jaw-sigmas are not accepted without --closed-loop")
    if args.agreement and (args.robustness or args.noise_mm or args.bias_mm or args.closed_loop or robot):
        p.error("--agreement is not accepted with --robustness, --noise-mm, --bias-mm, --closed-loop or a robot error")
    if args.per_frame and not args.closed_loop:
        p.error("--per-frame is not accepted without --closed-loop")
    if args.robustness and (
        args.noise_mm or args.bias_mm or args.closed_loop or args.clearance_mm is not None or robot
    ):
        p.error(
            "--robustness runs its own conditions; it is not accepted with --noise-mm, --bias-mm, --clearance-mm, "
            "--closed-loop or a robot error"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.evaluate", description=__doc__.splitlines()[0])
    p.add_argument(
        "--policy",
        default=None,
        help=f"policy folder, or a shipped name ({', '.join(shipped_policies())}; "
        f"default: the shipped one, {DEFAULT_POLICY.name})",
    )
    p.add_argument(
        "--testset",
        default="paper300",
        help=f"test set: a shipped name ({', '.join(TESTSETS)}) or an .npz file (default paper300)",
    )
    p.add_argument("--queries", type=int, default=None, help="time only the first N single queries (0: none)")
    p.add_argument("--repeats", type=int, default=5, help="repeats of the batched call (0: no throughput timing)")
    p.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help=f"queries of the throughput batch (test set repeated; default its size); more than {BATCH_CHUNK} run as "
        "equal chunks of at most that many, one after the other",
    )
    p.add_argument("--no-shield", action="store_true", help="roll the bare policy out (no collision shield)")
    p.add_argument(
        "--clearance-mm",
        type=float,
        default=None,
        help="collision margin in [0, 1] mm: a pose collides closer than this to the needle or the other tool "
        "(default: the policy's own, 0 for the shipped ones)",
    )
    p.add_argument(
        "--noise-mm",
        type=float,
        default=0.0,
        help="needle-estimate noise per camera frame, mm per axis (rotation 5 x as many degrees), in [0, 10]; "
        "success and collisions are judged on the true needle",
    )
    p.add_argument(
        "--bias-mm",
        type=float,
        default=0.0,
        help="needle-estimate bias fixed per episode, mm (5 x as many degrees), in [0, 10]",
    )
    p.add_argument(
        "--closed-loop",
        action="store_true",
        help="re-plan every step from the fused estimate (default with noise: plan once from one frame, open loop)",
    )
    p.add_argument("--per-frame", action="store_true", help="with --closed-loop: act on each frame alone, no fusing")
    p.add_argument(
        "--look-frames",
        type=int,
        default=None,
        help="with --closed-loop: before the last moves and before stopping, hold still and fuse up to this many "
        "frames while the estimate is too uncertain to stop on (default: the policy's own; 0: never)",
    )
    p.add_argument(
        "--jaw-deg",
        type=float,
        default=None,
        help="with --closed-loop: open the regrasping jaws before the first move, as wide as this (deg, up to the "
        "LND's 80) where the view leaves room (default: the policy's own; its scene's opening: never)",
    )
    p.add_argument(
        "--jaw-sigmas",
        type=float,
        default=None,
        help="with --jaw-deg: the room the opening keeps, in standard deviations of the view's known error "
        "(default: the policy's own, 2)",
    )
    robot = p.add_argument_group(
        "the robot's errors (each fixed per episode and independent per arm; judged on the true poses)"
    )
    robot.add_argument(
        "--calibration-mm",
        type=float,
        default=0.0,
        help=f"camera-to-base calibration error of each arm: a shift of this many mm in a random direction, "
        f"in [0, {MAX_CALIBRATION_MM:g}]",
    )
    robot.add_argument(
        "--calibration-deg",
        type=float,
        default=0.0,
        help=f"and a rotation of this many degrees about a random axis through the arm's remote centre, "
        f"in [0, {MAX_CALIBRATION_DEG:g}]",
    )
    robot.add_argument(
        "--joint-offset",
        type=float,
        default=0.0,
        help=f"each PSM joint reads off by up to this (degrees; mm for the insertion), in [0, {MAX_JOINT_OFFSET:g}]",
    )
    robot.add_argument(
        "--tool-noise-mm",
        type=float,
        default=0.0,
        help=f"the camera's tracking noise of each tool per frame, mm per axis (5 x as many degrees), "
        f"in [0, {MAX_TOOL_NOISE_MM:g}]",
    )
    robot.add_argument(
        "--camera",
        choices=tuple(PRESETS),
        default=None,
        help="a real camera's errors by name (they replace the needle and tool noise options): for the needle and "
        "each tool a bias per episode, a drift over frames and white noise, depth worse than across "
        "(docs/inference.md; rendered: fitted to the learned estimator's errors, docs/rendering.md)",
    )
    robot.add_argument(
        "--observe",
        choices=OBSERVE,
        default="camera",
        help="how the policy sees its tools: camera (tools and needle from the camera: a calibration error "
        "cancels; the default) or kinematic (tools from the joint readings through the calibration)",
    )
    p.add_argument(
        "--robustness",
        action="store_true",
        help="the robustness table: exact, noise 0.1/0.25/0.5 mm, bias 0.25 + noise 0.25 mm, margins 0.1/0.2 mm; "
        "open loop, per-frame and fused closed loop",
    )
    p.add_argument(
        "--agreement",
        action="store_true",
        help="plan every problem one at a time on the lean CPU path and as one batch on the JAX path, and compare "
        "(exit 1 when a verdict differs)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the needle-estimate noise")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    _check_args(p, args)
    try:
        policy = load_policy(args.policy)
        if args.clearance_mm is not None:
            policy = policy.with_env(clearance_mm=args.clearance_mm)
        episodes, _ = load_testset(args.testset)
    except (PolicyError, TestsetError, ConfigError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        return _run(policy, episodes, args.policy or DEFAULT_POLICY.name, args)
    except PoseError as err:  # a test set of needles or goal grasps the policy was not trained for
        print(f"error: --testset {args.testset}: {err}", file=sys.stderr)
        return 2
    except jax.errors.JaxRuntimeError as err:
        if "RESOURCE_EXHAUSTED" not in str(err) and "out of memory" not in str(err).lower():
            raise
        size = f"--batch-size {args.batch_size} " if args.batch_size else ""
        print(
            f"error: {size}does not fit in the memory of {jax.devices()[0].device_kind}; accepted: a smaller "
            "--batch-size (65536 fits one H100)",
            file=sys.stderr,
        )
        return 2


def _run(policy, episodes, name: str, args: argparse.Namespace) -> int:
    """What ``main`` was asked, on a loaded policy and test set."""
    if args.robustness:
        rows = robustness.table(policy, episodes, seed=args.seed, log=None if args.json else print)
        if args.json:
            print(
                dumps(
                    {
                        "policy": name,
                        "policy_hash": robustness.policy_hash(args.policy),
                        "testset": args.testset,
                        "rows": rows,
                    }
                )
            )
        else:
            print(f"{name} on {args.testset}, shielded, judged on the true needle:")
            print("\n".join(robustness_report.markdown(rows)))
        return 0
    if args.agreement:
        return _agreement(policy, episodes, name, args)
    if args.noise_mm or args.bias_mm or args.closed_loop or args.robot != RobotErrors() or args.camera:
        mode = ("per-frame" if args.per_frame else "fused") if args.closed_loop else "open"
        camera = None if args.camera is None else args.camera_errors
        condition = robustness.Condition(
            "given",
            args.noise_mm,
            args.bias_mm,
            policy.env_config.clearance_mm,
            args.robot,
            args.observe,
            camera=camera,
        )
        closed_loop = {"look_frames": args.look_frames, "jaw_deg": args.jaw_deg, "jaw_sigmas": args.jaw_sigmas}
        r = robustness.measure(
            policy,
            episodes,
            condition,
            mode,
            args.seed,
            shield=not args.no_shield,
            **{k: v for k, v in closed_loop.items() if v is not None},
        )
        r.update(policy=name, testset=args.testset)
        print(dumps(r) if args.json else testset_report.condition_text(r, mode, args.camera))
        return 0
    r = evaluate(policy, episodes, args.queries, args.repeats, args.batch_size, shield=not args.no_shield)
    r["policy"] = name
    r["clearance_mm"] = policy.env_config.clearance_mm
    r["testset"] = args.testset
    print(dumps(r) if args.json else testset_report.evaluation_text(r, timed_batch=bool(args.repeats)))
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "nothing was written: run the same command again"))
