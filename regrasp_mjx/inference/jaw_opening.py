"""The regrasping jaw opened by the loop (issue 67): before the first move, as wide as the view says
it may (below), or on the way for a policy trained to (``EnvConfig.jaw_open_deg``: the executor's
margin :func:`regrasp_mjx.envs.camera_errors.view_sd_mm` and its outputs :func:`outputs`, at the end).

At the 20 degree opening the policies are trained with, the goal grasp leaves the wire 0.27-0.54 mm
of room: a camera's millimetre errors bring the jaws onto it. Wider jaws leave more, but a start
drawn for 20 degrees may have the needle or the other tool beside a jaw. So the loop decides per
problem, once, on the view the first move is made on (after the warm-up frames): it opens the jaws
to the widest of a ladder of openings (:func:`rungs`, from the scene's up to ``jaw_deg``) whose
opening sweep, the tool holding still, keeps a margin from the viewed needle and grasping tool
(``jaw_sigmas`` times the view's known error, ``CameraErrors.relative_sd_mm``)
at every check point (:func:`regrasp_mjx.world.jaw.opening_fn`: proved clear between them too), and
plans the whole motion with the jaws there (the policy, the shield and the continuous test in the
scene of that opening). The verdict is the truth's: a sweep that the true poses do not prove clear
is a collision. Rows whose view leaves no room keep the scene's opening, so no valid start is refused.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config import ConfigError, is_number
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.world import jaw
from regrasp_mjx.world.sampling import Episode
from regrasp_mjx.world.scene import load_scene

RUNG_DEG = 10.0  # the ladder's step: each rung a rung's scene (one more executor pass where chosen)


def rungs(base_deg: float, widest_deg: float, step_deg: float = RUNG_DEG) -> np.ndarray:
    """The openings the loop chooses from: the scene's, every ``step_deg`` above it, and ``widest_deg``."""
    inner = np.arange(base_deg + step_deg, widest_deg - 1e-9, step_deg)
    return np.unique(np.round(np.concatenate([[base_deg], inner, [widest_deg]]), 9))


def check(policy: Any, jaw_deg: Any, sigmas: Any) -> tuple[float, float]:
    """``(jaw_deg, sigmas)`` checked against the policy's scene, None the policy's own."""
    defaults = policy.closed_loop_defaults
    base = policy.env_config.scene.jaw_angle_deg
    jaw_deg = defaults["jaw_deg"] if jaw_deg is None else jaw_deg
    jaw_deg = base if jaw_deg is None else jaw_deg
    sigmas = defaults["jaw_sigmas"] if sigmas is None else sigmas
    if not (is_number(jaw_deg) and base <= jaw_deg <= jaw.JAW_MAX_DEG):
        raise ConfigError(
            f"jaw_deg={jaw_deg!r} is not accepted: the widest opening, degrees from the policy's "
            f"{base} to the LND's {jaw.JAW_MAX_DEG}"
        )
    if not (is_number(sigmas) and 0.0 <= sigmas <= 10.0):
        raise ConfigError(f"jaw_sigmas={sigmas!r} is not accepted: a number of standard deviations in [0, 10]")
    return float(jaw_deg), float(sigmas)


def _clearance(scene, widest: float, poses: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`regrasp_mjx.world.jaw.opening_fn` on ``[B, 14]`` needle and tool poses."""
    angles, fn = jaw.opening_fn(scene, widest)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    p = f32(poses)
    return angles, np.asarray(fn(p[:, :3], p[:, 3:7], p[:, 7:10], p[:, 10:], f32(radii[:, 0]), f32(radii[:, 1])))


def choose(policy: Any, seen: np.ndarray, radii: np.ndarray, jaw_deg: float, margin_mm: float) -> np.ndarray:
    """Each row's opening [deg]: the widest rung whose sweep keeps ``margin_mm`` from the view
    ``seen`` ``[B, 14]`` (needle, tool; e_g); ``radii`` ``[B, 2]`` each needle's radius and wire [m]."""
    scene = load_scene(policy.env_config.scene)
    ladder = rungs(scene.config.jaw_angle_deg, jaw_deg)
    if len(ladder) == 1:
        return np.full(len(seen), ladder[0])
    angles, clearance = _clearance(scene, jaw_deg, seen, radii)
    return jaw.widest_clear(angles, clearance, ladder, margin_mm * 1e-3)


def proved_clear(policy: Any, opening: np.ndarray, needle, start, radii, jaw_deg: float) -> np.ndarray:
    """Whether each row's sweep to ``opening`` is proved clear on the true poses (the scene's own
    opening: True, the start as given), by :func:`choose`'s check (the same compiled program, the
    check points up to the first at or past each row's opening, as :func:`~regrasp_mjx.world.jaw.widest_clear`
    reads them)."""
    base = policy.env_config.scene.jaw_angle_deg
    ok = np.ones(len(opening), bool)
    if not np.any(opening > base):
        return ok
    scene = load_scene(policy.env_config.scene)
    angles, clearance = _clearance(scene, jaw_deg, np.concatenate([needle, start], -1), radii)
    upto = np.arange(len(angles))[None, :] <= np.searchsorted(angles, opening - 1e-9)[:, None]
    return np.all((clearance >= 0.0) | ~upto, axis=1)


def opened(policy: Any, deg: float) -> Any:
    """The policy planning with its regrasping jaws at ``deg``."""
    if math.isclose(deg, policy.env_config.scene.jaw_angle_deg, abs_tol=1e-9):
        return policy
    return policy.with_env(**{"scene.jaw_angle_deg": float(deg)})


def execute_opened(
    run: Callable[[Any], dict[str, np.ndarray]],
    policy: Any,
    needle: np.ndarray,
    start: np.ndarray,
    radii: np.ndarray,
    jaw_deg: float,
    margin_mm: float,
) -> dict[str, np.ndarray]:
    """``run(policy)`` (one executor pass, :func:`regrasp_mjx.inference.closed_loop_host.execute`'s)
    with each row's jaws opened as the view at its first move allows: the scene's pass decides (its
    ``start_seen``; the same frames in every pass), one more pass for each wider rung any row
    chose, each row's outcome taken from its own; ``jaw_deg`` (each row's opening) and
    ``opening_collision`` (a sweep the true poses do not prove clear: a collision, not a success)
    added; ``start_valid`` the problem's own (the scene's opening)."""
    out = run(policy)
    base = policy.env_config.scene.jaw_angle_deg
    chosen = choose(policy, out["start_seen"], radii, jaw_deg, margin_mm)
    for deg in np.unique(chosen[chosen > base]):
        rows = chosen == deg
        wide = run(opened(policy, float(deg)))
        for k, v in wide.items():
            if k != "start_valid":
                out[k] = np.where(rows.reshape((-1,) + (1,) * (v.ndim - 1)), v, out[k])
    hit = ~proved_clear(policy, chosen, needle, start, radii, jaw_deg)
    out["opening_collision"] = hit
    out["collision"] = out["collision"] | hit
    out["success"] = out["success"] & ~hit
    out["time_out"] = out["time_out"] & ~hit
    out["jaw_deg"] = chosen.astype(np.float32)
    return out


# ---- jaws that open on the way (EnvConfig.jaw_open_deg): the executor's margin and outputs
def outputs(env: RegraspEnv, state, poses: jax.Array, traced: jax.Array, steps: jax.Array) -> dict:
    """The executor's jaw outputs from the opening traced after each step ``[horizon + 1, B]``: the
    last, the step they opened before (-1: never) and whether that sweep is not proved clear on the
    true poses (the environment's own check, at the pose the step started from)."""
    base = env.config.scene.jaw_angle_deg
    b = poses.shape[0]
    if not env.opens:
        return {
            "jaw_deg": jnp.full(b, base, jnp.float32),
            "opened_at": jnp.full(b, -1, jnp.int32),
            "opening_collision": jnp.zeros(b, bool),
        }
    live = jnp.arange(traced.shape[0])[:, None] < steps[None, :]
    wide = live & (traced > base)
    opened_at = jnp.where(jnp.any(wide, 0), jnp.argmax(wide, 0), -1).astype(jnp.int32)
    last = jnp.where(opened_at >= 0, jnp.float32(env.config.jaw_open_deg), jnp.float32(base))
    at = jnp.take_along_axis(poses, jnp.maximum(opened_at, 0)[:, None, None], axis=1)[:, 0]
    es = state.pipeline_state.replace(ee_pos=at[:, :3], ee_quat=at[:, 3:], jaw_deg=jnp.full(b, base, jnp.float32))
    room = jax.vmap(env.opening_room, in_axes=(0, None))(es, env.config.jaw_open_deg)
    return {"jaw_deg": last, "opened_at": opened_at, "opening_collision": (opened_at >= 0) & (room < env.clearance)}


def opening_steps(policy: Any, needle: np.ndarray, poses: np.ndarray, steps: np.ndarray, radii=None) -> np.ndarray:
    """For plans of a policy whose jaws open on the way (``Policy.plan``'s exact rollouts: ``needle``
    ``[B, 7]``, ``poses`` ``[B, T + 1, 7]``, ``steps`` ``[B]``; ``radii`` ``[B, 2]`` for a task that
    draws needles): the step each plan's jaws open before (-1: never), found as the environment finds
    it: the first pose of the plan whose opening sweep keeps ``jaw_open_margin_mm``
    (:meth:`~regrasp_mjx.envs.env.RegraspEnv.opening_room`). What a robot commands: open the jaws to
    ``jaw_open_deg`` at that pose, then go on."""
    config = policy.env_config
    if config.jaw_open_deg is None:
        raise ConfigError("opening_steps takes a policy whose jaws open on the way (EnvConfig.jaw_open_deg set)")
    room = opening_room(policy, needle, poses, radii)
    n = room.shape[1]
    ok = (room >= config.jaw_open_margin_mm * 1e-3) & (np.arange(n)[None, :] < np.asarray(steps)[:, None])
    return np.where(ok.any(axis=1), ok.argmax(axis=1), -1)


def opening_room(policy: Any, needle: np.ndarray, poses: np.ndarray, radii=None) -> np.ndarray:
    """The room [m] opening the jaws from the scene's opening to ``jaw_open_deg`` leaves at each pose
    ``poses`` ``[B, N, 7]`` of ``needle`` ``[B, 7]`` (e_g; ``radii`` ``[B, 2]`` m for a task that draws
    needles), the tool holding still: :meth:`~regrasp_mjx.envs.env.RegraspEnv.opening_room`, jitted
    once per policy, ``[B, N]`` float32."""
    room_of = policy.program(("opening_room",), lambda: _room_program(RegraspEnv(policy.env_config)))
    f32 = lambda x: None if x is None else np.asarray(x, np.float32)  # noqa: E731
    return np.asarray(room_of(f32(needle), f32(poses), f32(radii)))


def _room_program(env: RegraspEnv) -> Callable:
    """``room(weights, needle [B, 7], poses [B, N, 7], radii) -> [B, N]``, jitted: the room to open the
    jaws to the policy's opening at every pose of every plan (the weights bound by ``Policy.program``,
    unused)."""

    def room(_weights, needle, poses, radii):
        b, n = poses.shape[:2]
        tile = lambda x: None if x is None else jnp.repeat(x, n, axis=0)  # noqa: E731
        flat = poses.reshape(b * n, 7)
        es = jax.vmap(env.reset_from)(Episode.from_poses(tile(needle), flat, flat, tile(radii))).pipeline_state
        return jax.vmap(env.opening_room, in_axes=(0, None))(es, env.config.jaw_open_deg).reshape(b, n)

    return jax.jit(room)
