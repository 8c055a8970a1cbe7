"""The errors of a real camera (ours; SPEC "Errors of a lab", issue 67): what a lab's endoscope
reports of the needle and of each tool, frame by frame.

Every tracked object (the needle, each tool) is seen at its true pose moved by three errors
(:class:`Tracking`), applied in this order:

- a **bias** fixed for the episode: a shift of exactly ``bias_mm`` in a random direction and a
  rotation of ``deg_per_mm * bias_mm`` degrees about a random axis (a calibration or model error);
- a **drift**, correlated over frames: a first-order autoregressive (AR(1)) process per axis,
  stationary with standard deviation ``drift_mm`` (position, per axis) and ``deg_per_mm * drift_mm``
  degrees (the rotation vector's RMS angle), whose correlation between frames ``k`` apart is
  ``exp(-k / drift_frames)`` (cable stretch and hysteresis: errors that depend on the history);
- **white** noise per frame: ``white_mm`` per axis and a rotation of ``deg_per_mm * white_mm``
  degrees (std) about a random axis (:func:`regrasp_mjx.envs.estimates.frame_estimate`).

A stereo camera sees depth worse than across its image: every position error is stretched along the
camera's viewing axis (:data:`DEPTH_AXIS`, the scene's camera, in the e_g frame) by
:attr:`CameraErrors.depth_factor`, so the sizes above are the errors across the axis.

With ``deg_per_mm = 5``, no drift and ``depth_factor = 1`` this is today's
:class:`~regrasp_mjx.envs.estimates.NeedleNoise` for the needle (bias, white) and ``tool_noise_mm``
for the tools (white), draw for draw (:meth:`CameraErrors.of`). The named models (``lab-good``,
``lab-typical``, ``rendered``) are :mod:`regrasp_mjx.envs.camera_presets`'.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import ConfigError, require_numbers
from regrasp_mjx.world.scene import load_scene

MAX_MM = 10.0  # the largest size accepted for each part (NeedleNoise's range)
MAX_DRIFT_FRAMES = 3000.0  # 100 s at 30 frames per second
MAX_DEPTH_FACTOR = 20.0
DEG_PER_MM = 5.0  # rotation (deg) per mm of position error: the success test's scale (today's models)
FPS = 30.0  # the endoscope's frame rate: what a frame spent looking costs in time


@dataclasses.dataclass(frozen=True)
class Tracking:
    """One tracked object's errors (see the module docstring): ``bias_mm`` fixed per episode,
    ``drift_mm`` correlated over ``drift_frames`` frames, ``white_mm`` per frame, each rotation
    ``deg_per_mm`` degrees per mm of its position error."""

    bias_mm: float = 0.0
    drift_mm: float = 0.0
    drift_frames: float = 30.0
    white_mm: float = 0.0
    deg_per_mm: float = DEG_PER_MM

    def __post_init__(self) -> None:
        sizes = ("bias_mm", "drift_mm", "white_mm")
        require_numbers(self, sizes, lambda v: 0.0 <= v <= MAX_MM, f"a finite number of mm in [0, {MAX_MM:g}]")
        require_numbers(self, ("drift_frames",), lambda v: 1.0 <= v <= MAX_DRIFT_FRAMES, "frames in [1, 3000]")
        require_numbers(self, ("deg_per_mm",), lambda v: 0.0 <= v <= 30.0, "degrees per mm in [0, 30]")

    def rms_mm(self, depth_factor: float = 1.0) -> float:
        """The position error's root mean square over episodes and frames, all three axes together,
        stretched by ``depth_factor`` along the camera axis: ``sqrt((2 + k^2) / 3)`` times
        ``sqrt(bias^2 + 3 drift^2 + 3 white^2)`` (each part isotropic before the stretch)."""
        stretch = math.sqrt((2.0 + depth_factor**2) / 3.0)
        return stretch * math.sqrt(self.bias_mm**2 + 3.0 * self.drift_mm**2 + 3.0 * self.white_mm**2)

    def fused_sd_mm(self, frames: int) -> float:
        """The standard deviation per axis (mm, across the camera axis) of the mean of ``frames``
        consecutive frames' errors, less the bias (which no number of frames removes)."""
        return float(jnp.sqrt(fused_variance(jnp.float32(max(int(frames), 1)), jnp.asarray(self.numbers()))))

    def numbers(self) -> tuple[float, ...]:
        return (self.bias_mm, self.drift_mm, self.drift_frames, self.white_mm, self.deg_per_mm)


@dataclasses.dataclass(frozen=True)
class CameraErrors:
    """The errors of the camera's ``needle`` estimate and of its view of each of the two ``tools``
    (each a :class:`Tracking`, drawn independently per tool), position errors ``depth_factor``
    times larger along the camera's viewing axis than across it."""

    needle: Tracking = Tracking()
    tools: Tracking = Tracking()
    depth_factor: float = 1.0

    def __post_init__(self) -> None:
        for name in ("needle", "tools"):
            if not isinstance(getattr(self, name), Tracking):
                raise ConfigError(f"{name}={getattr(self, name)!r} is not accepted: a Tracking")
        require_numbers(self, ("depth_factor",), lambda v: 1.0 <= v <= MAX_DEPTH_FACTOR, "a number in [1, 20]")

    @classmethod
    def of(cls, sigma_mm: float = 0.0, bias_mm: float = 0.0, tool_noise_mm: float = 0.0) -> CameraErrors:
        """Today's model: the needle's frame noise and bias (``NeedleNoise``), white tool noise."""
        return cls(Tracking(bias_mm=bias_mm, white_mm=sigma_mm), Tracking(white_mm=tool_noise_mm))

    def relative_sd_mm(self, frames: int) -> float:
        """The standard deviation (mm) along the camera axis of the needle's position relative to the
        regrasping tool in a view of ``frames`` fused frames: the needle's and both tools' errors (the
        needle is placed relative to the grasping tool), each bias's per-axis spread ``b / sqrt(3)``
        included (fixed per episode, but unknown), stretched by the depth factor: :func:`view_sd_mm`
        without the rotations (levers of 0)."""
        n, p = jnp.float32(max(int(frames), 1)), np.asarray(self.numbers(), np.float32)
        return float(view_sd_mm(n, p[:5], p[5:10], p[10], 0.0, 0.0, jnp.zeros((1, 3)))[0])

    def numbers(self) -> tuple[float, ...]:
        """The jitted programs' argument: the needle's, then the tools' numbers, then the depth factor."""
        return self.needle.numbers() + self.tools.numbers() + (self.depth_factor,)


@functools.lru_cache(maxsize=1)
def depth_axis() -> np.ndarray:
    """The scene camera's viewing axis in the e_g frame (a unit 3-vector): MuJoCo's cameras look
    along their frame's -z."""
    model = load_scene().model
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.cam_quat[0])
    axis = -rot.reshape(3, 3)[:, 2]
    return axis / np.linalg.norm(axis)


# ---- the draws, in the jitted programs ------------------------------------------------------------
# Sizes may be traced scalars or ``[B]`` rows; ``depth`` is ``(k, d)``: the depth factor and the unit
# axis [3], or None for none (no stretch computed: today's draws exactly). Drift states are [B, 6]:
# position (m) and rotation vector (rad).


def stretch(error: jax.Array, depth) -> jax.Array:
    """Position errors ``[..., 3]`` stretched by ``k`` along the unit axis ``d`` (``depth = (k, d)``;
    exactly ``error`` where ``k`` is 1 or ``depth`` is None)."""
    if depth is None:
        return error
    k, d = depth
    return jnp.where(k == 1.0, error, error + (k - 1.0) * jnp.sum(error * d, -1, keepdims=True) * d)


def rotate(axis_key: jax.Array, angle: jax.Array, quat: jax.Array) -> jax.Array:
    """Quaternions ``[..., 4]`` turned by ``angle`` about a random axis (``axis_key``)."""
    axis = jax.random.normal(axis_key, quat.shape[:-1] + (3,))
    axis = axis / jnp.linalg.norm(axis, axis=-1, keepdims=True)
    return geometry.quat_mul(geometry.quat_from_rotvec(axis * angle[..., None]), quat)


def _size(x, shape) -> jax.Array:
    return jnp.broadcast_to(jnp.asarray(x, jnp.result_type(float)), shape)


def biased(key: jax.Array, pose: jax.Array, bias_mm, deg_per_mm=DEG_PER_MM, depth=None) -> jax.Array:
    """Poses ``[..., 7]`` moved by an episode's bias (``key`` fixed per episode): a shift of exactly
    ``bias_mm`` in a random direction (stretched by ``depth``), a rotation of ``deg_per_mm bias_mm``
    degrees about a random axis."""
    bias_mm = _size(bias_mm, pose.shape[:-1])
    k_dir, k_axis = jax.random.split(key)
    direction = jax.random.normal(k_dir, pose.shape[:-1] + (3,))
    direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
    angle = jnp.radians(deg_per_mm * bias_mm)
    pos = pose[..., :3] + stretch(bias_mm[..., None] * 1e-3 * direction, depth)
    return jnp.concatenate([pos, rotate(k_axis, angle, pose[..., 3:])], axis=-1)


def white(key: jax.Array, pose: jax.Array, white_mm, deg_per_mm=DEG_PER_MM, depth=None) -> jax.Array:
    """One frame's zero-mean Gaussian noise on poses ``[..., 7]``: ``white_mm`` per axis (stretched
    by ``depth``), a rotation of ``deg_per_mm white_mm`` degrees (std) about a random axis."""
    white_mm = _size(white_mm, pose.shape[:-1])
    k_pos, k_angle, k_axis = jax.random.split(key, 3)
    noise = white_mm[..., None] * 1e-3 * jax.random.normal(k_pos, pose.shape[:-1] + (3,))
    angle = jnp.radians(deg_per_mm * white_mm) * jax.random.normal(k_angle, pose.shape[:-1])
    return jnp.concatenate([pose[..., :3] + stretch(noise, depth), rotate(k_axis, angle, pose[..., 3:])], -1)


def fused_variance(n: jax.Array, p: jax.Array) -> jax.Array:
    """The variance per axis (mm^2, across the camera axis) of the mean of ``n`` consecutive frames'
    errors under a tracking's numbers ``p`` (:meth:`Tracking.numbers`), less the bias: the white
    part's ``white^2 / n`` and the drift's ``drift^2 (1 / n^2) sum_{i, j} rho^|i - j|``."""
    rho = jnp.exp(-1.0 / p[2])
    pairs = n * (1.0 + rho) / (1.0 - rho) - 2.0 * rho * (1.0 - rho**n) / (1.0 - rho) ** 2
    return p[3] ** 2 / n + p[1] ** 2 * pairs / n**2


def _drift_scale(p: jax.Array) -> jax.Array:
    """The drift's stationary standard deviation per component ``[6]`` of a tracking's numbers
    ``p`` (:meth:`Tracking.numbers`): position (m), rotation vector (rad; the RMS angle over the
    square root of 3 per axis)."""
    pos = p[1] * 1e-3
    rot = jnp.radians(p[4] * p[1]) / jnp.sqrt(3.0)
    return jnp.concatenate([jnp.full(3, pos), jnp.full(3, rot)])


def drift_start(key: jax.Array, b: int, p: jax.Array) -> jax.Array:
    """The drift's state ``[B, 6]`` at the first frame: a draw from its stationary distribution."""
    return jax.random.normal(key, (b, 6)) * _drift_scale(p)


def drift_next(key: jax.Array, state: jax.Array, p: jax.Array) -> jax.Array:
    """The drift one frame later: ``rho x + sqrt(1 - rho^2) sd n``, ``rho = exp(-1 / drift_frames)``."""
    rho = jnp.exp(-1.0 / p[2])
    return rho * state + jnp.sqrt(1.0 - rho**2) * _drift_scale(p) * jax.random.normal(key, state.shape)


def frame(key: jax.Array, pose: jax.Array, drift: jax.Array, p: jax.Array, depth) -> jax.Array:
    """One frame of objects at ``pose`` ``[B, 7]`` (bias already in) under a tracking's numbers
    ``p``: the drift at this frame (``drift`` ``[B, 6]``), then this frame's white noise (``key``)."""
    turned = geometry.quat_mul(geometry.quat_from_rotvec(drift[:, 3:]), pose[:, 3:])
    out = jnp.where(p[1] > 0, jnp.concatenate([pose[:, :3] + stretch(drift[:, :3], depth), turned], -1), pose)
    return white(key, out, p[3], p[4], depth)


def seen(keys, pose: jax.Array, drift: jax.Array, p: jax.Array, depth) -> jax.Array:
    """One frame of objects truly at ``pose`` ``[B, 7]`` under a tracking's numbers ``p``: the
    bias (``keys[0]``, fixed per episode), then :func:`frame` (``keys[1]``, this frame's)."""
    return frame(keys[1], biased(keys[0], pose, p[0], p[4], depth), drift, p, depth)


def no_errors(p: jax.Array) -> jax.Array:
    """Whether a tracking's numbers ``p`` have no bias, drift or white noise (its view is exact)."""
    return (p[0] == 0) & (p[1] == 0) & (p[3] == 0)


IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def in_grasping_frame(grasping: jax.Array, needle: jax.Array, regrasping: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The needle and the regrasping tool ``[B, 7]`` (e_g frame) as seen from the seen grasping tool."""
    inv = geometry.inverse((grasping[:, :3], grasping[:, 3:]))
    seen_needle = jnp.concatenate(geometry.compose(inv, (needle[:, :3], needle[:, 3:])), -1)
    return seen_needle, jnp.concatenate(geometry.compose(inv, (regrasping[:, :3], regrasping[:, 3:])), -1)


def camera_frame(keys, needle: jax.Array, ee: jax.Array, drifts: jax.Array, p: jax.Array, depth):
    """One camera frame of both tools: the needle estimate ``[B, 7]`` (its own errors already in) and
    the regrasping tool truly at ``ee``, each tool seen under the tools' numbers ``p`` (``keys``
    ``[2, 2]``: the grasping tool's, the regrasping tool's; ``drifts`` ``[B, 12]`` their drift
    states), both expressed in the seen grasping tool's frame: the grasping tool's error moves the
    whole view. Exactly ``needle`` and ``ee`` where the tools' sizes are all zero."""
    b = needle.shape[0]
    identity = jnp.broadcast_to(jnp.asarray(IDENTITY, needle.dtype), (b, 7))
    grasping = seen(keys[0], identity, drifts[:, :6], p, depth)
    regrasping = seen(keys[1], ee, drifts[:, 6:], p, depth)
    seen_needle, seen_ee = in_grasping_frame(grasping, needle, regrasping)
    exact = no_errors(p)
    return jnp.where(exact, needle, seen_needle), jnp.where(exact, ee, seen_ee)


def view_sd_mm(n, pn, pt, depth_factor, reach, needle_radius, ee_seen_pos) -> jax.Array:
    """``[B]`` the standard deviation [mm] of where the view puts a jaw point relative to the needle and
    the grasping tool after ``n`` fused frames (``pn``, ``pt``: the needle's and the tools'
    :meth:`~regrasp_mjx.envs.camera_errors.Tracking.numbers`): each tracked object's position error
    (its bias's per-axis spread, unknown though fixed, and the fused rest) stretched by the depth
    factor, and its rotation error (``deg_per_mm`` per mm of it) at its lever: the regrasping tool's
    at the jaws' ``reach`` [m], the needle's at its radius [m] (about its centre), the grasping tool's
    at the regrasping tool's distance from it [m] (the frame the view is in)."""

    def part(p, lever_m):
        var = p[0] ** 2 / 3.0 + fused_variance(n, p)
        return (depth_factor**2 + (jnp.radians(p[4]) * lever_m * 1e3) ** 2) * var

    lever_g = jnp.linalg.norm(ee_seen_pos, axis=-1)
    return jnp.sqrt(part(pn, needle_radius) + part(pt, reach) + part(pt, lever_g))
