"""The closed loop of a lab whose camera sees both tools and the needle (ours, issue 45): frame by
frame, on the host, with each step on the lean CPU path.

A camera-to-base calibration error of either arm cancels here (:mod:`regrasp_mjx.robot.robot_errors`,
the ``camera`` view): the state is built from three poses measured in one image, and each step is
sent to the arm as a motion in its own tool frame, ``FK(q) @ motion`` in its base frame, which no
camera-to-base transform enters. Between frames the regrasping tool's fused view is moved by the
motion its kinematics report (by default the motion last commanded), so every frame's view of it
can be averaged like the needle's (which does not move in the grasping tool).

    loop = policy.camera_loop(camera=errors)  # the policy's own settings; errors: your camera's (CameraErrors)
    for frame in camera:  # camera-frame 7-vectors [x y z qw qx qy qz] of both tools and the needle
        command = loop.update(frame.grasping_ee, frame.regrasping_ee, frame.needle)
        if command.at_goal:
            break  # the camera says the regrasp pose is reached: close the jaws
        if command.opening:  # jaws that open on the way (issue 67): open them first, the arm at rest
            arm.open_jaw(command.jaw_deg)  # your arm API: the dVRK's jaw/move_jp (radians), waited for
        if command.ready:  # False while frames are fused before a decision (the warm-up, a look): hold still
            arm.move_to(arm.forward_kinematics() @ command.motion)  # in the arm's own base frame

Jaws that open on the way (a policy with ``EnvConfig.jaw_open_deg``, issue 67): the loop keeps the
jaws' opening as its state and opens them as the simulated loop does
(:func:`regrasp_mjx.inference.closed_loop.make_executor`): before the first step whose view leaves the
opening sweep the environment's margin (``jaw_open_margin_mm``) plus ``jaw_sigmas`` standard
deviations of the view's known error at the jaws (:func:`regrasp_mjx.envs.camera_errors.view_sd_mm`,
from the ``camera``'s error sizes and the frames fused), the sweep proved clear on the fused view by
the environment's test (the lean path's :func:`regrasp_mjx.inference.lean_rollout.opening_keeps` on
the CPU, :meth:`regrasp_mjx.envs.env.RegraspEnv.opening_room` elsewhere). :class:`Command` says what
the jaw must do: ``jaw_deg``, the opening to command before this step's motion, and ``opening``, this
step opens them (open the jaw with the arm at rest, then move: the sweep was proved with the tool still).

Looking before the last moves (``look_frames``, the policy's own by default): as the simulated loop,
before the last moves (the first time the view comes within ``closed_loop.NEAR`` times the stop
tolerances of the goal) and before declaring the goal reached (the first time the view says so), the
loop holds still and fuses frames while twice the fused estimate's standard deviation (from the
``camera``'s known error sizes) exceeds the room between the stop and the success tolerance, at most
``look_frames`` frames a look: each such frame's :class:`Command` is a hold (``ready`` False,
``looking`` True) and is counted in ``looked``. Both rules need the camera's error sizes: without
``camera`` the loop knows of no error, so it never looks and opens the jaws at the environment's
margin alone (as ``Policy.execute`` without errors).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_errors import CameraErrors
from regrasp_mjx.inference import jaw_opening
from regrasp_mjx.inference.closed_loop import MAX_LOOK, NEAR, tolerances
from regrasp_mjx.inference.plans import auto_engine, default_goal
from regrasp_mjx.inference.queries import PoseError, TaskSpec, batch_poses
from regrasp_mjx.robot import dvrk
from regrasp_mjx.world import jaw
from regrasp_mjx.world.scene import load_scene

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

    ready: bool  # False while frames are fused before a decision (warm-up, a look): hold still, motion the identity
    at_goal: bool  # the fused view says the goal grasp is reached (stop; motion is the identity)
    motion: np.ndarray  # 4x4: the regrasping tool's motion in its own frame (metres)
    action: np.ndarray  # [6]: the policy's action (zero when not moving)
    needle: np.ndarray  # [7]: the fused needle in the seen grasping tool's frame e_g
    ee: np.ndarray  # [7]: the fused regrasping tool in that frame (before this motion)
    t: int  # steps taken before this one
    jaw_deg: float  # the regrasping jaws' opening to command before this motion [deg] (the PSM's jaw joint)
    opening: bool  # this step opens the jaws (to jaw_deg): open them with the arm at rest, then move
    looking: bool  # a look is under way: hold still, the fused view too uncertain to go on (more frames fused)
    looked: int  # the frames fused in looks so far (this one, where it is one)


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


def _fused_variance(n: float, p) -> float:
    """:func:`regrasp_mjx.envs.camera_errors.fused_variance` of one count in float64 (mm^2)."""
    rho = np.exp(-1.0 / p[2])
    pairs = n * (1.0 + rho) / (1.0 - rho) - 2.0 * rho * (1.0 - rho**n) / (1.0 - rho) ** 2
    return p[3] ** 2 / n + p[1] ** 2 * pairs / n**2


def _view_sd_mm(n: float, pn, pt, depth_factor: float, reach: float, needle_radius: float, ee_pos) -> float:
    """:func:`regrasp_mjx.envs.camera_errors.view_sd_mm` of one view in float64 (mm)."""

    def part(p, lever_m):
        var = p[0] ** 2 / 3.0 + _fused_variance(n, p)
        return (depth_factor**2 + (np.radians(p[4]) * lever_m * 1e3) ** 2) * var

    lever_g = float(np.linalg.norm(ee_pos))
    return float(np.sqrt(part(pn, needle_radius) + part(pt, reach) + part(pt, lever_g)))


def _goal_error(needle: np.ndarray, ee: np.ndarray, goal_needle: np.ndarray) -> tuple[float, float]:
    """The distance [m] and angle [rad] of the needle seen from ``ee`` (7-vectors) to ``goal_needle``
    (4x4, the needle seen from the goal), as :func:`regrasp_mjx.inference.closed_loop._at_goal` tests them."""
    current = _inverse(dvrk.pose_matrix(ee)) @ dvrk.pose_matrix(needle)
    turn = np.eye(4)
    turn[:3, :3] = goal_needle[:3, :3] @ current[:3, :3].T
    q = _vector(turn)[3:]  # the angle of q* q^-1: 2 atan2(|v|, |w|)
    angle = 2.0 * np.arctan2(np.linalg.norm(q[1:]), abs(q[0]))
    return float(np.linalg.norm(goal_needle[:3, 3] - current[:3, 3])), float(angle)


class CameraLoop:
    """A regrasp driven by camera frames of both tools and the needle (see the module docstring).

    ``CameraLoop(policy, goal_in_needle=None, warmup_frames=None, stop_tolerance=None,
    shield=True, look_frames=None, camera=None, jaw_sigmas=None, **task)``: the goal end-effector pose
    in the needle's frame (a 7-vector or 4x4; None: the task's goal grasp, ``task``'s keywords as for
    ``Policy.closed_loop_step``), which moves with the needle's fused view; the frames fused before the
    first step and the fraction of the success tolerances the fused view must be within to stop; the
    frames a look may take at most (0: never look); the camera's known error sizes (a
    :class:`~regrasp_mjx.envs.camera_errors.CameraErrors` or a preset's name; None: none known), which
    the looking and the jaws' margin are decided by; and the standard deviations of the view's known
    error the jaws' opening sweep must keep beyond the environment's margin. None: the policy's own
    (``Policy.closed_loop_defaults``). A ``look_frames`` above 0 given without ``camera`` is refused (it
    could never look); without ``camera`` the policy's own never looks either (as ``Policy.execute``
    without errors).
    """

    def __init__(
        self,
        policy: Any,
        goal_in_needle: Any = None,
        warmup_frames: int | None = None,
        stop_tolerance: float | None = None,
        shield: bool = True,
        look_frames: int | None = None,
        camera: CameraErrors | str | None = None,
        jaw_sigmas: float | None = None,
        **task: Any,
    ):
        defaults = policy.closed_loop_defaults
        self.policy = policy
        self.warmup = defaults["warmup_frames"] if warmup_frames is None else warmup_frames
        self.stop = defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
        self.look = defaults["look_frames"] if look_frames is None else look_frames
        if not (isinstance(self.warmup, int) and self.warmup >= 1):
            raise ValueError(f"warmup_frames={warmup_frames!r} is not accepted: an integer >= 1")
        if not (np.isfinite(self.stop) and 0.0 < self.stop <= 1.0):
            raise ValueError(f"stop_tolerance={stop_tolerance!r} is not accepted: a fraction in (0, 1]")
        if not (isinstance(self.look, int) and not isinstance(self.look, bool) and 0 <= self.look <= MAX_LOOK):
            raise ValueError(f"look_frames={look_frames!r} is not accepted: an integer in [0, {MAX_LOOK}]")
        if camera is None and look_frames:
            raise ValueError(
                f"look_frames={look_frames!r} is not accepted without camera=: the loop looks while its fused "
                "estimate is too uncertain by the camera's known error sizes; pass camera= (a CameraErrors or "
                f"one of {tuple(camera_presets.PRESETS)})"
            )
        if isinstance(camera, str):
            camera = camera_presets.preset(camera)
        if not isinstance(camera, (CameraErrors, type(None))):
            raise ValueError(
                f"camera={camera!r} is not accepted: a CameraErrors, one of {tuple(camera_presets.PRESETS)} or None"
            )
        self.camera = CameraErrors() if camera is None else camera  # None: no error known
        ladder, self.jaw_sigmas = jaw_opening.check(policy, None, jaw_sigmas)
        config = policy.env_config
        if config.jaw_open_deg is None and ladder > config.scene.jaw_angle_deg:
            # Policy.execute opens such a policy's jaws once, before the first move, to the widest of a ladder
            # of openings its view allows, each planned in its own scene: not this loop's (it would run with
            # the jaws at the scene's opening, another loop than the file's)
            raise ValueError(
                f"this policy's file opens its jaws before the first move (closed_loop.jaw_deg {ladder}: "
                "Policy.execute's ladder of openings), which CameraLoop does not choose; accepted: a policy whose "
                "jaws stay or open on the way (EnvConfig.jaw_open_deg)"
            )
        self.shield, self.task = shield, task
        self.goal = None if goal_in_needle is None else _matrix(goal_in_needle, "goal_in_needle")
        self.horizon = config.horizon
        grasp, radii = policy.task_ranges.resolve(1, TaskSpec.of(task))
        self.radii = np.array(radii[0], np.float64)  # the needle's radius and wire [m]
        goal = self.goal
        if goal is None:  # the task's goal grasp, in the needle's frame
            goal = dvrk.pose_matrix(default_goal(np.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]), grasp, radii)[0])
        self.goal_needle = _inverse(goal)  # the needle seen from the goal: what looking compares with
        numbers = np.asarray(self.camera.numbers(), np.float64)
        self.pn, self.pt, self.depth_factor = numbers[:5], numbers[5:10], float(numbers[10])
        success, self.stop_tol = tolerances(config, 1.0), tolerances(config, float(self.stop))
        self.look_room = success[0] - self.stop_tol[0]  # [m] the stop tolerance's room inside the success test
        self.base_deg = float(config.scene.jaw_angle_deg)
        self.open_deg = None if config.jaw_open_deg is None else float(config.jaw_open_deg)
        if self.open_deg is not None:
            self.reach = jaw.jaw_reach(load_scene(config.scene))
            self.jaw_margin = config.jaw_open_margin_mm * 1e-3  # the environment's [m]
        self.frames, self.t = 0, 0
        self.needle: np.ndarray | None = None
        self.ee: np.ndarray | None = None
        self.commanded = np.eye(4)
        self.jaw_deg = self.base_deg  # the jaws' opening now
        self.opened_at = -1  # the step the jaws opened before (-1: not yet)
        self.looked = 0  # frames spent looking
        self.looked_near = self.looked_stop = False  # whether the view came near the goal, said stop (a look each)
        self.look_frame: int | None = None  # frames of the look under way (None: none)

    def unsure(self) -> bool:
        """Whether the fused view is too uncertain to stop on, as the simulated loop decides it: twice
        its standard deviation on the worst axis (the camera's depth; the needle's and the tools'
        errors less their biases after the frames fused, from the camera's known sizes) exceeds the
        room the stop tolerance keeps inside the success tolerance."""
        n = float(self.frames)
        var = _fused_variance(n, self.pn) + _fused_variance(n, self.pt)
        return 2.0 * self.depth_factor * np.sqrt(var) * 1e-3 > self.look_room

    def _near(self) -> tuple[bool, bool]:
        """Whether the fused view says the goal is reached (within the stop tolerances) and whether it
        is within ``NEAR`` times them (about to make its last moves)."""
        dist, angle = _goal_error(self.needle, self.ee, self.goal_needle)
        stopping = dist <= self.stop_tol[0] and angle <= self.stop_tol[1]
        return stopping, bool(dist <= NEAR * self.stop_tol[0] and angle <= NEAR * self.stop_tol[1])

    def _opens(self) -> bool:
        """Whether the jaws open before this step: at the scene's opening, and the fused view leaves the
        opening sweep the environment's margin plus ``jaw_sigmas`` standard deviations of its known
        error at the jaws (the simulated loop's rule)."""
        if self.open_deg is None or self.jaw_deg >= self.open_deg:
            return False
        sd = _view_sd_mm(
            float(self.frames), self.pn, self.pt, self.depth_factor, self.reach, float(self.radii[0]), self.ee[:3]
        )
        margin = np.float32(self.jaw_margin + self.jaw_sigmas * sd * 1e-3)  # compared in float32, as there
        if auto_engine(1, self.policy) == "lean":
            return self.policy.lean(self.shield).opening_keeps(self.needle, self.ee, self.radii, margin)
        room = jaw_opening.opening_room(self.policy, self.needle[None], self.ee[None, None], self.radii[None])
        return bool(room[0, 0] >= margin)

    def _hold(self, looking: bool, ready: bool = False, done: bool = False) -> Command:
        """No motion this frame: warming up or looking (``ready`` False), or at the goal (both True)."""
        return Command(
            ready,
            done,
            np.eye(4),
            np.zeros(6),
            self.needle,
            self.ee,
            self.t,
            self.jaw_deg,
            False,
            looking,
            self.looked,
        )

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
            return self._hold(False)
        if self.look_frame is not None:  # a frame of the look under way
            self.looked += 1
            self.look_frame += 1
            if self.look_frame < self.look and self.unsure():
                return self._hold(True)
            self.look_frame = None  # the look ends: decide on this view
        elif self.look and self.t < self.horizon:
            # the simulated loop's rule: look the first time the view is near the goal, and the first time
            # it says the goal is reached, while the fused view is too uncertain to stop on
            stopping, near = self._near()
            first = (stopping and not self.looked_stop) or (near and not self.looked_near)
            self.looked_near |= near
            self.looked_stop |= stopping
            if first and self.unsure():
                self.look_frame = 0
                return self._hold(True)
        goal = None if self.goal is None else _vector(dvrk.pose_matrix(self.needle) @ self.goal)
        jaws = {} if self.open_deg is None else {"jaw_deg": self.jaw_deg}
        action, next_ee, at_goal, *_ = self.policy.closed_loop_step(
            self.needle, self.ee, goal, t=self.t, shield=self.shield, stop_tolerance=self.stop, **jaws, **self.task
        )
        if at_goal:
            return self._hold(False, ready=True, done=True)
        # the jaws: opened before this motion where the view leaves their sweep its margin (the action was
        # chosen with them as the environment's own rule has them on the view, as in the simulated loop)
        opening = self._opens()
        if opening:
            self.jaw_deg, self.opened_at = self.open_deg, self.t
        self.commanded = _inverse(dvrk.pose_matrix(self.ee)) @ dvrk.pose_matrix(next_ee)
        self.t += 1
        return Command(
            True,
            False,
            self.commanded,
            np.asarray(action),
            self.needle,
            self.ee,
            self.t - 1,
            self.jaw_deg,
            opening,
            False,
            self.looked,
        )
