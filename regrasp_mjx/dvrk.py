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

import numpy as np

from regrasp_mjx.geometry import unit_quaternions

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
    """``q``: the joints (6); ``reachable``: within every joint limit; ``violations``: the names of
    the joints outside their limits (empty when reachable); ``error``: the residual of FK(q) against
    the asked pose (metres, radians), near zero for every pose the arm's geometry can realise."""

    q: np.ndarray
    reachable: bool
    violations: tuple[str, ...]
    position_error: float
    rotation_error: float


def as_matrix(pose) -> np.ndarray:
    """A pose as a 4x4 matrix: a 4x4 is checked and returned, a 7-vector converted (unit quaternion)."""
    pose = np.asarray(pose, np.float64)
    if pose.shape == (7,):
        if not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be [x, y, z, qw, qx, qy, qz] with finite values, got {pose!r}")
        return pose_matrix(np.r_[pose[:3], unit_quaternions("pose [x, y, z, qw, qx, qy, qz]", pose[3:])])
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"pose must be a 4x4 homogeneous matrix or a 7-vector, got shape {pose.shape}")
    return pose


def inverse_kinematics(pose, q_ref=None) -> IKResult:
    """Joints that put the tool tip at ``pose`` (4x4 or 7-vector, in the PSM base frame), with a
    verdict: out-of-limit joints are reported, never clipped. ``q_ref`` picks, of the roll angles
    ``q4 + 2 pi k`` (the roll range spans 520 degrees), the one nearest its roll (default 0), so a
    trajectory solved pose by pose stays continuous.

    Raises:
      ValueError: a malformed pose, or one whose wrist-link direction is undefined (the yaw axis
        passes through the RCM).
    """
    t = as_matrix(pose)
    p, x = t[:3, 3], t[:3, 0]
    # The wrist link (pitch axis to yaw axis) is perpendicular to the yaw axis x, and the shaft
    # through the RCM (the origin) projects onto the plane through p normal to x along that link:
    # so the link points from p towards the origin's projection, and the pitch-axis point is
    # WRIST_LINK back along it.
    towards = p.dot(x) * x - p
    norm = float(np.linalg.norm(towards))
    if norm < 1e-9:
        raise ValueError("pose has its yaw axis through the remote centre of motion: the wrist is undefined")
    pitch_point = p + WRIST_LINK * towards / norm
    r = float(np.linalg.norm(pitch_point))
    shaft = pitch_point / r  # the insertion direction (z of joint 3's frame)
    q3 = r - PITCH_FROM_RCM
    # z3 = (sin q1 cos q2, -sin q2, -cos q1 cos q2) for this DH (cos q2 > 0 within the pitch limits)
    q2 = math.asin(float(np.clip(-shaft[1], -1.0, 1.0)))
    q1 = math.atan2(float(shaft[0]), float(-shaft[2]))
    r03 = forward_kinematics(np.array([q1, q2, q3, 0.0, 0.0, 0.0]), upto=3)[:3, :3]
    m = r03.T @ t[:3, :3]  # the tool tip's rotation in joint 3's frame
    # columns of m (derived from the DH above): x = (-c4 c5, -s4 c5, s5), row 3 = (s5, -s6 c5, c5 c6)
    q5 = math.asin(float(np.clip(m[2, 0], -1.0, 1.0)))
    q4 = math.atan2(float(-m[1, 0]), float(-m[0, 0]))
    q6 = math.atan2(float(-m[2, 1]), float(m[2, 2]))
    ref = 0.0 if q_ref is None else float(np.asarray(q_ref, np.float64)[3])
    q4 += 2.0 * math.pi * round((ref - q4) / (2.0 * math.pi))
    q = np.array([q1, q2, q3, q4, q5, q6])
    back = forward_kinematics(q)
    rot = back[:3, :3].T @ t[:3, :3]
    skew = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    rot_err = math.atan2(float(np.linalg.norm(skew)) / 2.0, (float(np.trace(rot)) - 1.0) / 2.0)  # accurate near 0
    out = (q < Q_MIN - 1e-12) | (q > Q_MAX + 1e-12)
    return IKResult(
        q=q,
        reachable=not out.any(),
        violations=tuple(n for n, o in zip(JOINT_NAMES, out) if o),
        position_error=float(np.linalg.norm(back[:3, 3] - t[:3, 3])),
        rotation_error=rot_err,
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


@dataclasses.dataclass(frozen=True)
class JointTrajectory:
    """A plan's poses as PSM joints: ``q`` ``[T, 6]``, ``reachable`` ``[T]`` (every joint within its
    limits), ``violations`` (per pose, the joints outside), and ``all_reachable``."""

    q: np.ndarray
    reachable: np.ndarray
    violations: tuple[tuple[str, ...], ...]

    @property
    def all_reachable(self) -> bool:
        return bool(self.reachable.all())

    @property
    def joint_path_length(self) -> np.ndarray:
        """Sum of ``|dq|`` per joint over the trajectory (rad, m for the insertion)."""
        return np.abs(np.diff(self.q, axis=0)).sum(0)


def joint_trajectory(base, poses, q_ref=None) -> JointTrajectory:
    """Joints of the PSM whose base (RCM) frame is ``base`` (7-vector or 4x4, in the frame of
    ``poses``) for tool-tip poses ``[T, 7]`` (e.g. ``Plan.trajectory("camera")`` with ``base`` in
    the camera frame); each pose's roll is taken nearest the previous pose's (the first: ``q_ref``)."""
    base_inv = np.linalg.inv(as_matrix(base))
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    qs, ok, bad, ref = [], [], [], q_ref
    for pose in poses:
        r = inverse_kinematics(base_inv @ pose_matrix(pose), ref)
        qs.append(r.q)
        ok.append(r.reachable)
        bad.append(r.violations)
        ref = r.q
    return JointTrajectory(np.stack(qs), np.array(ok), tuple(bad))


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
    frame) reaches tool-tip poses ``pos [3]``, ``quat [4]`` (wxyz) within every joint limit. The
    same closed form as :func:`inverse_kinematics` (the roll taken nearest zero, where its +-260
    degree range matters least), for checks inside jitted planners; vmap for batches."""
    import jax.numpy as jnp

    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    rot = jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    r = base_inv[:3, :3] @ rot
    p = base_inv[:3, :3] @ pos + base_inv[:3, 3]
    xa = r[:, 0]
    towards = jnp.dot(p, xa) * xa - p
    pitch_point = p + WRIST_LINK * towards / jnp.maximum(jnp.linalg.norm(towards), 1e-12)
    dist = jnp.linalg.norm(pitch_point)
    shaft = pitch_point / dist
    q3 = dist - PITCH_FROM_RCM
    q2 = jnp.arcsin(jnp.clip(-shaft[1], -1.0, 1.0))
    q1 = jnp.arctan2(shaft[0], -shaft[2])
    s1, c1, s2, c2 = jnp.sin(q1), jnp.cos(q1), jnp.sin(q2), jnp.cos(q2)
    r03 = jnp.array([[-s1 * s2, -c1, s1 * c2], [-c2, 0.0, -s2], [s2 * c1, -s1, -c1 * c2]])  # forward_kinematics(upto=3)
    m = r03.T @ r
    q5 = jnp.arcsin(jnp.clip(m[2, 0], -1.0, 1.0))
    q4 = jnp.arctan2(-m[1, 0], -m[0, 0])
    q6 = jnp.arctan2(-m[2, 1], m[2, 2])
    q = jnp.stack([q1, q2, q3, q4, q5, q6])
    return jnp.all((q >= jnp.asarray(Q_MIN)) & (q <= jnp.asarray(Q_MAX)))
