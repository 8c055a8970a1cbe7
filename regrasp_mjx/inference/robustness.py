"""How a policy copes with a wrong needle estimate: frame noise, a fixed bias, a clearance margin.

A lab never has the exact needle pose (the paper's real robot fell from 97 % to 73 % on exactly
this). :func:`measure` runs a policy on test-set problems with each step's needle estimate drawn
from :class:`~regrasp_mjx.envs.estimates.NeedleNoise` and judges success and collisions on the true
needle, in one of three modes (:data:`MODES`):

- ``open``: one camera frame, one plan, executed open loop (what the paper's real-robot runs did);
  at no noise this is ``Policy.plan`` exactly;
- ``per-frame``: closed loop, each step acting on that step's frame alone, stopping when that frame
  says the goal is reached (``per-frame-stop``: when it says the pose is within the policy's own
  stop tolerance, ``Policy.closed_loop_defaults``);
- ``fused``: closed loop on the mean of the frames so far, with the policy's own warm-up frames and
  stop tolerance (``Policy.execute``'s defaults; 10 frames and 0.7 for a policy that names none).

A clearance margin ``clearance_mm`` judges (and shields) every pose with that much kept from the
needle and the other tool. :data:`CONDITIONS` are the rows of the robustness table
(:func:`table`): ``python -m regrasp_mjx.evaluate --robustness`` prints it for one policy,
``python -m regrasp_mjx.compare --robustness`` for several (every shipped one by default); its
markdown, the merging of tables run apart and the docs' blocks are
:mod:`regrasp_mjx.inference.robustness_report`'s.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config import ConfigError, is_number, require
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_errors import FPS, CameraErrors
from regrasp_mjx.envs.camera_presets import LITERATURE, PRESETS
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.inference.policy_file import resolve
from regrasp_mjx.robot.robot_errors import OBSERVE, RobotErrors, check_observe
from regrasp_mjx.world.sampling import episode_needles, episode_poses

# mode -> Policy.execute's keywords
MODES: dict[str, dict[str, Any]] = {
    "open": {"frames": "one", "warmup_frames": 1, "stop_tolerance": 1.0},
    "per-frame": {"frames": "each", "warmup_frames": 1, "stop_tolerance": 1.0},
    "per-frame-stop": {"frames": "each", "warmup_frames": 1},
    "fused": {"frames": "fused"},
}
MAX_NOISE_MM = 10.0  # NeedleNoise's range
MAX_CLEARANCE_MM = 1.0  # EnvConfig's range


@dataclasses.dataclass(frozen=True)
class Condition:
    """One row of the robustness table: frame noise ``sigma_mm``, a fixed bias ``bias_mm`` and a
    clearance margin ``clearance_mm`` (each checked: finite, within its range); the robot's errors
    ``robot`` (:class:`~regrasp_mjx.robot.robot_errors.RobotErrors`) and how the policy sees its tools,
    ``observe``; ``modes``: the only modes it is measured in (None: every one asked); ``camera``: a
    real camera's errors (a :class:`~regrasp_mjx.envs.camera_errors.CameraErrors`, or a preset's name,
    read when measured: a fitted preset's file may not exist yet, :meth:`resolved_camera`)."""

    name: str
    sigma_mm: float = 0.0
    bias_mm: float = 0.0
    clearance_mm: float = 0.0
    robot: RobotErrors = RobotErrors()
    observe: str = "camera"
    modes: tuple[str, ...] | None = None
    camera: CameraErrors | str | None = None

    def __post_init__(self) -> None:
        check_condition(self.sigma_mm, self.bias_mm, self.clearance_mm)
        check_observe(self.observe)
        if not isinstance(self.robot, RobotErrors):
            raise ConfigError(f"robot={self.robot!r} is not accepted: a RobotErrors")
        if self.camera is not None:
            if not (isinstance(self.camera, CameraErrors) or isinstance(self.camera, str) and self.camera in PRESETS):
                raise ConfigError(f"camera={self.camera!r} is not accepted: a CameraErrors or one of {tuple(PRESETS)}")
            if self.sigma_mm or self.bias_mm or self.robot.tool_noise_mm:
                raise ConfigError("a camera's errors are not accepted with sigma_mm, bias_mm or tool_noise_mm")

    def resolved_camera(self) -> CameraErrors | None:
        """The camera's errors, a preset's read now (:class:`ConfigError` if its fit file is missing)."""
        return camera_presets.preset(self.camera) if isinstance(self.camera, str) else self.camera


def check_condition(sigma_mm: float, bias_mm: float, clearance_mm: float) -> None:
    """Raises :class:`ConfigError` naming the bad value and what is accepted."""
    for name, v, hi in (
        ("noise_mm", sigma_mm, MAX_NOISE_MM),
        ("bias_mm", bias_mm, MAX_NOISE_MM),
        ("clearance_mm", clearance_mm, MAX_CLEARANCE_MM),
    ):
        require(is_number(v) and 0.0 <= v <= hi, name, v, f"a finite number of millimetres in [0, {hi:g}]")


CONDITIONS = (
    Condition("exact"),
    Condition("sigma 0.1 mm", 0.1),
    Condition("sigma 0.25 mm", 0.25),
    Condition("sigma 0.5 mm", 0.5),
    Condition("bias 0.25 mm + sigma 0.25 mm", 0.25, 0.25),
    Condition("margin 0.1 mm", clearance_mm=0.1),
    Condition("margin 0.2 mm", clearance_mm=0.2),
)
# the robot's errors (issue 45): camera-to-base calibration T mm / R deg of each arm, joint offsets up to
# 0.5 (deg, mm), needle and tool tracking noise 0.25 mm; fused closed loop, each way of seeing the tools
CALIBRATIONS = ((0.0, 0.0), (1.0, 1.0), (3.0, 2.0), (5.0, 3.0), (10.0, 5.0))


def robot_condition_name(calibration_mm: float, calibration_deg: float, observe: str) -> str:
    """A robot-error row's name (the one place it is written: the docs' block finds its rows by it)."""
    if calibration_mm:
        return f"calibration {calibration_mm:g} mm {calibration_deg:g} deg ({observe})"
    return f"tools tracked ({observe})"


ROBOT_CONDITIONS = tuple(
    Condition(
        robot_condition_name(t, r, observe),
        0.25,
        robot=RobotErrors(t, r, 0.5 if t else 0.0, 0.25),
        observe=observe,
        modes=("fused",),
    )
    for t, r in CALIBRATIONS
    for observe in OBSERVE
)
# a real camera's errors (issue 67): the tools seen by the camera, calibration 5 mm / 3 deg, joint offsets
# up to 0.5; white tool noise or a needle bias beyond the 0.25 mm above, then the named presets
CAMERA_ROBOT = RobotErrors(5.0, 3.0, 0.5, 0.0)
CAMERA_ERRORS = {
    "tools 0.5 mm": CameraErrors.of(0.25, 0.0, 0.5),
    "tools 1.0 mm": CameraErrors.of(0.25, 0.0, 1.0),
    "needle bias 0.5 mm": CameraErrors.of(0.25, 0.5, 0.25),
    "needle bias 1.0 mm": CameraErrors.of(0.25, 1.0, 0.25),
    **LITERATURE,
}
CAMERA_CONDITIONS = tuple(
    Condition(f"camera: {name}", robot=CAMERA_ROBOT, modes=("fused",), camera=camera)
    for name, camera in CAMERA_ERRORS.items()
)
ALL_CONDITIONS = CONDITIONS + ROBOT_CONDITIONS + CAMERA_CONDITIONS
# the presets fitted to a measurement (issue 68: "rendered", the learned estimator's errors on rendered
# frames), read from their files when measured: rows only asked for by name (``compare --robustness
# --conditions "camera: rendered"``), not in the default table, so that a table runs before a fit exists
FITTED_CONDITIONS = tuple(
    Condition(f"camera: {name}", robot=CAMERA_ROBOT, modes=("fused",), camera=name) for name in camera_presets.FITTED
)
NAMED_CONDITIONS = ALL_CONDITIONS + FITTED_CONDITIONS  # every row a table may be asked for by name


def program_groups(modes: tuple[str, ...], names: tuple[str, ...] | None = None) -> list[tuple[str, list[str]]]:
    """The rows of a table (``modes`` x the conditions named ``names``, all where None) grouped by
    the compiled program they run: ``[(mode, [condition names])]``, in table order. A group
    compiles one program (a mode, a clearance margin, a way of seeing the tools, joints or not;
    the noise is the program's argument), so groups run side by side compile side by side
    (``python -m regrasp_mjx.recipe``'s report; join their files with ``compare --merge``)."""
    groups: dict[tuple, tuple[str, list[str]]] = {}
    for mode in modes:
        for c in ALL_CONDITIONS if names is None else NAMED_CONDITIONS:
            if (names is not None and c.name not in names) or (c.modes is not None and mode not in c.modes):
                continue
            key = (mode, c.clearance_mm, c.observe, c.robot.joint_offset > 0)
            groups.setdefault(key, (mode, []))[1].append(c.name)
    return list(groups.values())


def measure(
    policy,
    episodes,
    condition: Condition,
    mode: str = "fused",
    seed: int = 0,
    shield: bool = True,
    **options: Any,
) -> dict[str, Any]:
    """Rates of one pass over test-set rows ``episodes`` under ``condition`` in ``mode``, judged on
    the true needle: ``success_rate``, ``collision_rate``, ``time_out_rate``, ``wrong_stop_rate``
    (stopped where the estimate, not the truth, was at the goal) and the mean ``steps`` of the
    successes, over the ``problems_valid`` problems whose start and goal keep the condition's
    clearance margin (all of a test set at no margin: with one, a start already within it fails
    before any step, whatever the policy; ``success_rate_all`` counts those as failures); the
    median of the frames each fused and the mean it looked at holding still. ``options``: more of
    ``Policy.execute``'s keywords (``look_frames``, ``stop_tolerance``: the policy's own without)."""
    if mode not in MODES:
        raise ConfigError(f"mode={mode!r} is not accepted: one of {tuple(MODES)}")
    if condition.clearance_mm != policy.env_config.clearance_mm:
        policy = policy.with_env(clearance_mm=condition.clearance_mm)
    needle, start, goal = episode_poses(episodes)
    camera = condition.resolved_camera()
    noise = None if camera else NeedleNoise(condition.sigma_mm, condition.bias_mm)
    r = policy.execute(
        needle,
        start,
        goal,
        noise,
        shield=shield,
        seed=seed,
        robot=condition.robot,
        observe=condition.observe,
        camera=camera,
        **{**MODES[mode], **options},
        **episode_needles(episodes),
    )
    valid = clear_problems(policy.env_config, episodes)
    ok, collided = r["success"][valid], (r["collision"] | ~r["start_valid"])[valid]
    return {
        "condition": condition.name,
        "mode": mode,
        "sigma_mm": condition.sigma_mm,
        "bias_mm": condition.bias_mm,
        "clearance_mm": condition.clearance_mm,
        **dataclasses.asdict(condition.robot),
        "observe": condition.observe,
        "camera": None if camera is None else dataclasses.asdict(camera),
        "shield": shield,
        "seed": seed,
        "problems": int(valid.size),
        "problems_valid": int(valid.sum()),
        "success_rate": float(ok.mean()),
        "success_rate_all": float(r["success"].mean()),
        "collision_rate": float(collided.mean()),
        "time_out_rate": float(r["time_out"][valid].mean()),
        "wrong_stop_rate": float((r["stopped"][valid] & ~ok & ~collided).mean()),
        "steps": float(r["steps"][valid][ok].mean()) if ok.any() else None,
        "frames_median": float(np.median(r["frames"][valid])) if valid.any() else None,
        "looked_mean": float(r["looked"][valid].mean()) if valid.any() else None,
        # the jaws opened before the first move (inference/jaw_opening.py): rows opened, sweeps not clear
        "opened_rate": float((r["jaw_deg"][valid] > policy.env_config.scene.jaw_angle_deg).mean())
        if valid.any()
        else None,
        "opening_collision_rate": float(r["opening_collision"][valid].mean()) if valid.any() else None,
        # frames taken holding still (the warm-up, the looks, the last): at the endoscope's 30 per second
        "still_s": [float(x) for x in np.percentile((r["frames"] - r["steps"])[valid] / FPS, (50, 95))]
        if valid.any()
        else None,
    }


def clear_problems(env_config, episodes) -> np.ndarray:
    """``[N]`` whether each problem's start and goal keep ``env_config.clearance_mm`` from the
    needle and the other tool (its own needle where the task varies needles), by the collision
    model the environment judges with."""
    rows = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), episodes)
    return np.asarray(_clear_program(env_config)(rows))


@functools.lru_cache(maxsize=8)
def _clear_program(env_config):
    """One compiled check per environment configuration (a table asks 28 times for a few)."""
    env = RegraspEnv(env_config)

    def clear(e):
        start = jnp.min(env.needle_distances(e, e.start_pos, e.start_quat))
        goal = jnp.min(env.needle_distances(e, e.goal_pos, e.goal_quat))
        return jnp.minimum(start, goal) > env.clearance

    return jax.jit(jax.vmap(clear))


def table(
    policy, episodes, modes: tuple[str, ...] = tuple(MODES), seed: int = 0, conditions=CONDITIONS, log=None
) -> list[dict[str, Any]]:
    """:func:`measure` for every condition and mode (shielded); one row each."""
    rows = []
    for condition in conditions:
        for mode in modes:
            if condition.modes is not None and mode not in condition.modes:
                continue
            rows.append(measure(policy, episodes, condition, mode, seed))
            if log is not None:
                r = rows[-1]
                log(
                    f"  {condition.name:<30} {mode:<9} success {r['success_rate']:.3f}  "
                    f"collision {r['collision_rate']:.3f}"
                )
    return rows


def policy_hash(path: str | os.PathLike | None = None) -> str:
    """SHA-256 (first 16 hex digits) of a policy's ``policy.npz`` and ``policy.json``: what a
    table records so that a test can tell when the policy it measured has changed."""
    folder = resolve(path)
    h = hashlib.sha256()
    for name in ("policy.npz", "policy.json"):
        h.update(Path(folder, name).read_bytes())
    return h.hexdigest()[:16]
