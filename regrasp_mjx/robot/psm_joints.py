"""A plan's poses as dVRK PSM joints: continuous joint trajectories and how well an arm follows a
batch of plans (:func:`reachability`), through :mod:`regrasp_mjx.robot.dvrk`'s kinematics."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from regrasp_mjx.robot.dvrk import Q_MAX, Q_MIN, as_matrix, inverse_kinematics, pose_matrix


@dataclasses.dataclass(frozen=True)
class JointTrajectory:
    """A plan's poses as PSM joints: ``q`` ``[T, 6]``, ``reachable`` ``[T]`` (every joint within its
    limits and the pose realised, :class:`IKResult`), ``violations`` (per pose, the joints outside),
    the residuals ``position_error`` and ``rotation_error`` ``[T]`` (m, rad), and ``all_reachable``."""

    q: np.ndarray
    reachable: np.ndarray
    violations: tuple[tuple[str, ...], ...]
    position_error: np.ndarray
    rotation_error: np.ndarray

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
