"""One query on one CPU core without XLA: the planning rollout compiled with numba (issue 31).

``Policy.plan`` of one query on the CPU spends most of its time around the XLA program, not in it:
dispatch, argument handling, and a while loop whose every small op is a runtime thunk. The compute
is tiny (a few matrix-vector products and a few dozen capsule distances per step, about seven
steps), so the same rollout as :func:`regrasp_mjx.inference.planner.make_planner` runs for one
query as plain loops compiled once by numba (:mod:`regrasp_mjx.inference.lean_rollout`: the network,
the step with its continuous collision test, the jaws that open on the way, the shield). This module
holds what a policy keeps of it (:class:`LeanPlanner`: the weights, the capsules, the shield's draws,
made once) and the query's entry: the poses checked, the default goal and the grasp-library distance
in the same compiled call. What every query passes is held in one native object
(:class:`~regrasp_mjx.envs.lean_collision.Held`), so a call unboxes one pointer.

It mirrors the JAX path, the reference (batches, the GPU, camera-frame queries and PSM joint checks
go there): geometry in float64 here, float32 there, the network in float32 in both. ``python -m
regrasp_mjx.evaluate --agreement`` finds the same verdicts on paper300, held-out 3000 and
general1000 (tests/test_lean_planner.py on samples; a policy that opens its jaws on the way there too).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import numpy as np
from numba import njit

from regrasp_mjx.core.geometry import QUAT_NORM_TOLERANCE
from regrasp_mjx.envs import lean_collision
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.lean_collision import capsules
from regrasp_mjx.envs.lean_geometry import goal_pose, nearest_grasp
from regrasp_mjx.envs.lean_jaw import jaws
from regrasp_mjx.envs.shield import candidate_noise, step_key
from regrasp_mjx.inference.lean_rollout import closed_loop_step, opening_keeps, rollout

# the status _query reports in outcome[STATUS]: the pose that failed its check, or none
POSE_OK, BAD_NEEDLE, BAD_START, BAD_GOAL = 0, 1, 2, 3
STATUS, START_MM, NEAREST, OPENED_AT = 7, 8, 9, 10  # outcome's entries after the rollout's seven
NO_GOAL = np.zeros(0)  # _query's goal for the goal grasp on the needle


@njit(cache=True)
def _checked(v, tolerance, out):
    """Whether the 7-vector ``v`` is finite with a quaternion norm within ``tolerance`` of 1
    (:func:`regrasp_mjx.inference.policy.check_poses`); ``out`` gets it with its quaternion normalised."""
    for r in range(7):
        if not math.isfinite(v[r]):
            return False
    n = math.sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6])
    if abs(n - 1.0) > tolerance:
        return False
    out[:3] = v[:3]
    for r in range(3, 7):
        out[r] = v[r] / n
    return True


@njit(cache=True)
def _query(held, needle, start, goal, task, library_p, library_q, columns, tolerance):
    """One query (``held``: :attr:`LeanPlanner.held`) from unchecked input: ``needle``,
    ``start`` and ``goal`` ``[7]`` (an empty goal: the goal grasp ``task[:4]`` on the needle),
    ``task`` ``(alpha*, d*, theta*, phi*, R, wire)`` [m].
    Checks the poses, makes the goal, measures the start's distance from the needle and the
    needle's from the grasp library (when it is not empty), and plans. Returns the fields of a
    :class:`LeanResult` (its ``status`` names a pose that failed its check, and nothing was planned
    then)."""
    state = held.state
    outcome = np.zeros(11)
    outcome[NEAREST] = np.nan
    outcome[OPENED_AT] = -1
    checked = np.empty((3, 7))
    for k, pose, status in ((0, needle, BAD_NEEDLE), (1, start, BAD_START), (2, goal, BAD_GOAL)):
        if k == 2 and goal.shape[0] == 0:
            checked[2] = goal_pose(checked[0], task[0], task[1], task[2], task[3], task[4])
        elif not _checked(pose, tolerance, checked[k]):
            outcome[STATUS] = status
            return _result(outcome, np.zeros((0, 7), np.float32), np.zeros((0, 6), np.float32))
    dx, dy, dz = checked[1, 0] - checked[0, 0], checked[1, 1] - checked[0, 1], checked[1, 2] - checked[0, 2]
    outcome[START_MM] = math.sqrt(dx * dx + dy * dy + dz * dz) * 1e3
    if library_p.shape[0]:
        outcome[NEAREST] = nearest_grasp(library_p, library_q, columns, checked[0])
    poses, actions, opened_at = rollout(state, checked[0], checked[1], checked[2], task[4:], outcome)
    outcome[OPENED_AT] = opened_at
    return _result(outcome, poses, actions)


@njit(cache=True)
def _result(outcome, poses, actions):
    """:class:`LeanResult`'s fields of ``_query``'s outcome: plain numbers (Python reads a tuple's
    faster than an array's)."""
    o = outcome
    rolled = (o[0], o[1], o[2], o[3], o[4], o[5], o[6])
    return rolled, int(o[STATUS]), o[START_MM], o[NEAREST], poses, actions, int(o[OPENED_AT])


class LeanPlanner:
    """A policy's planning rollout for one query at a time on the CPU (see the module docstring).

    ``LeanPlanner(env_config, weights)`` with ``weights`` one ``(params, mean, std)`` per member (a
    ``Policy``'s); see :meth:`__call__`.
    """

    def __init__(self, env_config: Any, weights: Any, shield: bool = True):
        env = RegraspEnv(env_config)
        cfg = env.config
        self.horizon = cfg.horizon
        # a step's, a collision's and a success's reward, and the discount rollout.rollout uses by default
        self.rewards = np.array([cfg.step_reward, cfg.collision_reward, cfg.success_reward, 0.99])
        self.shield = bool(shield)
        self.varies = bool(env.varies_needle)
        self.general = bool(env.general)
        self.consts = np.array(
            [
                np.float32(env.max_dp),
                np.float32(env.max_drot),
                np.float32(env.clearance),
                np.float32(cfg.success_pos_mm * 1e-3),
                np.float32(math.radians(cfg.success_rot_deg)),
            ],
            np.float64,
        )
        self.geo = capsules(env.scene.capsule_frames, env.scene.config.needle_radius_mm * 1e-3)
        # the jaws that open on the way (EnvConfig.jaw_open_deg), by the environment's margin
        self.jaws = jaws(env.scene, cfg.jaw_open_deg, env.jaw_margin)
        self.base_deg = float(env.scene.config.jaw_angle_deg)
        kernels, biases, layers = [], [], None
        for params, _, _ in weights:
            names = sorted(params["params"], key=lambda n: int(n.rsplit("_", 1)[1]))
            layers = len(names)
            for k, name in enumerate(names):
                kernel = np.asarray(params["params"][name]["kernel"], np.float32)
                # the output layer's kernel transposed: six dot products (see _output)
                kernels.append(np.array(kernel.T if k == len(names) - 1 else kernel, order="C"))
                biases.append(np.array(params["params"][name]["bias"], np.float32))
        self.net = (
            tuple(kernels),
            tuple(biases),
            layers,
            np.stack([np.asarray(m, np.float32) for _, m, _ in weights]),
            np.stack([np.asarray(s, np.float32) for _, _, s in weights]),
        )
        # shield_candidates' perturbations at every step of the horizon, [horizon, 24, 6]
        noise = jax.vmap(lambda t: candidate_noise(step_key(t), 6))(np.arange(self.horizon))
        self.noise = np.ascontiguousarray(np.asarray(noise, np.float32)[:, :, 0])
        # what every call passes, the capsules as a plain tuple (numba types a named tuple's fields
        # in Python, microseconds a call; a plain tuple's in C)
        self.state = (
            self.net,
            tuple(self.geo),
            self.consts,
            self.rewards,
            self.varies,
            self.general,
            self.noise,
            self.shield,
            None if self.jaws is None else tuple(self.jaws),
        )
        self.held = lean_collision.hold(self.state)  # what a call passes: the state as one native object

    def goal(self, needle: np.ndarray, grasp: np.ndarray, radius: float) -> np.ndarray:
        """The goal end-effector pose ``[7]`` (e_g) of a goal grasp ``(alpha*, d* [m], theta*, phi*)``
        on a needle of ``radius`` [m] at ``needle`` ``[7]``."""
        g = np.asarray(grasp, np.float64)
        return goal_pose(np.asarray(needle, np.float64), g[0], g[1], g[2], g[3], float(radius))

    def __call__(
        self, needle: np.ndarray, start: np.ndarray, goal: np.ndarray | None, task: np.ndarray, library: tuple
    ) -> LeanResult:
        """One query: ``needle``, ``start``, ``goal`` 7-vectors (e_g; goal None: the goal grasp on the
        needle), ``task`` ``[6]`` = ``(alpha*, d*, theta*, phi*, R, wire)`` [m], ``library`` the grasp
        library's :attr:`~regrasp_mjx.grasps.GraspLibrary.unit_arrays` (empty: not checked). The
        poses are checked here (a :attr:`LeanResult.status` names the first that fails)."""
        f64 = np.ascontiguousarray  # one compiled signature: contiguous float64
        goal = NO_GOAL if goal is None else f64(goal, np.float64)
        return LeanResult(
            *_query(
                self.held, f64(needle, np.float64), f64(start, np.float64), goal, task, *library, QUAT_NORM_TOLERANCE
            )
        )

    def step(
        self,
        needle: np.ndarray,
        ee: np.ndarray,
        goal: np.ndarray,
        radii: np.ndarray,
        t: int,
        stop_scale: float,
        opened: bool = False,
    ):
        """One closed-loop step from checked estimates (``[7]`` each, e_g; ``radii`` ``[2]`` m) at
        step ``t`` (< the horizon: it seeds the shield's alternatives) with the jaws ``opened`` (at
        ``jaw_open_deg``) or at the scene's opening: ``(at_goal, next_ee [7], action [6], jaw_deg)``,
        ``jaw_deg`` the opening to command before the motion
        (:func:`~regrasp_mjx.inference.lean_rollout.closed_loop_step`)."""
        out = np.empty(14)
        f64 = np.ascontiguousarray
        needle, ee, goal = f64(needle, np.float64), f64(ee, np.float64), f64(goal, np.float64)
        at_goal = closed_loop_step(self.state, needle, ee, goal, radii, t, stop_scale, bool(opened), out)
        jaw_deg = self.base_deg if self.jaws is None or not out[13] else self.jaws.open_deg
        return at_goal, out[:7], out[7:13], jaw_deg

    def opening_keeps(self, needle: np.ndarray, ee: np.ndarray, radii: np.ndarray, margin: float) -> bool:
        """Whether opening the jaws at the pose ``ee`` keeps ``margin`` [m] (rounded to float32, as the
        environment compares it) from the needle ``needle`` (``[7]`` each, e_g; ``radii`` ``[2]`` m) and
        the grasping tool (:func:`~regrasp_mjx.inference.lean_rollout.opening_keeps`); False where the
        jaws stay."""
        f64 = np.ascontiguousarray
        needle, ee, radii = f64(needle, np.float64), f64(ee, np.float64), f64(radii, np.float64)
        return bool(opening_keeps(self.state, needle, ee, radii, float(np.float32(margin))))


class LeanResult(NamedTuple):
    """What :class:`LeanPlanner` returns for one query."""

    outcome: tuple  # 7 floats: start_valid, success, collision, time_out, steps, path length [m], return
    status: int  # POSE_OK, or the pose that failed its check (BAD_NEEDLE, BAD_START, BAD_GOAL): nothing planned
    start_mm: float  # the start's distance from the needle
    nearest: float  # the needle's distance to the nearest grasp of the library (NaN: not checked)
    poses: np.ndarray  # [steps + 1, 7] float32, as the JAX planner returns them
    actions: np.ndarray  # [steps, 6] float32
    opened_at: int  # the step the jaws opened before (EnvConfig.jaw_open_deg), -1: never
