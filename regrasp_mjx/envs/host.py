"""The same task on the host: CPU MuJoCo, one thread, the same MJCF, geoms and filtering.

:class:`HostChecker` is the collision checker that the OMPL planners call; :class:`HostEnv` steps
the MDP exactly as :class:`regrasp_mjx.envs.env.RegraspEnv` does (same continuous collision test, reward and success
test), one problem at a time, for cross-checks and as the CPU baseline of the benchmarks.
Quaternion and pose arithmetic uses MuJoCo's own ``mju_*`` functions.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from regrasp_mjx.core.config import EnvConfig, is_number, require
from regrasp_mjx.core.geometry import segment_gap
from regrasp_mjx.world import continuous
from regrasp_mjx.world.scene import Scene, load_scene, needle_scene


def quat_mul(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(q1, float), np.asarray(q2, float))
    return out


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    out = np.array([1.0, 0.0, 0.0, 0.0])
    angle = float(np.linalg.norm(rotvec))
    if angle > 0.0:
        mujoco.mju_axisAngle2Quat(out, np.asarray(rotvec, float) / angle, angle)
    return out


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]], float)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """``log`` of a unit quaternion: the shortest rotation vector (angle in [0, pi])."""
    q = canonical(np.asarray(q, float))
    norm = float(np.linalg.norm(q[1:]))
    if norm < 1e-12:
        return 2.0 * q[1:]
    return q[1:] / norm * 2.0 * math.atan2(norm, q[0])


def canonical(q: np.ndarray) -> np.ndarray:
    return -q if q[0] < 0 else q


def relative(a_pos, a_quat, b_pos, b_quat) -> tuple[np.ndarray, np.ndarray]:
    """Pose b in frame a, both given in one frame: ``T_a_b = T_w_a^-1 T_w_b``."""
    inv_pos, inv_quat = np.empty(3), np.empty(4)
    mujoco.mju_negPose(inv_pos, inv_quat, np.asarray(a_pos, float), np.asarray(a_quat, float))
    pos, quat = np.empty(3), np.empty(4)
    mujoco.mju_mulPose(pos, quat, inv_pos, inv_quat, np.asarray(b_pos, float), np.asarray(b_quat, float))
    return pos, canonical(quat)


def quat_angle(q1: np.ndarray, q2: np.ndarray) -> float:
    """Angle of ``q1 q2^-1`` in [0, pi]."""
    d = quat_mul(q1, quat_conj(q2))
    return 2.0 * math.atan2(float(np.linalg.norm(d[1:])), abs(float(d[0])))


MARGIN_ACCEPTED = "a margin >= 0 in millimetres"  # what a checker's clearance_mm may be


class HostChecker:
    """Collision verdicts and clearances for a needle pose and a regrasping end-effector pose.

    ``clearance_mm`` (kept in metres as ``margin``): a pose collides when a counted pair is closer
    than this (0: when it penetrates), as ``EnvConfig.clearance_mm`` in :class:`regrasp_mjx.envs.env.RegraspEnv`.
    Not thread-safe (it owns one ``MjData``); give each worker process its own.
    """

    def __init__(self, scene: Scene | None = None, clearance_mm: float = 0.0):
        require(is_number(clearance_mm) and clearance_mm >= 0.0, "clearance_mm", clearance_mm, MARGIN_ACCEPTED)
        self.scene = scene if scene is not None else load_scene()
        self.model = self.scene.model
        self.data = mujoco.MjData(self.model)
        self.clearance_mm = float(clearance_mm)
        self.margin = self.clearance_mm * 1e-3
        # for motion_collides: each tool capsule's lever; the pairs' geoms, tool by tool
        frames = self.scene.capsule_frames
        self.levers = continuous.levers(frames.tool_ends)
        self._tool_geoms, self._other_geoms = np.array(frames.tool_ids), np.array(frames.other_ids)

    def for_needle(self, radius: float | None, wire: float | None) -> HostChecker:
        """A checker of the same margin around another needle (radius and wire radius [m]; None
        keeps this one's): this checker itself when the needle is its scene's."""
        scene = needle_scene(self.scene, radius, wire)
        return self if scene is self.scene else HostChecker(scene, self.clearance_mm)

    def _set(self, needle_pos, needle_quat, ee_pos, ee_quat) -> None:
        self.data.qpos[:] = self.scene.qpos(
            np.asarray(needle_pos, float),
            np.asarray(needle_quat, float),
            np.asarray(ee_pos, float),
            np.asarray(ee_quat, float),
        )
        mujoco.mj_kinematics(self.model, self.data)

    def collides(self, needle_pos, needle_quat, ee_pos, ee_quat) -> bool:
        """True when a counted pair penetrates (MuJoCo's broad and narrow phase, margin 0) or, with a
        clearance margin, comes closer than it (``mj_geomDistance`` of every pair)."""
        if self.margin > 0.0:
            distmax = 2.0 * self.margin  # farther pairs need no exact distance
            return bool(np.min(self.distances(needle_pos, needle_quat, ee_pos, ee_quat, distmax)) < self.margin)
        self._set(needle_pos, needle_quat, ee_pos, ee_quat)
        mujoco.mj_collision(self.model, self.data)
        n = self.data.ncon
        return bool(n and np.any(self.data.contact.dist[:n] < 0.0))

    def distances(self, needle_pos, needle_quat, ee_pos, ee_quat, distmax: float = 0.1) -> np.ndarray:
        """Signed surface distance of every counted pair [m] (``mj_geomDistance``), capped at distmax."""
        self._set(needle_pos, needle_quat, ee_pos, ee_quat)
        return np.array(
            [mujoco.mj_geomDistance(self.model, self.data, g1, g2, distmax, None) for g1, g2 in self.scene.pairs]
        )

    def motion_collides(self, needle_pos, needle_quat, pos, quat, dp, rotvec) -> bool:
        """Whether the motion from ``(pos, quat)`` along ``(pos + s dp, exp(s rotvec) quat)``, s in
        [0, 1], comes closer than the margin anywhere (:mod:`regrasp_mjx.world.continuous`: every pose
        proved clear, not sampled ones), as one environment step."""
        pos, quat = np.asarray(pos, float), np.asarray(quat, float)
        dp, rotvec = np.asarray(dp, float), np.asarray(rotvec, float)
        per_tool = np.linalg.norm(dp) + np.linalg.norm(rotvec) * self.levers
        speed = np.repeat(per_tool, len(self._other_geoms))  # each pair's: its tool capsule's

        def bound_at(s: float, h: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
            at = pos + s * dp
            d = self.distances(needle_pos, needle_quat, at, quat_mul(quat_from_rotvec(s * rotvec), quat), reach)
            moved = d - h * speed  # the motion bound: where it proves every pair, or the pose collides,
            if np.all(moved - self.margin >= continuous.SLACK) or np.any(d < self.margin):  # it decides
                return d, moved
            tool, other = self._capsule_ends(self._tool_geoms), self._capsule_ends(self._other_geoms)
            # the closest-point direction from the capsules' axes, as the other engines compute it
            gap = segment_gap(tool[:, None, 0], tool[:, None, 1], other[None, :, 0], other[None, :, 1], xp=np)
            d = d.reshape(gap.shape[:2])
            low = continuous.interval_low(tool, at, other, gap, d, h, dp, rotvec, self.levers, xp=np)
            far = d >= reach  # reported at reach: proved by the motion bound alone
            return d.ravel(), np.where(far, d, low).ravel()

        return continuous.motion_collides_host(bound_at, per_tool.max(), self.margin)

    def _capsule_ends(self, geoms: np.ndarray) -> np.ndarray:
        """The capsules ``geoms``' axis end points ``[G, 2, 3]`` at the pose set."""
        axis = self.data.geom_xmat[geoms].reshape(-1, 3, 3)[:, :, 2] * self.model.geom_size[geoms, 1][:, None]
        centre = self.data.geom_xpos[geoms]
        return np.stack([centre - axis, centre + axis], axis=1)

    def motion_collides_between(self, needle: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether a planner's motion from pose ``a`` to pose ``b`` (7-vectors; position linear,
        orientation slerped the shorter way, as OMPL interpolates) collides, tested as the
        environment steps that replay it (:func:`~regrasp_mjx.world.continuous.pieces`), each with
        :meth:`motion_collides`."""
        needle, a, b = (np.asarray(x, float) for x in (needle, a, b))
        quat = a[3:] / np.linalg.norm(a[3:])
        rotvec = quat_to_rotvec(quat_mul(b[3:], quat_conj(quat)))
        dp = b[:3] - a[:3]
        n = continuous.pieces(dp, rotvec)
        for k in range(n):
            at = quat_mul(quat_from_rotvec(k / n * rotvec), quat)
            if self.motion_collides(needle[:3], needle[3:], a[:3] + k / n * dp, at, dp / n, rotvec / n):
                return True
        return False

    def clear_problems(self, needle, start, goal) -> list[int]:
        """Rows of ``[N, 7]`` needle, start and goal poses whose start and goal both keep this
        checker's margin (the others fail before a step is taken)."""
        needle, start, goal = (np.asarray(x, float).reshape(-1, 7) for x in (needle, start, goal))
        return [
            i
            for i in range(len(needle))
            if not self.collides(needle[i, :3], needle[i, 3:], start[i, :3], start[i, 3:])
            and not self.collides(needle[i, :3], needle[i, 3:], goal[i, :3], goal[i, 3:])
        ]

    def clear_episodes(self, episodes) -> list[int]:
        """Rows of a batch of problems (``sampling.Episode``) whose start and goal keep this margin,
        each around its own needle."""
        rows = []
        for i in range(len(episodes)):
            job = episodes.problem(i)
            checker = self.for_needle(job.get("needle_radius"), job.get("wire_radius"))
            if checker.clear_problems(job["needle"], job["start"], job["goal"]):
                rows.append(i)
        return rows

    def clearance(self, needle_pos, needle_quat, ee_pos, ee_quat) -> float:
        return float(self.distances(needle_pos, needle_quat, ee_pos, ee_quat).min())

    def path_clearance(self, needle, poses, substeps: int = 20) -> float:
        """Smallest clearance (m) along a path of regrasping end-effector poses ``[K, 7]`` for a
        needle pose ``[7]``, each segment moved as the environment moves (position linear,
        orientation along the rotation vector) and checked at ``substeps`` poses per 0.5 mm or 3
        degrees of motion (at least ``substeps`` per segment): an independent re-check of a plan."""
        needle, poses = np.asarray(needle, float), np.asarray(poses, float).reshape(-1, 7)
        best = self.clearance(needle[:3], needle[3:], poses[0, :3], poses[0, 3:])
        for a, b in zip(poses[:-1], poses[1:]):
            rotvec = quat_to_rotvec(quat_mul(b[3:], quat_conj(a[3:])))
            size = max(1.0, np.linalg.norm(b[:3] - a[:3]) / 0.5e-3, np.linalg.norm(rotvec) / math.radians(3.0))
            n = substeps * math.ceil(size - 1e-9)
            for k in range(1, n + 1):
                s = k / n
                quat = quat_mul(quat_from_rotvec(s * rotvec), a[3:])
                best = min(best, self.clearance(needle[:3], needle[3:], a[:3] + s * (b[:3] - a[:3]), quat))
        return best


class HostEnv:
    """One regrasping problem stepped on the CPU, as :class:`regrasp_mjx.envs.env.RegraspEnv` steps it."""

    def __init__(self, config: EnvConfig = EnvConfig(), scene: Scene | None = None):
        self.config = config
        self.scene_checker = HostChecker(scene if scene is not None else load_scene(config.scene), config.clearance_mm)
        self.checker = self.scene_checker
        self.max_dp = config.max_dp_mm * 1e-3
        self.max_drot = math.radians(config.max_drot_deg)

    def reset_from(self, episode) -> np.ndarray:
        """Starts from one problem (an :class:`~regrasp_mjx.world.sampling.Episode` row, around its own
        needle where it names one); returns the obs (21 numbers, 37 for a general task)."""
        self.checker = self.scene_checker.for_needle(episode.needle_radius, episode.wire_radius)
        self.radii = (
            self.checker.scene.config.needle_radius_mm * 1e-3,
            self.checker.scene.config.wire_radius_mm * 1e-3,
        )
        self.goal = (np.asarray(episode.goal_pos, float), np.asarray(episode.goal_quat, float))
        self.needle = (np.asarray(episode.needle_pos, float), np.asarray(episode.needle_quat, float))
        self.ee = (np.asarray(episode.start_pos, float), np.asarray(episode.start_quat, float))
        self.goal_needle = relative(
            np.asarray(episode.goal_pos, float), np.asarray(episode.goal_quat, float), *self.needle
        )
        self.t = 0
        return self.obs()

    def obs(self) -> np.ndarray:
        er_n = relative(*self.ee, *self.needle)
        obs = np.concatenate([self.needle[0], canonical(self.needle[1]), self.ee[0], canonical(self.ee[1]), *er_n])
        if not self.config.task.general:
            return obs
        goal_n = relative(*self.goal, *self.needle)
        er_goal = relative(*self.ee, *self.goal)
        return np.concatenate([obs, *goal_n, *er_goal, self.radii])

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict]:
        """Returns ``(obs, reward, done, info)``; info holds success, collision, time_out."""
        a = np.clip(np.asarray(action, float), -1.0, 1.0)
        if a.shape != (6,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be 6 finite numbers, got {action!r}")
        dp, rotvec = a[:3] * self.max_dp, a[3:] * self.max_drot
        pos, quat = self.ee[0] + dp, quat_mul(quat_from_rotvec(rotvec), self.ee[1])
        collision = self.checker.collides(*self.needle, pos, quat) or self.checker.motion_collides(
            *self.needle, *self.ee, dp, rotvec
        )
        self.ee = (pos, canonical(quat))
        self.t += 1
        er_n = relative(*self.ee, *self.needle)
        distance = float(np.linalg.norm(self.goal_needle[0] - er_n[0]))
        angle = quat_angle(self.goal_needle[1], er_n[1])
        success = (
            (not collision)
            and distance <= self.config.success_pos_mm * 1e-3
            and angle <= math.radians(self.config.success_rot_deg)
        )
        time_out = not (collision or success) and self.t >= self.config.horizon
        c = self.config
        reward = c.collision_reward if collision else c.success_reward if success else c.step_reward
        info = {
            "success": success,
            "collision": collision,
            "time_out": time_out,
            "distance_mm": distance * 1e3,
            "angle_deg": math.degrees(angle),
        }
        return self.obs(), reward, collision or success or time_out, info
