"""Kinematics of the dVRK Patient Side Manipulator (PSM) with the Large Needle Driver (LND).

Modified (Craig) Denavit-Hartenberg parameters and joint limits from the dVRK's own configuration
files, jhu-dvrk/sawIntuitiveResearchKit:

- arm: ``core/share/kinematic/psm.json`` (commit 2538493c): outer yaw, outer pitch, insertion;
- tool: ``share/tool/LARGE_NEEDLE_DRIVER_400006.json`` (commit 00bb61b8): roll, wrist pitch, wrist
  yaw (``A`` = 9.1 mm from the pitch to the yaw axis), and its ``tooltip-offset``, a pure rotation.

The chain's base frame sits at the PSM's remote centre of motion (RCM): with the outer joints at
zero the shaft points along the base's -z, and the pitch axis of the wrist lies ``q3 - 0.0156`` m
along the shaft from the RCM. The end frame after the tool-tip offset has its
origin on the yaw (jaw) axis, x along that axis, z along the jaws out of the tool: exactly this
project's end-effector frame e (``models/mjcf/regrasp_scene.xml``: origin at the jaw pivot, x the
hinge axis, z along the jaws, the pitch axis 9.1 mm behind the pivot), so the offset between the
PSM's end frame and our e frame is the identity (tested). Poses are 4x4 homogeneous matrices in
metres, or ``[x, y, z, qw, qx, qy, qz]`` 7-vectors where named.

The inverse is closed-form (the PSM is an RCM arm with a wrist), in numpy: the yaw axis and the
9.1 mm wrist link fix the pitch-axis point, which fixes the outer yaw, pitch and insertion; the wrist
angles follow from the remaining rotation. No library: the maths is twenty lines, and the robotics
toolboxes we looked at (roboticstoolbox-python, ikpy) would add heavy dependencies for a chain whose
closed form is exact.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.geometry import unit_quaternions

# (alpha, a, d, theta offset, type) per joint, modified DH, metres and radians
DH = (
    (math.pi / 2, 0.0, 0.0, math.pi / 2, "revolute"),  # outer yaw
    (-math.pi / 2, 0.0, 0.0, -math.pi / 2, "revolute"),  # outer pitch
    (math.pi / 2, 0.0, -0.4318, 0.0, "prismatic"),  # insertion (offset on d)
    (0.0, 0.0, 0.4162, 0.0, "revolute"),  # tool roll
    (-math.pi / 2, 0.0, 0.0, -math.pi / 2, "revolute"),  # wrist pitch
    (-math.pi / 2, 0.0091, 0.0, -math.pi / 2, "revolute"),  # wrist yaw
)
JOINT_NAMES = ("outer_yaw", "outer_pitch", "outer_insertion", "outer_roll", "outer_wrist_pitch", "outer_wrist_yaw")
Q_MIN = np.array([-1.588, -0.925025, 0.0, -4.53786, -1.39626, -1.39626])
Q_MAX = np.array([1.588, 0.925025, 0.24, 4.53786, 1.39626, 1.39626])
TOOLTIP_OFFSET = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
WRIST_LINK = DH[5][1]  # pitch axis to yaw axis, m
PITCH_FROM_RCM = DH[2][2] + DH[3][2]  # pitch-axis point along the shaft: q3 + this (-0.0156 m)


def _dh(alpha: float, a: float, theta: float, d: float) -> np.ndarray:
    ca, sa, ct, st = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    return np.array(
        [
            [ct, -st, 0.0, a],
            [st * ca, ct * ca, -sa, -d * sa],
            [st * sa, ct * sa, ca, d * ca],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _check_q(q) -> np.ndarray:
    q = np.asarray(q, np.float64)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise ValueError(f"joints must be 6 finite numbers {JOINT_NAMES} (rad, rad, m, rad, rad, rad), got {q!r}")
    return q


def forward_kinematics(q, upto: int = 6) -> np.ndarray:
    """The tool-tip pose (4x4, metres) in the PSM base (RCM) frame for joints ``q`` (6: radians, and
    metres for the insertion); ``upto < 6`` returns the DH frame of that joint instead (no offset)."""
    q = _check_q(q)
    t = np.eye(4)
    for (alpha, a, d, offset, kind), qi in list(zip(DH, q))[:upto]:
        theta, dd = (qi + offset, d) if kind == "revolute" else (offset, qi + d)
        t = t @ _dh(alpha, a, theta, dd)
    return t @ TOOLTIP_OFFSET if upto == 6 else t


@dataclasses.dataclass(frozen=True)
class IKResult:
    """``q``: the joints (6); ``reachable``: every joint within its limit and FK(q) within
    :data:`IK_POSITION_TOLERANCE` / :data:`IK_ROTATION_TOLERANCE` of the asked pose;
    ``violations``: the names of the joints outside their limits; ``position_error`` (m) and
    ``rotation_error`` (rad): the residual of FK(q) against the asked pose, near zero for every
    pose the arm's geometry can realise."""

    q: np.ndarray
    reachable: bool
    violations: tuple[str, ...]
    position_error: float
    rotation_error: float


# how far a 4x4 pose's rotation block may be from a rotation (largest entry of R^T R - I, and det R - 1)
# and its last row from [0, 0, 0, 1]: float32 rounding of a measured pose stays far inside it, a scale
# or shear (a matrix of another meaning) far outside
RIGID_TOLERANCE = 1e-4


def as_matrix(pose, name: str = "pose") -> np.ndarray:
    """A pose as a 4x4 matrix: a 4x4 is checked (finite, rigid: a rotation and a translation) and
    returned, a 7-vector converted (unit quaternion); a ValueError naming ``name`` and the problem."""
    pose = np.asarray(pose, np.float64)
    if pose.shape == (7,):
        if not np.all(np.isfinite(pose)):
            raise ValueError(f"{name} must be [x, y, z, qw, qx, qy, qz] with finite values, got {pose!r}")
        return pose_matrix(np.r_[pose[:3], unit_quaternions(f"{name} [x, y, z, qw, qx, qy, qz]", pose[3:])])
    if pose.shape != (4, 4):
        raise ValueError(f"{name} has shape {pose.shape}; accepted: a 4x4 homogeneous matrix or a 7-vector")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{name} (a 4x4 matrix) holds NaN or inf; accepted: finite values")
    r = pose[:3, :3]
    off = float(np.max(np.abs(r.T @ r - np.eye(3))))
    det = float(np.linalg.det(r))
    last = float(np.max(np.abs(pose[3] - (0.0, 0.0, 0.0, 1.0))))
    if max(off, abs(det - 1.0), last) > RIGID_TOLERANCE:
        raise ValueError(
            f"{name} (a 4x4 matrix) is not a rigid transform (rotation block off orthonormal by {off:.3g}, "
            f"determinant {det:.6g}, last row {pose[3].tolist()}); accepted: a rotation and a translation, "
            f"within {RIGID_TOLERANCE:g}"
        )
    return pose


# what a solution of the closed form may miss the asked pose by and still count as reaching it
IK_POSITION_TOLERANCE = 1e-6  # m
IK_ROTATION_TOLERANCE = 1e-5  # rad
JAX_LIMIT_SLACK = 1e-6  # rad or m past a limit that the float32 check still accepts
# the pitch point this close to the RCM [m]: the closed form also tries CROSSING_FAMILY's members of
# the singular family there (inverse_kinematics; the shaft turned about the pitch axis by each angle)
CROSSING = 1e-6
CROSSING_FAMILY = tuple(float(a) for a in np.radians(np.arange(-90.0, 90.5, 1.0)) if a != 0.0)
ROLL_SLACK = 1e-9  # rad: a roll this far past its limit (rounding along a trajectory) is put on the limit


def _dh_batch(alpha: float, a: float, theta, d, xp):
    """:func:`_dh` for a batch of joint values ``theta``, ``d`` ``[K]`` (numpy or jax.numpy ``xp``)."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    ct, st = xp.cos(theta), xp.sin(theta)
    zero = xp.zeros_like(ct)
    d = d + zero
    rows = (
        (ct, -st, zero, zero + a),
        (st * ca, ct * ca, zero - sa, -d * sa),
        (st * sa, ct * sa, zero + ca, d * ca),
        (zero, zero, zero, zero + 1.0),
    )
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


def fk_batch(q, xp=np):
    """Tool-tip poses ``[K, 4, 4]`` (base frame) of joint vectors ``q`` ``[K, 6]``: :func:`forward_kinematics`
    of a batch at once, in the array module ``xp`` (numpy, or jax.numpy inside jitted code); ``q`` is
    not validated."""
    t = None
    for i, (alpha, a, d, offset, kind) in enumerate(DH):
        theta, dd = (q[:, i] + offset, d) if kind == "revolute" else (q[:, i] * 0.0 + offset, q[:, i] + d)
        m = _dh_batch(alpha, a, theta, dd, xp)
        t = m if t is None else t @ m
    return t @ xp.asarray(TOOLTIP_OFFSET)


def forward_kinematics_jax(q):
    """JAX: tool-tip poses ``[..., 4, 4]`` (base frame) of joint vectors ``q`` ``[..., 6]``
    (:func:`forward_kinematics` in jax.numpy, for jitted simulations of the arm)."""
    q = jnp.asarray(q)
    return fk_batch(q.reshape(-1, 6), jnp).reshape(q.shape[:-1] + (4, 4))


def inverse_kinematics_jax(t, q_ref):
    """JAX: the joints ``[6]`` that put the tool tip at ``t`` (4x4, base frame) nearest ``q_ref``
    ``[6]``: of the closed form's candidates that reach it (:func:`inverse_kinematics`'s residual
    test at float32's resolution), the nearest, its roll turned by whole turns to the one nearest
    ``q_ref``'s. Limits are not applied (a simulation of where the arm goes; see
    :func:`within_limits_jax` for the verdict). vmap for batches."""
    cands = _ik_candidates(t[:3, 3], t[:3, :3], jnp)
    pos, rot = _residuals(cands, t, jnp)
    turns = jnp.round((q_ref[3] - cands[:, 3]) / (2.0 * jnp.pi))
    cands = cands.at[:, 3].add(2.0 * jnp.pi * turns)
    misses = jnp.where((pos < 1e-6) & (rot < 1e-4), 0.0, 1e6 + pos + rot)
    return cands[jnp.argmin(misses + jnp.sum((cands - q_ref) ** 2, axis=1))]


def _ik_candidates(p, rot, xp, family=()):
    """The closed form's six candidate joint vectors ``[6, 6]`` for a tool-tip position ``p`` and rotation
    ``rot`` (the roll nearest zero): one of them reaches the pose wherever the arm can.

    The wrist link (pitch axis to yaw axis) is perpendicular to the yaw axis x, and the shaft
    through the RCM (the origin) projects onto the plane through p normal to x along that link's
    line; so the pitch-axis point lies ``WRIST_LINK`` from p along that line, on one side or the
    other (the projection can lie beyond the pitch point when the pitch point is behind the RCM),
    and the shaft points from the RCM through the pitch point, or away from it when the pitch point
    lies behind the RCM (insertion below ``-PITCH_FROM_RCM`` = 15.6 mm). Each of the four choices
    gives the outer joints, and the wrist angles follow from the remaining rotation; two more cover
    the pitch point at the RCM itself; forward kinematics tells which choices reach the pose.

    ``family``: angles (rad, not 0) of more members of the singular family at the RCM, the shaft turned
    from the straight wrist by each about the pitch axis (in the plane of the wrist link and the
    yaw axis), the wrist pitch turning back by as much: at the crossing, the straight wrist may put
    the outer joints out of their limits where another member does not."""
    x = rot[:, 0]
    towards = xp.dot(p, x) * x - p
    unit = towards / xp.maximum(xp.linalg.norm(towards), 1e-12)
    shafts = []  # (insertion direction, insertion)
    for link in (1.0, -1.0):
        pitch_point = p + link * WRIST_LINK * unit
        dist = xp.maximum(xp.linalg.norm(pitch_point), 1e-12)
        shafts += [(side * pitch_point / dist, side * dist - PITCH_FROM_RCM) for side in (1.0, -1.0)]
    # the pitch axis at the RCM (a singularity: the shaft may turn about the pitch axis while the
    # wrist pitch turns back): the straight-wrist member of that family, the shaft along the link
    along = p / xp.maximum(xp.linalg.norm(p), 1e-12)
    across = x - xp.dot(x, along) * along
    across = across / xp.maximum(xp.linalg.norm(across), 1e-12)
    for phi in (0.0, *family):  # 0: the straight wrist
        turned = math.cos(phi) * along + math.sin(phi) * across
        shafts += [(side * turned, -PITCH_FROM_RCM + 0.0 * p[0]) for side in (1.0, -1.0)]
    qs = []
    for shaft, q3 in shafts:
        # z3 = (sin q1 cos q2, -sin q2, -cos q1 cos q2) for this DH (cos q2 > 0 within the pitch limits)
        q2 = xp.arcsin(xp.clip(-shaft[1], -1.0, 1.0))
        q1 = xp.arctan2(shaft[0], -shaft[2])
        s1, c1, s2, c2 = xp.sin(q1), xp.cos(q1), xp.sin(q2), xp.cos(q2)
        zero = s1 * 0.0
        r03 = xp.stack(
            [
                xp.stack([-s1 * s2, -c1, s1 * c2]),
                xp.stack([-c2, zero, -s2]),
                xp.stack([s2 * c1, -s1, -c1 * c2]),
            ]
        )  # forward_kinematics(upto=3)'s rotation
        m = r03.T @ rot  # the tool tip's rotation in joint 3's frame
        # columns of m (derived from the DH above): x = (-c4 c5, -s4 c5, s5), row 3 = (s5, -s6 c5, c5 c6)
        q5 = xp.arcsin(xp.clip(m[2, 0], -1.0, 1.0))
        q4 = xp.arctan2(-m[1, 0], -m[0, 0])
        q6 = xp.arctan2(-m[2, 1], m[2, 2])
        qs.append(xp.stack([q1, q2, q3, q4, q5, q6]))
    return xp.stack(qs)


def _residuals(q, t, xp):
    """Position (m) and rotation (rad) residuals ``[K]`` of joint vectors ``q`` ``[K, 6]`` against
    the pose ``t`` (4x4)."""
    back = fk_batch(q, xp)
    pos = xp.linalg.norm(back[:, :3, 3] - t[:3, 3], axis=-1)
    rel = xp.swapaxes(back[:, :3, :3], -1, -2) @ t[:3, :3]
    skew = xp.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    trace = rel[:, 0, 0] + rel[:, 1, 1] + rel[:, 2, 2]
    rot = xp.arctan2(xp.linalg.norm(skew, axis=-1) / 2.0, (trace - 1.0) / 2.0)  # accurate near 0
    return pos, rot


def inverse_kinematics(pose, q_ref=None) -> IKResult:
    """Joints that put the tool tip at ``pose`` (4x4 or 7-vector, in the PSM base frame), with a
    verdict: out-of-limit joints are reported, never clipped, and so is a pose the arm's geometry
    cannot realise (its residual then stays above :data:`IK_POSITION_TOLERANCE` /
    :data:`IK_ROTATION_TOLERANCE`, and ``reachable`` is false). Over the whole insertion range,
    both sides of the pitch axis crossing the RCM. Of the roll angles ``q4 + 2 pi k`` (the roll
    range spans 520 degrees): with ``q_ref``, the one nearest its roll, so that a trajectory solved
    pose by pose never jumps a turn (out of the limits it is reported, not swapped for the turn
    within them: the arm cannot unwind a turn between two poses; one within :data:`ROLL_SLACK` of a
    limit is put on it); without, the one within the limits nearest 0.

    Raises:
      ValueError: a malformed pose, or one whose wrist-link direction is undefined (the yaw axis
        passes through the RCM).
    """
    t = as_matrix(pose)
    p, x = t[:3, 3], t[:3, 0]
    if np.linalg.norm(p.dot(x) * x - p) < 1e-9:
        raise ValueError("pose has its yaw axis through the remote centre of motion: the wrist is undefined")
    # the pitch point within a micrometre of the RCM: the singular family's members too
    crossing = abs(np.linalg.norm(p) - WRIST_LINK) < CROSSING and abs(p.dot(x)) < CROSSING
    cands = _ik_candidates(p, t[:3, :3], np, CROSSING_FAMILY if crossing else ())
    pos, rot = _residuals(cands, t, np)
    roll = cands[:, 3:4] + 2.0 * math.pi * np.array([0.0, -1.0, 1.0])  # some turn of the roll may fit
    outside = (cands < Q_MIN - 1e-12) | (cands > Q_MAX + 1e-12)
    outside[:, 3] = ~np.any((roll >= Q_MIN[3]) & (roll <= Q_MAX[3]), axis=1)
    solves = (pos < 1e-9) & (rot < 1e-8)
    realised = (pos < IK_POSITION_TOLERANCE) & (rot < IK_ROTATION_TOLERANCE)
    # a solution within the limits first (exact, else within the tolerances: near the crossing the
    # family's members miss by the pitch point's distance from the RCM), then the solution with the
    # fewest joints outside, then the closest miss
    order = np.lexsort((pos + rot, ~(solves | realised & ~outside.any(1)), outside.sum(1), ~realised))
    q = cands[order[0]].copy()
    ref = 0.0 if q_ref is None else float(np.asarray(q_ref, np.float64)[3])
    rolls = q[3] + 2.0 * math.pi * (round((ref - q[3]) / (2.0 * math.pi)) + np.array([0, -1, 1]))
    if q_ref is None:  # the nearest zero within the limits (every roll in [-pi, pi] is)
        ok = (rolls >= Q_MIN[3]) & (rolls <= Q_MAX[3])
        q[3] = rolls[np.argmax(ok)] if ok.any() else rolls[0]
    else:  # the nearest the reference, a rounding past a limit put back on it
        q[3] = rolls[0] if abs(rolls[0]) > Q_MAX[3] + ROLL_SLACK else float(np.clip(rolls[0], Q_MIN[3], Q_MAX[3]))
    position_error, rotation_error = (float(v[0]) for v in _residuals(q[None], t, np))
    out = (q < Q_MIN - 1e-12) | (q > Q_MAX + 1e-12)
    realised = position_error < IK_POSITION_TOLERANCE and rotation_error < IK_ROTATION_TOLERANCE
    return IKResult(
        q=q,
        reachable=bool(realised and not out.any()),
        violations=tuple(n for n, o in zip(JOINT_NAMES, out) if o),
        position_error=position_error,
        rotation_error=rotation_error,
    )


def pose_matrix(pose) -> np.ndarray:
    """``[x, y, z, qw, qx, qy, qz]`` -> 4x4."""
    pose = np.asarray(pose, np.float64)
    w, x, y, z = pose[3:] / np.linalg.norm(pose[3:])
    t = np.eye(4)
    t[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    t[:3, 3] = pose[:3]
    return t


def average_pose(poses) -> np.ndarray:
    """The mean position and the average orientation (the principal eigenvector of the quaternions'
    scatter matrix, Markley et al. 2007) of poses ``[N, 7]``: e.g. where to put one port for a set
    of tool poses, ``base_behind(average_pose(starts))``."""
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    _, vectors = np.linalg.eigh(poses[:, 3:].T @ poses[:, 3:])
    quat = vectors[:, -1] * (1.0 if vectors[0, -1] >= 0 else -1.0)
    return np.r_[poses[:, :3].mean(0), quat]


def base_behind(tool_pose, distance: float = 0.12) -> np.ndarray:
    """A PSM base (RCM) frame for which ``tool_pose`` (4x4 or 7-vector) is the neutral configuration:
    outer joints and wrist at zero, the pitch axis ``distance`` from the RCM along the shaft (4x4).
    A way to place a port where a tool already is (the experiments' set-up)."""
    q = np.array([0.0, 0.0, distance - PITCH_FROM_RCM, 0.0, 0.0, 0.0])
    return as_matrix(tool_pose) @ np.linalg.inv(forward_kinematics(q))


def within_limits_jax(base_inv, pos, quat):
    """JAX: whether the PSM whose base frame's inverse is ``base_inv`` (``[4, 4]``, in the poses'
    frame) reaches tool-tip poses ``pos [3]``, ``quat [4]`` (wxyz) within every joint limit: the
    verdict of :func:`inverse_kinematics` (the same closed form and residual test; the roll
    within its +-260 degree range whenever some turn of it is), for checks inside jitted planners;
    vmap for batches."""

    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    rot = jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    t = jnp.eye(4).at[:3, :3].set(base_inv[:3, :3] @ rot).at[:3, 3].set(base_inv[:3, :3] @ pos + base_inv[:3, 3])
    cands = _ik_candidates(t[:3, 3], t[:3, :3], jnp)
    pos_err, rot_err = _residuals(cands, t, jnp)
    # float32 on a GPU: the residual test is looser than the float64 host's (tens of nm, 1e-5 rad)
    solves = (pos_err < 1e-6) & (rot_err < 1e-4)
    # float32 puts a joint exactly at its limit up to ~1e-7 past it: the limits get that much slack
    lo, hi = jnp.asarray(Q_MIN) - JAX_LIMIT_SLACK, jnp.asarray(Q_MAX) + JAX_LIMIT_SLACK
    roll_ok = jnp.any(
        (cands[:, 3:4] + 2 * jnp.pi * jnp.array([0.0, -1.0, 1.0]) >= lo[3])
        & (cands[:, 3:4] + 2 * jnp.pi * jnp.array([0.0, -1.0, 1.0]) <= hi[3]),
        axis=1,
    )
    others = jnp.all((cands >= lo) & (cands <= hi) | (jnp.arange(6) == 3), axis=1)
    return jnp.any(solves & others & roll_ok)
