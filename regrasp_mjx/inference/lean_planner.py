"""One query on one CPU core without XLA: the planning rollout compiled with numba (issue 31).

``Policy.plan`` of one query on the CPU spends most of its time around the XLA program, not in it:
dispatch, argument handling, and a while loop whose every small op is a runtime thunk. The compute
is tiny (a few matrix-vector products and a few dozen capsule distances per step, about seven
steps), so this module runs the same rollout as :func:`regrasp_mjx.inference.planner.make_planner`
for one query, as plain loops compiled once by numba: the network (members averaged), the
ego-centric observation (:mod:`regrasp_mjx.inference.lean_network`), the step with its continuous
collision test (:mod:`regrasp_mjx.envs.lean_collision`; poses:
:mod:`regrasp_mjx.envs.lean_geometry`), the shield's alternatives in the same order with the same
random draws (:func:`regrasp_mjx.envs.shield.shield_candidates`, drawn once here for every step of
the horizon), the success test, the trajectory. Nothing is allocated per step: the network's layers,
the observation and the member actions use buffers made once per query, poses are tuples. What every
query passes is held in one native object (:class:`~regrasp_mjx.envs.lean_collision.Held`), so a
call unboxes one pointer.

It mirrors the JAX path, the reference (batches, the GPU, camera-frame queries and PSM joint checks
go there): geometry in float64 here, float32 there, the network in float32 in both. ``python -m
regrasp_mjx.evaluate --agreement`` finds the same verdicts on paper300, held-out 3000 and
general1000 (tests/test_lean_planner.py on samples).
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
from regrasp_mjx.envs.lean_collision import Capsules, capsules, collides, fixed_ends, make_scratch, motion_collides
from regrasp_mjx.envs.lean_geometry import angle, canonical, goal_pose, nearest_grasp, qexp, qmul, relative, unit
from regrasp_mjx.envs.shield import candidate_noise, step_key
from regrasp_mjx.inference.lean_network import buffers, member_actions, observe

# ---- the step and the rollout (regrasp_mjx.envs.env.RegraspEnv.step, regrasp_mjx.envs.rollout.rollout) -----


class _Setup(NamedTuple):
    """What every step of one query reads and nothing in it changes, made once per query by
    :func:`_setup` in compiled code (numba builds and passes a named tuple there natively; only one
    passed in from Python is typed field by field, hence the plain-tuple state)."""

    net: tuple  # (kernels, biases, layers, mean, std) of the members
    geo: lean_collision.Capsules
    consts: np.ndarray  # max_dp, max_drot, clearance, success tolerances [m, rad]
    fixed: lean_collision.Fixed  # the query's needle and grasping tool placed
    scratch: tuple  # make_scratch's arrays
    general: bool
    shield: bool
    needle: tuple  # (p, q): position and unit quaternion, tuples of float32 values
    goal: tuple
    goal_in_needle: tuple  # the goal in the needle's frame
    radii: tuple  # the needle's radius and wire radius [m]
    buffers: tuple  # lean_network.buffers': what a step of the network and the shield write into


@njit(cache=True)
def _setup(state, needle, goal, radii):
    """:class:`_Setup` of one query: the state (:attr:`LeanPlanner.state`), the needle's and the
    goal's poses ``[7]`` and the radii ``[2]`` [m], each rounded to float32 as the JAX path takes them."""
    net, geo, consts, _, varies, general, _, shield = state
    geo = Capsules(*geo)
    radii = (_f32(radii[0]), _f32(radii[1]))
    needle, goal = _pose(needle), _pose(goal)
    fixed = fixed_ends(geo, varies, *needle, *radii)
    goal_in_needle = relative(*goal, *needle)
    scratch, work = make_scratch(geo.tool_local), buffers(net[3], net[1])
    return _Setup(net, geo, consts, fixed, scratch, general, shield, needle, goal, goal_in_needle, radii, work)


@njit(cache=True)
def _step(s, ee_p, ee_q, action):
    """One step of the float32 ``action`` from the pose ``ee`` (``s``: the query's :class:`_Setup`):
    the new pose, whether the swept motion collides, whether it reached the goal, and its
    translation [m]."""
    consts, scratch, (gn_p, gn_q) = s.consts, s.scratch, s.goal_in_needle
    max_dp, max_drot, clearance, tol_pos, tol_rot = consts[0], consts[1], consts[2], consts[3], consts[4]
    # the action clipped; the JAX path steps it in float32
    lo, hi = np.float32(-1.0), np.float32(1.0)
    dx = np.float64(min(max(action[0], lo), hi)) * max_dp
    dy = np.float64(min(max(action[1], lo), hi)) * max_dp
    dz = np.float64(min(max(action[2], lo), hi)) * max_dp
    wx = np.float64(min(max(action[3], lo), hi)) * max_drot
    wy = np.float64(min(max(action[4], lo), hi)) * max_drot
    wz = np.float64(min(max(action[5], lo), hi)) * max_drot
    pos = (ee_p[0] + dx, ee_p[1] + dy, ee_p[2] + dz)
    quat = qmul(qexp(wx, wy, wz), ee_q)
    # the whole motion proved clear, not sampled poses (regrasp_mjx.world.continuous)
    collision = motion_collides(
        s.geo, s.fixed, ee_p, ee_q, (dx, dy, dz), (wx, wy, wz), clearance, scratch[0], scratch[1], scratch[2]
    )
    quat = canonical(quat)
    p, q = relative(pos, quat, *s.needle)
    ex, ey, ez = gn_p[0] - p[0], gn_p[1] - p[1], gn_p[2] - p[2]
    distance = math.sqrt(ex * ex + ey * ey + ez * ez)
    success = (not collision) and distance <= tol_pos and angle(gn_q, q) <= tol_rot
    return pos, quat, collision, success, math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True)
def _f32(x):
    """A float64 rounded to float32 and back (the JAX path holds its state in float32)."""
    return np.float64(np.float32(x))


@njit(cache=True)
def _pose(v):
    """``(p, q)`` of a 7-vector, each number rounded to float32 first, ``q`` normalised."""
    p = (_f32(v[0]), _f32(v[1]), _f32(v[2]))
    return p, unit((_f32(v[3]), _f32(v[4]), _f32(v[5]), _f32(v[6])))


@njit(cache=True)
def _decide(s, noise_t, ee_p, ee_q):
    """One step of the policy from the pose ``ee`` (``s``: the query's :class:`_Setup`): the members'
    mean action (into ``s.buffers[4]``) and, with ``s.shield``, where it collides, the first free
    alternative (``noise_t``: this step's perturbations); returns :func:`_step`'s outcome of the
    action taken."""
    kernels, biases, layers, mean, std = s.net
    obs, work, rows, own, act, cand = s.buffers
    members = mean.shape[0]
    observe(obs, s.general, *s.needle, ee_p, ee_q, *s.goal, *s.radii)
    member_actions(kernels, biases, layers, mean, std, obs, work, rows, own)
    for j in range(6):  # the members' mean, summed in their order as the JAX path does
        act[j] = own[0, j]
        for m in range(1, members):
            act[j] += own[m, j]
        if members > 1:
            act[j] /= np.float32(members)
    pos, quat, collision, success, dl = _step(s, ee_p, ee_q, act)
    if collision and s.shield:
        # the alternatives in shield_candidates' order: each member's own (an ensemble), half
        # the action, then the action plus the step's fixed noise, clipped; the first free one
        extra = members if members > 1 else 0
        for c in range(extra + 1 + noise_t.shape[0]):
            for j in range(6):
                if c < extra:
                    cand[j] = own[c, j]
                elif c == extra:
                    cand[j] = np.float32(0.5) * act[j]
                else:
                    cand[j] = min(max(act[j] + noise_t[c - extra - 1, j], np.float32(-1.0)), np.float32(1.0))
            p2, q2, col2, suc2, dl2 = _step(s, ee_p, ee_q, cand)
            if not col2:
                act[:] = cand
                return p2, q2, col2, suc2, dl2
    return pos, quat, collision, success, dl


@njit(cache=True)
def _closed_loop_step(state, needle, ee, goal, radii, t, stop_scale, out):
    """One closed-loop step (:func:`regrasp_mjx.inference.closed_loop.make_stepper` for one query) from the
    estimates ``needle``, ``ee``, ``goal`` ``[7]`` (rounded to float32 as the JAX path takes them):
    ``out[:7]`` the pose to command next and ``out[7:]`` the action (zero, and ``ee`` kept, where
    the estimate is within ``stop_scale`` of the success tolerances of the goal). Returns that."""
    s = _setup(state, needle, goal, radii)
    consts, noise = state[2], state[6]
    ee_p, ee_q = _pose(ee)
    p, q = relative(ee_p, ee_q, *s.needle)
    gn_p, gn_q = s.goal_in_needle
    ex, ey, ez = gn_p[0] - p[0], gn_p[1] - p[1], gn_p[2] - p[2]
    if math.sqrt(ex * ex + ey * ey + ez * ez) <= stop_scale * consts[3] and angle(gn_q, q) <= stop_scale * consts[4]:
        out[:3] = ee_p
        out[3:7] = ee_q
        out[7:] = 0.0
        return True
    pos, quat, _, _, _ = _decide(s, noise[t], ee_p, ee_q)
    for r in range(3):
        out[r] = _f32(pos[r])
    for r in range(4):
        out[3 + r] = _f32(quat[r])
    for j in range(6):
        out[7 + j] = min(max(s.buffers[4][j], np.float32(-1.0)), np.float32(1.0))
    return False


@njit(cache=True)
def _rollout(state, needle, start, goal, radii, outcome):
    """The rollout of one query (poses and radii rounded to float32 first, as the JAX path takes
    them) into ``outcome[:7]``: ``start_valid, success, collision, time_out, steps, path_length
    [m], discounted return`` (``rewards``: a step's, a collision's, a success's reward and gamma).
    ``state``: :attr:`LeanPlanner.state`. Returns ``(poses[steps + 1, 7], actions[steps, 6])``
    (float32, as the JAX planner returns them: every number of the state is float32 already)."""
    rewards, noise = state[3], state[6]
    s = _setup(state, needle, goal, radii)
    horizon = noise.shape[0]
    poses = np.empty((horizon + 1, 7), np.float32)
    actions = np.empty((horizon, 6), np.float32)
    for r in range(7):
        poses[0, r] = _f32(start[r])
    ee_p, ee_q = _pose(start)
    valid = not collides(s.geo, s.fixed, ee_p, ee_q, s.scratch[0], s.scratch[1], s.consts[2])
    outcome[0] = 1.0 if valid else 0.0
    if not valid:
        outcome[2] = 1.0
        return poses[:1], actions[:0]
    length = 0.0
    steps = 0
    for t in range(horizon):
        pos, quat, collision, success, dl = _decide(s, noise[t], ee_p, ee_q)
        act = s.buffers[4]
        # the state as the JAX path keeps it, in float32 (the two paths' rounding drifts apart less)
        ee_p = (_f32(pos[0]), _f32(pos[1]), _f32(pos[2]))
        ee_q = (_f32(quat[0]), _f32(quat[1]), _f32(quat[2]), _f32(quat[3]))
        length += dl
        steps = t + 1
        for r in range(3):
            poses[steps, r] = ee_p[r]
        for r in range(4):
            poses[steps, 3 + r] = ee_q[r]
        for j in range(6):
            actions[t, j] = min(max(act[j], np.float32(-1.0)), np.float32(1.0))
        if collision or success:
            outcome[1] = 1.0 if success else 0.0
            outcome[2] = 1.0 if collision else 0.0
            break
        if steps >= horizon:
            outcome[3] = 1.0
    outcome[4] = steps
    outcome[5] = length
    ret = 0.0
    for t in range(steps):  # the rewards of the steps taken, the last one's by how it ended
        r = rewards[0]
        if t == steps - 1 and outcome[2] > 0:
            r = rewards[1]
        elif t == steps - 1 and outcome[1] > 0:
            r = rewards[2]
        ret += r * rewards[3] ** t
    outcome[6] = ret
    return poses[: steps + 1], actions[:steps]


# the status _query reports in outcome[STATUS]: the pose that failed its check, or none
POSE_OK, BAD_NEEDLE, BAD_START, BAD_GOAL = 0, 1, 2, 3
STATUS, START_MM, NEAREST = 7, 8, 9  # outcome's entries after the rollout's seven
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
    outcome = np.zeros(10)
    outcome[NEAREST] = np.nan
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
    return _result(outcome, *_rollout(state, checked[0], checked[1], checked[2], task[4:], outcome))


@njit(cache=True)
def _result(outcome, poses, actions):
    """:class:`LeanResult`'s fields of ``_query``'s outcome: plain numbers (Python reads a tuple's
    faster than an array's)."""
    o = outcome
    return (o[0], o[1], o[2], o[3], o[4], o[5], o[6]), int(o[STATUS]), o[START_MM], o[NEAREST], poses, actions


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

    def step(self, needle: np.ndarray, ee: np.ndarray, goal: np.ndarray, radii: np.ndarray, t: int, stop_scale: float):
        """One closed-loop step from checked estimates (``[7]`` each, e_g; ``radii`` ``[2]`` m) at
        step ``t`` (< the horizon: it seeds the shield's alternatives):
        ``(at_goal, next_ee [7], action [6])`` (:func:`_closed_loop_step`)."""
        out = np.empty(13)
        f64 = np.ascontiguousarray
        at_goal = _closed_loop_step(
            self.state, f64(needle, np.float64), f64(ee, np.float64), f64(goal, np.float64), radii, t, stop_scale, out
        )
        return at_goal, out[:7], out[7:]


class LeanResult(NamedTuple):
    """What :class:`LeanPlanner` returns for one query."""

    outcome: tuple  # 7 floats: start_valid, success, collision, time_out, steps, path length [m], return
    status: int  # POSE_OK, or the pose that failed its check (BAD_NEEDLE, BAD_START, BAD_GOAL): nothing planned
    start_mm: float  # the start's distance from the needle
    nearest: float  # the needle's distance to the nearest grasp of the library (NaN: not checked)
    poses: np.ndarray  # [steps + 1, 7] float32, as the JAX planner returns them
    actions: np.ndarray  # [steps, 6] float32
