"""The closed loop's host entry points (``Policy.closed_loop_step``, ``Policy.execute``): checked
numpy inputs in, the jitted programs of :mod:`regrasp_mjx.inference.closed_loop` (built once per
network shape and setting) run, numpy arrays out."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import numpy as np

from regrasp_mjx.core.config import ConfigError, is_number
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_errors import CameraErrors
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.inference import jaw_opening
from regrasp_mjx.inference.closed_loop import FRAMES, MAX_LOOK, make_executor, make_stepper, tolerances
from regrasp_mjx.inference.planner import members_apply
from regrasp_mjx.inference.plans import auto_engine, checked_goals
from regrasp_mjx.inference.queries import PoseError, TaskSpec, batch_poses, check_poses
from regrasp_mjx.robot.robot_errors import RobotErrors, check_observe


def _estimate_inputs(policy: Any, needle: Any, ee_name: str, ee: Any, goal: Any, spec: TaskSpec):
    """Checked ``[B, 7]`` needle, end-effector and goal poses (the goal grasp on ``needle`` by
    default), each needle's radii ``[B, 2]`` (m) and whether one query was given."""
    (needle, ee), single = batch_poses(needle=needle, **{ee_name: ee})
    grasp, radii = policy.task_ranges.resolve(len(needle), spec)
    return needle, ee, checked_goals(needle, goal, grasp, radii), radii, single


def _program(
    policy,
    kind,
    shield,
    frames="fused",
    clearance_mm=0.0,
    stop=1.0,
    warmup=1,
    observe="camera",
    joints=False,
    look=0,
    jaw_sigmas=1.0,
):
    """The jitted executor (``kind="execute"``) or stepper of a setting, built once per network shape."""

    def build():
        env = RegraspEnv(policy.env_config)
        config = policy.env_config
        margin = max(config.jaw_open_margin_mm, clearance_mm)  # the jaws' room keeps the shield's clearance
        guard = env
        if clearance_mm:  # the shield's own environment, keeping the clearance
            guard = RegraspEnv(dataclasses.replace(config, clearance_mm=clearance_mm, jaw_open_margin_mm=margin))
        apply = members_apply(policy.hidden)
        if kind == "execute":
            return make_executor(env, apply, shield, frames, guard, warmup, observe, joints, look, jaw_sigmas)
        return make_stepper(guard, apply, shield, stop)

    key = (kind, shield, frames, clearance_mm, stop, warmup, observe, joints, look)
    return policy.program(key + ((jaw_sigmas,) if policy.env_config.jaw_open_deg else ()), build)


def closed_loop_step(
    policy: Any,
    needle: Any,
    ee: Any,
    goal: Any = None,
    t: int = 0,
    shield: bool = True,
    clearance_mm: float = 0.0,
    stop_tolerance: float | None = None,
    jaw_deg: Any = None,
    **task: Any,
) -> tuple:
    """One closed-loop step from the current estimates (e_g frame, 7-vectors or ``[B, 7]``): the
    latest (or fused) needle estimate and the regrasping end-effector's current pose. Returns
    ``(action, next_ee, at_goal)``: the action, the pose to command next, and whether the
    estimate says the goal is already reached (then stop: the action is zero, ``next_ee`` is
    ``ee``). ``t`` is the step index (it seeds the shield's alternatives, as in a plan); the
    shield checks the alternatives against the estimated needle, keeping ``clearance_mm`` from it
    (room for the estimate's error). ``at_goal`` holds within ``stop_tolerance`` of the success
    tolerances (None: the policy's own, ``Policy.closed_loop_defaults``), as in :func:`execute`.
    ``task``: the goal grasp and needle keywords (:class:`~regrasp_mjx.inference.queries.TaskSpec`). One
    query on the CPU (no ``clearance_mm``, ``t`` within the horizon) takes the lean numba step
    (:meth:`regrasp_mjx.inference.lean_planner.LeanPlanner.step`), anything else the jitted JAX program.

    Jaws that open on the way (a policy with ``EnvConfig.jaw_open_deg``, issue 67): the step is
    stateless but for the jaws' opening, which a step may change and the robot carries out, so the
    opening goes in and comes out. ``jaw_deg`` (one value, or one per row) is where the jaws are
    now: the scene's opening at the start, then what the last step returned. The step opens them as
    the environment does, on the estimate: before this step's motion where they are at the scene's
    opening and the sweep to ``jaw_open_deg`` keeps ``jaw_open_margin_mm`` (or ``clearance_mm``,
    if larger) from the estimated needle and grasping tool; the action, the shield and the motion's
    collision test take the jaws there. Such a policy's step returns a fourth value, ``jaw_deg``:
    the opening to command before moving to ``next_ee`` (a row at its goal keeps its own). Both ends
    are explicit on purpose: a loop that dropped the opening would have the next motion tested with
    the jaws at the scene's opening while the robot holds them open, so ``jaw_deg`` is required for
    such a policy and the three-value unpacking of its result fails loudly. A policy whose jaws stay
    is called as before (``jaw_deg`` None or its scene's opening; three values out)."""
    stop_tolerance = policy.closed_loop_defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
    if not (is_number(stop_tolerance) and 0.0 < stop_tolerance <= 1.0):
        raise ConfigError(f"stop_tolerance={stop_tolerance!r} is not accepted: a fraction in (0, 1]")
    if not (isinstance(t, (int, np.integer)) and not isinstance(t, bool) and t >= 0):
        raise ConfigError(f"t={t!r} is not accepted: the step index, an integer >= 0")
    if not (is_number(clearance_mm) and 0.0 <= clearance_mm <= 1.0):
        raise ConfigError(f"clearance_mm={clearance_mm!r} is not accepted: a finite number of mm in [0, 1]")
    spec = TaskSpec.of(task)
    (needle, ee), single = batch_poses(needle=needle, ee=ee)
    opens = policy.env_config.jaw_open_deg is not None
    # each row's opening now; None: the scene's (a policy whose jaws stay, called as before: no work)
    jaws = None if jaw_deg is None and not opens else _jaws_now(policy, jaw_deg, len(needle))
    if single and not clearance_mm and 0 <= t < policy.env_config.horizon and auto_engine(1, policy) == "lean":
        # one query on the CPU: the lean numba step, its default goal made by the compiled code (the
        # JAX program below stays the reference)
        lean = policy.lean(shield)
        grasp, radii = policy.task_ranges.resolve(1, spec)
        goal = lean.goal(needle[0], grasp[0], radii[0, 0]) if goal is None else check_poses("goal", goal)
        if goal.shape != (7,):
            raise PoseError(f"goal {goal.shape} and needle (7,) poses differ in batch size")
        opened = jaws is not None and bool(jaws[0] > policy.env_config.scene.jaw_angle_deg)
        at_goal, nxt, a, jaw = lean.step(needle[0], ee[0], goal, radii[0], int(t), float(stop_tolerance), opened)
        return (a, nxt, np.bool_(at_goal)) + ((np.float64(jaw),) if opens else ())
    # one query stays one: the arrays are batched by now, so the flag is the caller's, found above
    needle, ee, goal, radii, _ = _estimate_inputs(policy, needle, "ee", ee, goal, spec)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    step = _program(policy, "step", shield, clearance_mm=float(clearance_mm), stop=float(stop_tolerance))
    jaws = np.full(len(needle), policy.env_config.scene.jaw_angle_deg) if jaws is None else jaws
    out = jax.device_get(step(f32(needle), f32(ee), f32(goal), np.int32(t), f32(radii), f32(jaws)))
    a, nxt, done, jaw = (np.asarray(x, np.float64) for x in out)
    out = (a, nxt, done.astype(bool)) + ((jaw,) if opens else ())
    return tuple(x[0] for x in out) if single else out


def _jaws_now(policy: Any, jaw_deg: Any, rows: int) -> np.ndarray:
    """Each row's jaw opening now [deg], ``[rows]``, as :func:`closed_loop_step` takes it: one of the
    two openings a row of the environment has (the scene's; ``jaw_open_deg`` once opened)."""
    config = policy.env_config
    base, wide = float(config.scene.jaw_angle_deg), config.jaw_open_deg
    if wide is None:
        if jaw_deg is None or (is_number(jaw_deg) and jaw_deg == base):
            return np.full(rows, base, np.float64)
        raise ConfigError(
            f"jaw_deg={jaw_deg!r} is not accepted: this policy's jaws stay at its scene's {base} deg (None or {base})"
        )
    wide = float(wide)
    accepted = f"the jaws' opening now, {base} (the scene's, at the start) or {wide} (opened), one value or one per row"
    if jaw_deg is None:
        raise ConfigError(
            f"jaw_deg is required for a policy whose jaws open on the way (to {wide} deg): {accepted}; "
            "pass back the jaw_deg each step returns"
        )
    values = np.asarray(jaw_deg)
    ok = values.dtype.kind in "iuf" and values.shape in ((), (rows,))
    if not (ok and np.isin(values, (base, wide)).all()):
        raise ConfigError(f"jaw_deg={jaw_deg!r} is not accepted: {accepted} ({rows} rows)")
    return np.broadcast_to(values.astype(np.float64), (rows,))


def execute(
    policy: Any,
    needle: Any,
    start: Any,
    goal: Any = None,
    noise: NeedleNoise | None = None,
    frames: str = "fused",
    shield: bool = True,
    seed: int = 0,
    clearance_mm: float = 0.0,
    stop_tolerance: float | None = None,
    warmup_frames: int | None = None,
    robot: RobotErrors | None = None,
    observe: str = "camera",
    camera: CameraErrors | str | None = None,
    look_frames: int | None = None,
    jaw_deg: float | None = None,
    jaw_sigmas: float | None = None,
    **task: Any,
) -> dict[str, np.ndarray]:
    """Simulates regrasping under needle-pose noise on true needle, start and goal poses ``[B, 7]``
    (e_g frame): each step the policy acts on an estimate of the needle (``noise``, a
    :class:`~regrasp_mjx.envs.estimates.NeedleNoise`; default none) and stops when the estimate says the
    goal is reached; success and collisions are judged on the true needle. ``frames``: ``"fused"``
    (the mean of the frames so far, the default), ``"each"`` (that step's frame alone) or ``"one"``
    (the first frame for the whole episode: a plan made once, executed open loop).
    ``clearance_mm``: the shield keeps this clearance from the estimated needle (room for the
    estimate's error); ``stop_tolerance``: stop when the estimate is within this fraction of the
    success tolerances (below 1: room for the estimate's error at the goal); ``warmup_frames``:
    with ``"fused"``, frames fused before the first step (the tool holds still meanwhile). Their
    defaults (None) are the policy's own (``Policy.closed_loop_defaults``: chosen for it on
    validation problems of their own seed by experiments/closed_loop_select.py; 10 frames and 0.7
    where its file names none); ``frames="one", stop_tolerance=1`` with no noise reproduces a plan
    exactly. ``robot``: the robot's errors (a :class:`~regrasp_mjx.robot.robot_errors.RobotErrors`:
    camera-to-base calibration, joint offsets, tool tracking noise; default none) and
    ``observe``: how the policy sees its tools through them, ``"camera"`` (tools and needle from
    the camera, the default) or ``"kinematic"`` (tools from the joint readings). ``camera``: the
    errors of a real camera instead of ``noise`` and the robot's ``tool_noise_mm`` (a
    :class:`~regrasp_mjx.envs.camera_errors.CameraErrors` or a preset's name: bias, drift and white
    noise for the needle and each tool, depth worse than across the image). ``look_frames``: with
    ``"fused"``, the frames a row holds still to fuse before its last moves and before it declares
    the goal reached, at most, while its estimate is too uncertain to stop on (:func:`make_executor`'s
    ``look``; None: the policy's own, else 0: no looking).
    ``jaw_deg``: the widest the loop may open the regrasping jaws to before the first move, where the
    view leaves ``jaw_sigmas`` times its known error (:meth:`CameraErrors.relative_sd_mm` after the
    warm-up) around the opening sweep (:mod:`regrasp_mjx.inference.jaw_opening`; None: the policy's
    own, else its scene's opening: no opening).
    ``task``: the goal grasp and needle keywords (a general policy's ranges). Returns
    numpy arrays per row: ``success``, ``collision``, ``time_out``, ``stopped``, ``steps``,
    ``frames`` (fused: warm-up, one a step, looked), ``looked``, ``start_valid``, ``start_seen``,
    ``jaw_deg`` (the row's opening), ``opening_collision`` (its sweep not proved clear on the
    truth: counted in ``collision``), ``poses``."""
    noise = NeedleNoise() if noise is None else noise
    robot = RobotErrors() if robot is None else robot
    if not isinstance(noise, NeedleNoise):
        raise ConfigError(f"noise={noise!r} is not accepted: a NeedleNoise")
    if not isinstance(robot, RobotErrors):
        raise ConfigError(f"robot={robot!r} is not accepted: a RobotErrors")
    check_observe(observe)
    if frames not in FRAMES:
        raise ConfigError(f"frames={frames!r} is not accepted: one of {FRAMES}")
    if camera is None:
        camera = CameraErrors.of(noise.sigma_mm, noise.bias_mm, robot.tool_noise_mm)
    else:
        camera = camera_presets.preset(camera) if isinstance(camera, str) else camera
        if not isinstance(camera, CameraErrors):
            raise ConfigError(
                f"camera={camera!r} is not accepted: a CameraErrors or one of {tuple(camera_presets.PRESETS)}"
            )
        if noise != NeedleNoise() or robot.tool_noise_mm:
            raise ConfigError(
                "camera= is not accepted with noise= or robot.tool_noise_mm: the camera's errors hold both"
            )
    if look_frames is None:  # the policy's own, where it fuses frames
        look_frames = policy.closed_loop_defaults["look_frames"] if frames == "fused" else 0
    ok = isinstance(look_frames, int) and not isinstance(look_frames, bool) and 0 <= look_frames <= MAX_LOOK
    if not ok or (look_frames and frames != "fused"):
        raise ConfigError(
            f"look_frames={look_frames!r} is not accepted: an integer in [0, {MAX_LOOK}], and only with fused frames"
        )
    defaults = policy.closed_loop_defaults
    stop_tolerance = defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
    warmup_frames = defaults["warmup_frames"] if warmup_frames is None else warmup_frames
    if not (isinstance(warmup_frames, int) and warmup_frames >= 1):
        raise ConfigError(f"warmup_frames={warmup_frames!r} is not accepted: an integer >= 1")
    if not (math.isfinite(stop_tolerance) and 0.0 < stop_tolerance <= 1.0):
        raise ConfigError(f"stop_tolerance={stop_tolerance!r} is not accepted: a fraction in (0, 1]")
    jaw_deg, jaw_sigmas = jaw_opening.check(policy, jaw_deg, jaw_sigmas)
    on_the_way = policy.env_config.jaw_open_deg is not None
    if on_the_way and jaw_deg > policy.env_config.scene.jaw_angle_deg:
        raise ConfigError(
            f"jaw_deg={jaw_deg!r} is not accepted for a policy whose jaws open on the way (to "
            f"{policy.env_config.jaw_open_deg} deg): None, or its scene's {policy.env_config.scene.jaw_angle_deg}"
        )
    needle, start, goal, radii, _ = _estimate_inputs(policy, needle, "start", start, goal, TaskSpec.of(task))
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    warmup = int(warmup_frames) if frames == "fused" else 1
    joints = robot.joint_offset > 0
    key = jax.random.PRNGKey(seed)
    errors = tuple(f32(v) for v in (robot.calibration_mm, robot.calibration_deg, robot.joint_offset))
    stop = tuple(f32(x) for x in tolerances(policy.env_config, float(stop_tolerance)))

    def one_pass(p) -> dict[str, np.ndarray]:
        # the stop tolerance is an argument (1.0 in the key)
        setting = (frames, float(clearance_mm), 1.0, warmup, observe, joints, look_frames, jaw_sigmas)
        run = _program(p, "execute", shield, *setting)
        out = run(f32(needle), f32(start), f32(goal), key, f32(camera.numbers()), f32(radii), errors, stop)
        return {k: np.asarray(v) for k, v in jax.device_get(out).items()}

    if on_the_way:  # the loop opens the jaws on the way itself (make_executor)
        return one_pass(policy)
    margin_mm = jaw_sigmas * camera.relative_sd_mm(warmup)
    return jaw_opening.execute_opened(one_pass, policy, needle, start, radii, jaw_deg, margin_mm)
