"""Errors of a lab's robot (ours; SPEC "Errors of a lab"), beside the needle estimate's
(:class:`~regrasp_mjx.envs.estimates.NeedleNoise`), and the two ways a policy can see its tools.

The model (:class:`RobotErrors`), each error fixed per episode and independent per arm unless said:

- **camera-to-base calibration**: the transform from the camera to each PSM's base (its remote
  centre of motion, RCM) that the lab uses is off by a shift of exactly ``calibration_mm`` in a
  random direction and a rotation of ``calibration_deg`` about a random axis through the RCM: the
  lab believes the base at ``B eps`` where it is at ``B``. About 100 mm from the RCM, a degree
  moves the tool by a further 1.7 mm.
- **PSM joint offsets**: each joint of each arm reads off by a fixed amount drawn from
  ``U[-joint_offset, joint_offset]`` (degrees for the rotary joints, mm for the insertion): the arm
  is at ``FK(q + o)`` when it reads ``q`` (:mod:`regrasp_mjx.robot.dvrk`'s kinematics).
- **tool tracking**: where the camera sees a tool, each frame's pose of it is the true pose moved
  by Gaussian noise of ``tool_noise_mm`` per axis and ``5 tool_noise_mm`` degrees about a random
  axis (the needle estimate's scale), independently per frame.

Where the arms stand: each tool starts at the PSM's neutral joint configuration (outer joints and
wrist at zero, the pitch axis 120 mm from the RCM, :func:`regrasp_mjx.robot.dvrk.base_behind`): the
grasping arm at its tool, the regrasping arm at the episode's start pose.

How a policy sees its tools (:data:`OBSERVE`):

- ``kinematic``: each tool's pose from its joint readings through the believed base, the needle
  from the camera; the ego-centric state then carries both arms' calibration and joint errors
  (the needle relative to the regrasping jaws is off by the regrasping arm's error).
- ``camera``: both tools and the needle from the camera, so the ego-centric state holds only poses
  relative to each other in one image (SPEC "Deployment"): a camera-to-base error of either arm
  cancels, and tracking noise enters instead. Fused over frames like the needle (the regrasping
  tool moves between frames by what its kinematics say, a motion in its own frame that no
  camera-to-base error changes).

In both, an action is carried out relative to the arm's current pose: the policy's motion in its
view, ``X' -> (dp, dq) o X'``, is the tool-frame motion ``D = X'^-1 ((dp, dq) o X')``, commanded as
``FK(q) D`` in the arm's own base frame (the same command a lab sends through its believed
calibration). No calibration error enters the execution; a joint offset does (the arm reaches
``FK(IK(FK(q) D) + o)``), and so does the view's error of the tool's orientation (the motion is
turned by it). Success and collisions are always judged on the true poses.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from flax import struct

from regrasp_mjx.core.config import ConfigError, is_number
from regrasp_mjx.robot import dvrk

OBSERVE = ("kinematic", "camera")
# the largest errors accepted: beyond the sizes documented for the dVRK (5-10 mm hand-eye, 5 cm setup)
MAX_CALIBRATION_MM, MAX_CALIBRATION_DEG, MAX_JOINT_OFFSET, MAX_TOOL_NOISE_MM = 50.0, 30.0, 10.0, 10.0
# the neutral configuration of each arm (radians, metres for the insertion): pitch axis 120 mm from the RCM
NEUTRAL = np.array([0.0, 0.0, 0.12 - dvrk.PITCH_FROM_RCM, 0.0, 0.0, 0.0])
# a joint offset of 1 unit (degree; mm for the insertion) in radians or metres
JOINT_UNIT = np.where(np.arange(6) == 2, 1e-3, math.pi / 180.0)


@dataclasses.dataclass(frozen=True)
class RobotErrors:
    """Errors of the robot's view of its tools (see the module docstring): ``calibration_mm`` and
    ``calibration_deg`` of each arm's camera-to-base transform, ``joint_offset`` (degrees, mm for
    the insertion) and the camera's ``tool_noise_mm`` per frame. Zero everywhere: none."""

    calibration_mm: float = 0.0
    calibration_deg: float = 0.0
    joint_offset: float = 0.0
    tool_noise_mm: float = 0.0

    def __post_init__(self) -> None:
        limits = (
            ("calibration_mm", MAX_CALIBRATION_MM, "mm"),
            ("calibration_deg", MAX_CALIBRATION_DEG, "degrees"),
            ("joint_offset", MAX_JOINT_OFFSET, "degrees (mm for the insertion)"),
            ("tool_noise_mm", MAX_TOOL_NOISE_MM, "mm"),
        )
        for name, hi, unit in limits:
            v = getattr(self, name)
            if not (is_number(v) and 0.0 <= v <= hi):
                raise ConfigError(f"{name}={v!r} is not accepted: a finite number of {unit} in [0, {hi:g}]")


def check_observe(observe: str) -> str:
    if observe not in OBSERVE:
        raise ConfigError(f"observe={observe!r} is not accepted: one of {OBSERVE}")
    return observe


# ---- poses as 7-vectors [..., 7] = (x, y, z, qw, qx, qy, qz), through jaxlie ---------------------


def se3(v: jax.Array) -> jaxlie.SE3:
    return jaxlie.SE3(jnp.concatenate([v[..., 3:], v[..., :3]], axis=-1))


def vec(t: jaxlie.SE3) -> jax.Array:
    return jnp.concatenate([t.translation(), t.rotation().wxyz], axis=-1)


def _fk(q: jax.Array) -> jaxlie.SE3:
    """The tool-tip poses (base frame) of joints ``q`` ``[..., 6]``."""
    return jaxlie.SE3.from_matrix(dvrk.forward_kinematics_jax(q))


def _unit(key: jax.Array, shape: tuple) -> jax.Array:
    v = jax.random.normal(key, shape + (3,))
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _error_transform(key: jax.Array, b: int, shift_mm: jax.Array, angle_deg: jax.Array) -> jaxlie.SE3:
    """``[B]`` rigid errors: a rotation of ``angle_deg`` about a random axis through the origin,
    then a shift of ``shift_mm`` in a random direction."""
    k_dir, k_axis = jax.random.split(key)
    rot = jaxlie.SO3.exp(_unit(k_axis, (b,)) * jnp.radians(angle_deg)[:, None])
    return jaxlie.SE3.from_rotation_and_translation(rot, _unit(k_dir, (b,)) * shift_mm[:, None] * 1e-3)


@struct.dataclass
class Arms:
    """One episode's robot errors per row (``[B, ...]``), all poses in the true e_g frame.

    Attributes:
      grasping_view: the grasping tool as its kinematics show it (the true one is the identity).
      base, believed_base: the regrasping arm's base (RCM) frame, true and as the lab believes it.
      offsets: the regrasping arm's joint offsets [rad, m] (it is at ``FK(q + offsets)`` reading q).
      exact: rows without calibration or joint error (their poses are used exactly as they are).
    """

    grasping_view: jax.Array
    base: jax.Array
    believed_base: jax.Array
    offsets: jax.Array
    exact: jax.Array


def draw_arms(key: jax.Array, start: jax.Array, calibration_mm, calibration_deg, joint_offset) -> Arms:
    """This episode's errors of both arms for start poses ``[B, 7]`` (sizes scalars or ``[B]``)."""
    b = start.shape[0]
    size = lambda x: jnp.broadcast_to(jnp.asarray(x, jnp.result_type(float)), (b,))  # noqa: E731
    shift, angle, joint = size(calibration_mm), size(calibration_deg), size(joint_offset)
    k_g, k_r, k_go, k_ro = jax.random.split(key, 4)
    unit = jnp.asarray(JOINT_UNIT, jnp.result_type(float))
    offsets_g = jax.random.uniform(k_go, (b, 6), minval=-1.0, maxval=1.0) * joint[:, None] * unit
    offsets_r = jax.random.uniform(k_ro, (b, 6), minval=-1.0, maxval=1.0) * joint[:, None] * unit
    neutral = jaxlie.SE3.from_matrix(jnp.asarray(dvrk.forward_kinematics(NEUTRAL), jnp.result_type(float)))
    # the grasping arm reads NEUTRAL - o where its tool (the identity) is FK(NEUTRAL)
    base_g = neutral.inverse()
    seen_g = _fk(jnp.asarray(NEUTRAL, jnp.result_type(float)) - offsets_g)
    grasping = base_g @ _error_transform(k_g, b, shift, angle) @ seen_g
    base_r = se3(start) @ neutral.inverse()
    believed_r = base_r @ _error_transform(k_r, b, shift, angle)
    exact = (shift == 0.0) & (angle == 0.0) & (joint == 0.0)
    return Arms(vec(grasping), vec(base_r), vec(believed_r), offsets_r, exact)


def kinematic_pose(q: jax.Array) -> jax.Array:
    """The tool poses ``[B, 7]`` (base frame) of joint readings ``q`` ``[B, 6]``."""
    return vec(_fk(q))


def first_readings(arms: Arms) -> jax.Array:
    """The regrasping arm's joint readings ``[B, 6]`` at the start (its tool at NEUTRAL)."""
    return jnp.asarray(NEUTRAL, jnp.result_type(float)) - arms.offsets


def readings(arms: Arms, ee: jax.Array, previous: jax.Array) -> jax.Array:
    """The regrasping arm's joint readings ``[B, 6]`` with its tool truly at ``ee`` ``[B, 7]``
    (the inverse kinematics' solution nearest the ``previous`` readings' joints)."""
    local = (se3(arms.base).inverse() @ se3(ee)).as_matrix()
    q = jax.vmap(dvrk.inverse_kinematics_jax)(local, previous + arms.offsets)
    return q - arms.offsets


def kinematic_view(arms: Arms, needle: jax.Array, ee: jax.Array, q: jax.Array | None) -> tuple[jax.Array, jax.Array]:
    """The ``kinematic`` view: the camera's needle ``[B, 7]`` and the regrasping tool truly at
    ``ee`` as the believed grasping tool's frame shows them (the tool from its readings ``q``
    through its believed base; ``q`` None: without joint offsets, where ``FK(q) = base^-1 ee``)."""
    if q is None:
        kin = se3(arms.base).inverse() @ se3(ee)
    else:
        kin = _fk(q)
    g_inv = se3(arms.grasping_view).inverse()
    seen_ee = vec(g_inv @ se3(arms.believed_base) @ kin)
    seen_needle = vec(g_inv @ se3(needle))
    exact = arms.exact[:, None]
    return jnp.where(exact, needle, seen_needle), jnp.where(exact, ee, seen_ee)


def propagate(seen: jax.Array, before: jax.Array, after: jax.Array) -> jax.Array:
    """A view of the tool ``[B, 7]`` moved by the motion its kinematics report between two poses
    ``before`` and ``after`` (any one frame; the motion in the tool's own frame)."""
    return vec(se3(seen) @ se3(before).inverse() @ se3(after))


def average(mean: jax.Array, count: jax.Array, new: jax.Array) -> jax.Array:
    """The running mean of ``count`` poses ``[B, 7]`` with ``new`` added (positions averaged, the
    quaternions' chordal mean on ``mean``'s hemisphere)."""
    w = jnp.reshape(1.0 / (count + 1.0), (-1, 1))
    sign = jnp.where(jnp.sum(new[:, 3:] * mean[:, 3:], -1, keepdims=True) < 0, -1.0, 1.0)
    pos = mean[:, :3] + w * (new[:, :3] - mean[:, :3])
    quat = (1.0 - w) * mean[:, 3:] + w * sign * new[:, 3:]
    return jnp.concatenate([pos, quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)], -1)


def executed(
    arms: Arms, ee: jax.Array, seen_ee: jax.Array, action: jax.Array, max_dp: float, max_drot: float, q=None
) -> jax.Array:
    """What the policy's ``action`` ``[B, 6]`` on its view ``seen_ee`` of the tool truly at ``ee``
    does, as an unclipped action in the true e_g frame (``[B, 6]``, units of ``max_dp`` and
    ``max_drot``): the tool-frame motion ``D`` it asks for, commanded from the readings ``q``
    (None: no joint offsets, where the arm moves its tool by exactly ``D``)."""
    a = jnp.clip(action, -1.0, 1.0)
    dp, rotvec = a[:, :3] * max_dp, a[:, 3:] * max_drot
    if q is None:  # D exactly: the motion turned by the view's orientation error r = q q'^-1
        r = jaxlie.SO3(ee[:, 3:]) @ jaxlie.SO3(seen_ee[:, 3:]).inverse()
        dp, rotvec = r.apply(dp), r.apply(rotvec)
        return jnp.concatenate([dp / max_dp, rotvec / max_drot], -1)
    target = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.exp(rotvec) @ jaxlie.SO3(seen_ee[:, 3:]), seen_ee[:, :3] + dp
    )
    motion = se3(seen_ee).inverse() @ target  # D, in the tool's frame
    commanded = (_fk(q) @ motion).as_matrix()
    q_next = jax.vmap(dvrk.inverse_kinematics_jax)(commanded, q)
    reached = se3(arms.base) @ _fk(q_next + arms.offsets)
    moved = reached.translation() - ee[:, :3]
    turned = (reached.rotation() @ jaxlie.SO3(ee[:, 3:]).inverse()).log()
    return jnp.concatenate([moved / max_dp, turned / max_drot], -1)
