"""Frames and poses of the regrasping task (paper §III-A, SPEC "Frames").

A pose is a pair ``(position[..., 3], quaternion[..., 4])`` with quaternions ``(w, x, y, z)`` like
MuJoCo and jaxlie; positions in metres. ``T_a_b`` reads "frame b expressed in frame a", so
``compose(T_a_b, T_b_c) = T_a_c``. Rigid-body algebra is jaxlie's (SE(3)/SO(3)); this module only
adds the task's frames: the needle frame n, the grasping-point frame g and the end-effector frame e.

All functions are pure jax.numpy, broadcast over leading axes and run under jit and vmap.
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
import numpy as np

Array = jnp.ndarray
Pose = tuple[Array, Array]

NEEDLE_RADIUS = 0.0054  # m, paper §V-C
OBS_SIZE = 21
# a general task's observation (ours): the paper's 21, then the needle in the goal end-effector frame
# (7), the goal end-effector in the current one (7), and the needle's radius and wire radius (2)
OBS_SIZE_GENERAL = OBS_SIZE + 16
# |norm - 1| up to this is normalised; beyond it a quaternion is refused (ours; one tolerance for
# every input: pose arrays to plan, test-set files, dVRK poses)
QUAT_NORM_TOLERANCE = 1e-2


def unit_quaternions(what: str, q, error: type[Exception] = ValueError) -> np.ndarray:
    """``q[..., 4]`` (wxyz) divided by its norms, as float64; ``error`` when a norm is off by more
    than :data:`QUAT_NORM_TOLERANCE`, naming ``what``, the first bad row and the tolerance."""
    q = np.asarray(q, np.float64)
    norms = np.linalg.norm(q, axis=-1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOLERANCE)
    if bad.size:
        raise error(
            f"{what}: quaternion norm {norms.reshape(-1)[bad[0]]:.6g} in row {bad[0]} ({bad.size} rows in all) "
            f"is not unit (a unit quaternion is needed, wxyz); accepted: |norm - 1| <= {QUAT_NORM_TOLERANCE:g} "
            "(normalised)"
        )
    return q / norms[..., None]


# ----------------------------------------------------------------------------------------------
# Pose algebra (thin wrappers so that the rest of the package speaks (pos, quat) pairs).
# ----------------------------------------------------------------------------------------------
def to_se3(pos: Array, quat: Array) -> jaxlie.SE3:
    """The jaxlie transform of a ``(pos, quat)`` pose."""
    pos, quat = jnp.asarray(pos), jnp.asarray(quat)
    batch = jnp.broadcast_shapes(pos.shape[:-1], quat.shape[:-1])
    pos, quat = jnp.broadcast_to(pos, (*batch, 3)), jnp.broadcast_to(quat, (*batch, 4))
    return jaxlie.SE3(jnp.concatenate([quat, pos], axis=-1))


def from_se3(transform: jaxlie.SE3) -> Pose:
    """``(pos, quat)`` of a jaxlie transform, the quaternion made canonical (``w >= 0``)."""
    return transform.translation(), canonical_quat(transform.rotation().wxyz)


def compose(a: Pose, b: Pose) -> Pose:
    """``T_a_b ∘ T_b_c``: the pose ``b`` (given in frame a's child) expressed in a's parent."""
    return from_se3(to_se3(*a) @ to_se3(*b))


def inverse(a: Pose) -> Pose:
    """The inverse pose ``T_b_a`` of ``T_a_b``."""
    return from_se3(to_se3(*a).inverse())


def relative(a: Pose, b: Pose) -> Pose:
    """``T_a_b = (T_w_a)^-1 T_w_b``: pose b seen from frame a, both given in one frame w."""
    return from_se3(to_se3(*a).inverse() @ to_se3(*b))


def canonical_quat(quat: Array) -> Array:
    """The same rotation with ``w >= 0`` (q and -q are one rotation; observations use w >= 0)."""
    return jnp.where(quat[..., :1] < 0.0, -quat, quat)


def quat_mul(q1: Array, q2: Array) -> Array:
    """Hamilton product ``q1 ⊗ q2`` (apply q2, then q1)."""
    return (jaxlie.SO3(q1) @ jaxlie.SO3(q2)).wxyz


def quat_from_rotvec(rotvec: Array) -> Array:
    """``exp`` of a rotation vector (axis times angle, radians)."""
    return jaxlie.SO3.exp(rotvec).wxyz


def quat_angle(q1: Array, q2: Array) -> Array:
    """Angle (radians, in [0, pi]) of the rotation ``q1 q2^-1``: the paper's eq. (9) distance.

    Computed as ``2 atan2(|v|, |w|)`` of the product so that q and -q give the same, smallest angle.
    """
    d = quat_mul(q1, jaxlie.SO3(q2).inverse().wxyz)
    return 2.0 * jnp.arctan2(jnp.linalg.norm(d[..., 1:], axis=-1), jnp.abs(d[..., 0]))


def rotation_matrix(quat: Array) -> Array:
    """3x3 rotation matrix of a quaternion; its columns are the frame's axes."""
    return jaxlie.SO3(quat).as_matrix()


# ----------------------------------------------------------------------------------------------
# The task's frames.
# ----------------------------------------------------------------------------------------------
def needle_point(alpha: Array, radius: float | Array = NEEDLE_RADIUS) -> Array:
    """Point ``p(alpha) = (0, R cos a, R sin a)`` of the needle, in the needle frame (paper eq. 1)."""
    alpha = jnp.asarray(alpha, dtype=jnp.result_type(float))
    return jnp.asarray(radius) * jnp.stack([jnp.zeros_like(alpha), jnp.cos(alpha), jnp.sin(alpha)], -1)


def needle_tangent(alpha: Array) -> Array:
    """Unit tangent ``dp/dalpha / R = (0, -sin a, cos a)`` of the needle, in the needle frame."""
    alpha = jnp.asarray(alpha, dtype=jnp.result_type(float))
    return jnp.stack([jnp.zeros_like(alpha), -jnp.sin(alpha), jnp.cos(alpha)], -1)


def spherical_offset(depth: Array, theta: Array, phi: Array) -> Array:
    """End-effector position in the grasping-point frame (paper eq. 2):
    ``(d cos phi, d sin phi cos theta, d sin phi sin theta)``."""
    depth, theta, phi = jnp.broadcast_arrays(
        *(jnp.asarray(x, dtype=jnp.result_type(float)) for x in (depth, theta, phi))
    )
    return jnp.stack(
        [depth * jnp.cos(phi), depth * jnp.sin(phi) * jnp.cos(theta), depth * jnp.sin(phi) * jnp.sin(theta)], -1
    )


def grasp_pose(alpha: Array, depth: Array, theta: Array, phi: Array, radius: float | Array = NEEDLE_RADIUS) -> Pose:
    """End-effector pose ``T_n_e`` in the needle frame for a grasp (paper eq. 3, SPEC "Frames").

    Position: the grasping point ``p(alpha)`` plus the spherical offset ``(d, theta, phi)``.
    Orientation: ``z_e`` points from the end-effector origin (the jaw pivot) at the grasping point;
    ``x_e`` (the hinge axis) is the needle's tangent at that point projected onto the plane normal
    to ``z_e``, so the wire lies across both jaws; ``y_e = z_e x x_e``. The roll is our choice
    (the paper says only "points at the grasping point"). Where the tangent is parallel to ``z_e``
    (the jaws would point along the wire) the needle-plane normal ``x_n`` takes its place.

    Args:
      alpha: angle on the needle, radians, in [pi/2, 3pi/2] (tip at pi/2).
      depth: distance d from the grasping point to the jaw pivot, metres.
      theta: azimuth, radians.
      phi: inclination from the needle-plane normal x_n, radians.
      radius: needle radius R, metres.

    Returns:
      ``(position[..., 3], quaternion wxyz[..., 4])`` of the end-effector in the needle frame,
      quaternion with ``w >= 0``.
    """
    alpha, depth, theta, phi, radius = jnp.broadcast_arrays(
        *(jnp.asarray(v, dtype=jnp.result_type(float)) for v in (alpha, depth, theta, phi, radius))
    )
    offset = spherical_offset(depth, theta, phi)
    pos = needle_point(alpha, radius[..., None]) + offset
    z = -offset / jnp.linalg.norm(offset, axis=-1, keepdims=True)
    tangent = needle_tangent(alpha)
    x = tangent - jnp.sum(tangent * z, -1, keepdims=True) * z
    x_n = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0], z.dtype), z.shape)
    fallback = x_n - jnp.sum(x_n * z, -1, keepdims=True) * z
    degenerate = jnp.linalg.norm(x, axis=-1, keepdims=True) < 1e-6
    x = jnp.where(degenerate, fallback, x)
    x = x / jnp.linalg.norm(x, axis=-1, keepdims=True)
    y = jnp.cross(z, x)
    rot = jnp.stack([x, y, z], axis=-1)
    return pos, canonical_quat(jaxlie.SO3.from_matrix(rot).wxyz)


# ----------------------------------------------------------------------------------------------
# The ego-centric state (paper §III-B).
# ----------------------------------------------------------------------------------------------
def ego_observation(grasp_ee: Pose, regrasp_ee: Pose, needle: Pose) -> Array:
    """The 21-number ego-centric state from three poses given in any one frame (world, camera).

    Layout: ``[p_eg_n(3), q_eg_n(4), p_eg_er(3), q_eg_er(4), p_er_n(3), q_er_n(4)]``: the needle and
    the regrasping end-effector in the grasping end-effector frame, then the needle in the
    regrasping end-effector frame; metres, quaternions with ``w >= 0``. Only relative poses enter,
    so one rigid transform of the whole world leaves it unchanged.
    """
    eg_n = relative(grasp_ee, needle)
    eg_er = relative(grasp_ee, regrasp_ee)
    er_n = relative(regrasp_ee, needle)
    return jnp.concatenate([eg_n[0], eg_n[1], eg_er[0], eg_er[1], er_n[0], er_n[1]], axis=-1)


def ego_observation_eg(needle: Pose, regrasp_ee: Pose) -> Array:
    """:func:`ego_observation` when poses are already in the grasping end-effector frame."""
    er_n = relative(regrasp_ee, needle)
    return jnp.concatenate(
        [needle[0], canonical_quat(needle[1]), regrasp_ee[0], canonical_quat(regrasp_ee[1]), er_n[0], er_n[1]],
        axis=-1,
    )


def task_observation(needle: Pose, regrasp_ee: Pose, goal_ee: Pose, radius: Array, wire: Array) -> Array:
    """What a general task adds to the ego-centric state (16 numbers, ours): ``[p_er*_n(3),
    q_er*_n(4), p_er_er*(3), q_er_er*(4), R, r_wire]``, the needle in the goal end-effector frame (the
    pose the success test compares ``p_er_n, q_er_n`` with), the goal end-effector in the current
    one, and the needle's radius and wire radius [m]. Poses in any one frame: only relative poses
    enter, so one rigid transform of the whole world leaves it unchanged."""
    goal_n = relative(goal_ee, needle)
    er_goal = relative(regrasp_ee, goal_ee)
    return jnp.concatenate(
        [goal_n[0], goal_n[1], er_goal[0], er_goal[1], jnp.stack([jnp.asarray(radius), jnp.asarray(wire)], -1)],
        axis=-1,
    )


def pose_error(current: Pose, goal: Pose) -> tuple[Array, Array]:
    """Position distance (m) and rotation angle (rad) between two poses of one frame (eqs. 8, 9):
    ``|p* - p|`` and the angle of ``q* q^-1``."""
    return jnp.linalg.norm(goal[0] - current[0], axis=-1), quat_angle(goal[1], current[1])


def dot3(a: Array, b: Array) -> Array:
    """``sum(a * b, -1)`` over a last axis of 3, written as three products and two sums: elementwise
    arithmetic that XLA fuses with its neighbours, where a reduction ends a fused kernel (and writes
    its result to memory) on a GPU; any array module."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def segment_gap(a0: Array, a1: Array, b0: Array, b1: Array, xp=jnp) -> Array:
    """The vector from the closest point of segment ``[b0, b1]`` to that of ``[a0, a1]`` (batched over
    leading axes): its length is their distance, its direction the separating plane's normal.
    ``xp``: ``jax.numpy`` or ``numpy`` (float64: the host checker's).

    Ericson, Real-Time Collision Detection, §5.1.9: minimise over s for the unclamped t, clamp t to
    [0, 1] and re-solve s for a clamped t. Both segments must have non-zero length (capsules do).
    """
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    s, t = segment_params(dot3(d1, d1), dot3(d2, d2), dot3(d1, d2), dot3(d1, r), dot3(d2, r), xp)
    return a0 + d1 * s[..., None] - (b0 + d2 * t[..., None])


def segment_params(a, e, b, c, f, xp=jnp):
    """:func:`segment_gap`'s closest points as parameters ``(s, t)`` along ``a0 + s d1`` and ``b0 + t d2``,
    from the dot products ``a = d1.d1``, ``e = d2.d2``, ``b = d1.d2``, ``c = d1.r``, ``f = d2.r``
    (``r = a0 - b0``): elementwise, so that a kernel holding its vectors as components
    (:mod:`regrasp_mjx.world.walk_kernel`) clamps them the same way."""
    denom = a * e - b * b
    # Parallel segments (denom ~ 0): any s works; s = 0 and the clamps below give the distance.
    s = xp.where(denom > 1e-9 * a * e, xp.clip((b * f - c * e) / xp.where(denom > 0, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = xp.where(t < 0.0, xp.clip(-c / a, 0.0, 1.0), xp.where(t > 1.0, xp.clip((b - c) / a, 0.0, 1.0), s))
    return s, xp.clip(t, 0.0, 1.0)


def segment_distance(a0: Array, a1: Array, b0: Array, b1: Array) -> Array:
    """Exact distance between segments ``[a0, a1]`` and ``[b0, b1]`` (batched over leading axes): the
    length of :func:`segment_gap`."""
    gap = segment_gap(a0, a1, b0, b1)
    return jnp.sqrt(dot3(gap, gap))
