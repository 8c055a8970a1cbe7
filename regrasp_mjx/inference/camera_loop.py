"""The closed loop of a lab whose camera sees both tools and the needle (ours, issue 45): frame by
frame, on the host, with each step on the lean CPU path.

A camera-to-base calibration error of either arm cancels here (:mod:`regrasp_mjx.robot.robot_errors`,
the ``camera`` view): the state is built from three poses measured in one image, and each step is
sent to the arm as a motion in its own tool frame, ``FK(q) @ motion`` in its base frame, which no
camera-to-base transform enters. Between frames the regrasping tool's fused view is moved by the
motion its kinematics report (by default the motion last commanded), so every frame's view of it
can be averaged like the needle's (which does not move in the grasping tool).

    loop = policy.camera_loop()  # the policy's own warm-up frames and stop tolerance
    for frame in camera:  # camera-frame 7-vectors [x y z qw qx qy qz] of both tools and the needle
        command = loop.update(frame.grasping_ee, frame.regrasping_ee, frame.needle)
        if command.at_goal:
            break  # the camera says the regrasp pose is reached: close the jaws
        if command.ready:
            arm.move_to(arm.forward_kinematics() @ command.motion)  # in the arm's own base frame
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from regrasp_mjx.inference.queries import PoseError, batch_poses
from regrasp_mjx.robot import dvrk

# The most the needle's estimate (in the grasping tool's frame, where the needle is held) may move from
# its fused view between frames [m]: held in the jaws it moves by the estimate's noise (millimetres), so
# a jump past this is a mismatched or mislabelled detection, refused rather than averaged in.
MAX_NEEDLE_JUMP_M = 0.05


def _matrix(pose: Any, name: str) -> np.ndarray:
    try:
        return dvrk.as_matrix(pose, name)
    except ValueError as err:
        raise PoseError(str(err)) from None


class Command(NamedTuple):
    """What :meth:`CameraLoop.update` returns for one frame."""

    ready: bool  # False while the warm-up frames are fused (hold still: motion is the identity)
    at_goal: bool  # the fused view says the goal grasp is reached (stop; motion is the identity)
    motion: np.ndarray  # 4x4: the regrasping tool's motion in its own frame (metres)
    action: np.ndarray  # [6]: the policy's action (zero when not moving)
    needle: np.ndarray  # [7]: the fused needle in the seen grasping tool's frame e_g
    ee: np.ndarray  # [7]: the fused regrasping tool in that frame (before this motion)
    t: int  # steps taken before this one


def _vector(m: np.ndarray) -> np.ndarray:
    r = m[:3, :3]
    w = np.sqrt(max(1.0 + np.trace(r), 1e-12)) / 2.0
    if w > 0.1:
        q = np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])
    else:  # near a half turn: from the largest diagonal element
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-12)) * 2.0
        q = np.empty(4)
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = s / 4.0
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = q / np.linalg.norm(q)
    return np.concatenate((m[:3, 3], q if q[0] >= 0 else -q))


def _inverse(m: np.ndarray) -> np.ndarray:
    """A rigid transform's inverse (the rotation transposed)."""
    out = np.empty((4, 4))
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -(m[:3, :3].T @ m[:3, 3])
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _mean(mean: np.ndarray, count: int, new: np.ndarray) -> np.ndarray:
    """The running mean of ``count`` poses with ``new`` added (positions averaged, the quaternions'
    chordal mean on the mean's hemisphere), as the simulated loop fuses them."""
    w = 1.0 / (count + 1.0)
    q = new[3:] if new[3:] @ mean[3:] >= 0 else -new[3:]
    quat = (1.0 - w) * mean[3:] + w * q
    return np.concatenate((mean[:3] + w * (new[:3] - mean[:3]), quat / np.linalg.norm(quat)))


class CameraLoop:
    """A regrasp driven by camera frames of both tools and the needle (see the module docstring).

    ``CameraLoop(policy, goal_in_needle=None, warmup_frames=None, stop_tolerance=None,
    shield=True, **task)``: the goal end-effector pose in the needle's frame (a 7-vector; None: the
    task's goal grasp, ``task``'s keywords as for ``Policy.closed_loop_step``), which moves with the
    needle's fused view; the frames fused before the first step and the fraction of the success
    tolerances the fused view must be within to stop (None: the policy's own,
    ``Policy.closed_loop_defaults``).
    """

    def __init__(
        self,
        policy: Any,
        goal_in_needle: Any = None,
        warmup_frames: int | None = None,
        stop_tolerance: float | None = None,
        shield: bool = True,
        **task: Any,
    ):
        defaults = policy.closed_loop_defaults
        self.policy = policy
        self.warmup = defaults["warmup_frames"] if warmup_frames is None else warmup_frames
        self.stop = defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
        if not (isinstance(self.warmup, int) and self.warmup >= 1):
            raise ValueError(f"warmup_frames={warmup_frames!r} is not accepted: an integer >= 1")
        if not (np.isfinite(self.stop) and 0.0 < self.stop <= 1.0):
            raise ValueError(f"stop_tolerance={stop_tolerance!r} is not accepted: a fraction in (0, 1]")
        self.shield, self.task = shield, task
        self.goal = None if goal_in_needle is None else _matrix(goal_in_needle, "goal_in_needle")
        self.frames, self.t = 0, 0
        self.needle: np.ndarray | None = None
        self.ee: np.ndarray | None = None
        self.commanded = np.eye(4)

    def update(self, grasping_ee: Any, regrasping_ee: Any, needle: Any, moved: Any = None) -> Command:
        """One camera frame: the camera-frame poses (7-vectors) of the grasping tool, the
        regrasping tool and the needle; ``moved`` (4x4 or 7-vector), the regrasping tool's motion
        in its own frame since the last frame as its kinematics report it (``FK(q_last)^-1
        FK(q_now)``; default: the motion last commanded). Returns the :class:`Command` for this
        frame. Raises :class:`~regrasp_mjx.inference.queries.PoseError` on a bad pose (``moved``: NaN
        or not rigid), and on a needle whose estimate moved more than :data:`MAX_NEEDLE_JUMP_M` from its
        fused view (the frame is then left out: the loop's state is unchanged)."""
        (g, x, n), single = batch_poses(grasping_ee=grasping_ee, regrasping_ee=regrasping_ee, needle=needle)
        if not single:
            raise ValueError("CameraLoop.update takes one frame: three 7-vectors, not batches")
        g_inv = _inverse(dvrk.pose_matrix(g[0]))
        needle_eg = _vector(g_inv @ dvrk.pose_matrix(n[0]))
        ee_eg = _vector(g_inv @ dvrk.pose_matrix(x[0]))
        motion = self.commanded if moved is None else _matrix(moved, "moved")
        if (
            self.needle is not None
            and (jump := float(np.linalg.norm(needle_eg[:3] - self.needle[:3]))) > MAX_NEEDLE_JUMP_M
        ):
            raise PoseError(
                f"needle moved {jump * 1e3:.1f} mm in the grasping tool's frame since the last frames (fused view); "
                f"accepted: at most {MAX_NEEDLE_JUMP_M * 1e3:g} mm between frames (MAX_NEEDLE_JUMP_M; it is held)"
            )
        if self.frames == 0:
            self.needle, self.ee = needle_eg, ee_eg
        else:
            moved_ee = _vector(dvrk.pose_matrix(self.ee) @ motion)
            self.needle = _mean(self.needle, self.frames, needle_eg)
            self.ee = _mean(moved_ee, self.frames, ee_eg)
        self.frames += 1
        self.commanded = np.eye(4)
        if self.frames < self.warmup:
            return Command(False, False, np.eye(4), np.zeros(6), self.needle, self.ee, self.t)
        goal = None if self.goal is None else _vector(dvrk.pose_matrix(self.needle) @ self.goal)
        action, next_ee, at_goal = self.policy.closed_loop_step(
            self.needle, self.ee, goal, t=self.t, shield=self.shield, stop_tolerance=self.stop, **self.task
        )
        if at_goal:
            return Command(True, True, np.eye(4), np.zeros(6), self.needle, self.ee, self.t)
        self.commanded = _inverse(dvrk.pose_matrix(self.ee)) @ dvrk.pose_matrix(next_ee)
        self.t += 1
        return Command(True, False, self.commanded, np.asarray(action), self.needle, self.ee, self.t - 1)
