"""A plan's poses as dVRK PSM joints: continuous joint trajectories and how well an arm follows a
batch of plans (:func:`reachability`), through :mod:`regrasp_mjx.robot.dvrk`'s kinematics; the
regrasping tool's jaw, the PSM's seventh joint, as a plan's :class:`JawTrack` (issue 67: where the
jaws open on the way; their limits and timing in :mod:`regrasp_mjx.robot.psm_timing`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from regrasp_mjx.core.config import JAW_MAX_DEG, is_number
from regrasp_mjx.robot.dvrk import Q_MAX, Q_MIN, as_matrix, inverse_kinematics, pose_matrix

JAW_MIN_DEG = 0.0  # the jaw joint closed (the Large Needle Driver's opening: 0 to JAW_MAX_DEG, 80)


@dataclasses.dataclass(frozen=True)
class JointTrajectory:
    """A plan's poses as PSM joints: ``q`` ``[T, 6]``, ``reachable`` ``[T]`` (every joint within its
    limits and the pose realised, :class:`IKResult`), ``violations`` (per pose, the joints outside),
    the residuals ``position_error`` and ``rotation_error`` ``[T]`` (m, rad), and ``all_reachable``;
    ``jaw``, the jaw joint's track where the policy's jaws open on the way (:class:`JawTrack`: where
    it opens; ``jaw.waypoints(q)`` the seven joints), else None (the scene's fixed opening throughout)."""

    q: np.ndarray
    reachable: np.ndarray
    violations: tuple[tuple[str, ...], ...]
    position_error: np.ndarray
    rotation_error: np.ndarray
    jaw: JawTrack | None = None

    @property
    def all_reachable(self) -> bool:
        return bool(self.reachable.all())

    @property
    def joint_path_length(self) -> np.ndarray:
        """Sum of ``|dq|`` per joint over the trajectory (rad, m for the insertion)."""
        return np.abs(np.diff(self.q, axis=0)).sum(0)


@dataclasses.dataclass(frozen=True)
class JawTrack:
    """The jaw along a plan of ``poses`` poses: at ``from_deg`` (the scene's opening) up to the pose
    ``opens_at``, where it opens to ``to_deg`` with the arm holding still, then kept to the goal
    (``opens_at`` -1: never opened, ``to_deg`` then the opening it would have had)."""

    from_deg: float
    to_deg: float
    opens_at: int
    poses: int

    def __post_init__(self):
        for name in ("from_deg", "to_deg"):
            value = getattr(self, name)
            if not (is_number(value) and JAW_MIN_DEG <= value <= JAW_MAX_DEG):
                raise ValueError(
                    f"{name}={value!r} is not accepted: the jaw's opening in degrees, from {JAW_MIN_DEG:g} "
                    f"(closed) to the Large Needle Driver's {JAW_MAX_DEG:g}"
                )
        if not (isinstance(self.poses, (int, np.integer)) and self.poses >= 1):
            raise ValueError(f"poses={self.poses!r} is not accepted: the plan's number of poses, at least 1")
        k = self.opens_at
        if not (isinstance(k, (int, np.integer)) and -1 <= k <= self.poses - 2):
            raise ValueError(
                f"opens_at={k!r} is not accepted: -1 (never) or the pose a step leaves, 0 to {self.poses - 2} "
                f"for {self.poses} poses"
            )
        if k >= 0 and not self.to_deg > self.from_deg:
            raise ValueError(
                f"to_deg={self.to_deg!r} is not accepted where the jaws open (opens_at={k}): wider than "
                f"from_deg={self.from_deg!r}"
            )

    @classmethod
    def of(cls, env_config, opens_at: int, poses: int) -> JawTrack:
        """The track of a plan of ``poses`` poses of a policy whose environment is ``env_config``
        (from its scene's opening to its ``jaw_open_deg``), opening at the pose ``opens_at``."""
        base = float(env_config.scene.jaw_angle_deg)
        wide = base if env_config.jaw_open_deg is None else float(env_config.jaw_open_deg)
        return cls(base, wide, int(opens_at), int(poses))

    @property
    def opens(self) -> bool:
        return self.opens_at >= 0

    @property
    def deg(self) -> np.ndarray:
        """``[poses]``: the opening each pose is left with (the step from it moves at it; the last
        pose's, the one the tool arrives with)."""
        wide = self.opens & (np.arange(self.poses) >= self.opens_at)
        return np.where(wide, self.to_deg, self.from_deg).astype(np.float64)

    def waypoints(self, q) -> np.ndarray:
        """The arm's joint waypoints ``q`` ``[poses, 6]`` with the jaw as a seventh joint (rad):
        ``[poses + 1, 7]`` where it opens, the pose ``opens_at`` twice (arrived at ``from_deg``, left
        at ``to_deg``: only the jaw moves between them), else ``[poses, 7]``."""
        q = np.asarray(q, np.float64)
        if q.shape != (self.poses, 6):
            raise ValueError(f"q of shape {q.shape} is not accepted: [{self.poses}, 6], one row a pose of the track")
        wide = self.opens & (np.arange(self.poses) > self.opens_at)  # arrived at with the jaws open
        arrive = np.radians(np.where(wide, self.to_deg, self.from_deg))
        out = np.concatenate([q, arrive[:, None]], axis=1)
        if self.opens:
            k = self.opens_at
            out = np.insert(out, k + 1, np.r_[q[k], math.radians(self.to_deg)], axis=0)
        return out


def joint_trajectory(base, poses, q_ref=None) -> JointTrajectory:
    """Joints of the PSM whose base (RCM) frame is ``base`` (7-vector or 4x4, in the frame of
    ``poses``) for tool-tip poses ``[T, 7]`` (e.g. ``Plan.trajectory("camera")`` with ``base`` in
    the camera frame). Continuous: each pose's roll is the one nearest the previous pose's, never a
    turn away (:func:`inverse_kinematics`). The first pose's roll is the one nearest ``q_ref``'s;
    without ``q_ref``, of its turns within the limits (one or two: the range spans 520 degrees) the
    one that keeps the most poses within them, then the one nearest 0."""
    base_inv = np.linalg.inv(as_matrix(base, "base"))
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    targets = [base_inv @ pose_matrix(pose) for pose in poses]

    def walk(first):
        results = [first]
        for t in targets[1:]:
            results.append(inverse_kinematics(t, results[-1].q))
        return results

    first = inverse_kinematics(targets[0], q_ref)
    results = walk(first)
    if q_ref is None:  # the other turn of the first roll, where it is within the limits too
        other = first.q.copy()
        other[3] -= math.copysign(2.0 * math.pi, other[3])
        if Q_MIN[3] <= other[3] <= Q_MAX[3]:
            alternative = walk(inverse_kinematics(targets[0], other))
            if sum(r.reachable for r in alternative) > sum(r.reachable for r in results):
                results = alternative
    return JointTrajectory(
        np.stack([r.q for r in results]),
        np.array([r.reachable for r in results]),
        tuple(r.violations for r in results),
        np.array([r.position_error for r in results]),
        np.array([r.rotation_error for r in results]),
    )


def reachability(plan, bases) -> dict:
    """How well a PSM follows a batch of plans (``Plan``): each successful plan's poses as joints
    (:func:`joint_trajectory`) from its RCM base (``bases``: one 4x4 for every plan, or a callable
    of the plan's row giving its own). Returns the plans counted, the share whose every pose is within
    the joint limits, the out-of-limit poses by joint and each joint's median path length (degrees,
    mm for the insertion)."""
    ok, lengths, bad = [], [], {}
    for i in np.nonzero(plan.success)[0]:
        traj = joint_trajectory(bases(i) if callable(bases) else bases, plan.poses[i][: plan.steps[i] + 1])
        ok.append(traj.all_reachable)
        lengths.append(traj.joint_path_length)
        for j in (j for names in traj.violations for j in names):
            bad[j] = bad.get(j, 0) + 1
    median = np.median(np.reshape(lengths, (-1, 6)), axis=0)
    scale = np.where(np.arange(6) == 2, 1e3, 180 / np.pi)  # the insertion in mm, the rest in degrees
    names = ("outer_yaw_deg", "outer_pitch_deg", "insertion_mm", "roll_deg", "wrist_pitch_deg", "wrist_yaw_deg")
    return {
        "plans": len(ok),
        "all_reachable_share": float(np.mean(ok)) if ok else float("nan"),
        "out_of_limit_poses_by_joint": bad,
        "joint_path_median": {n: float(v) for n, v in zip(names, median * scale)},
    }
