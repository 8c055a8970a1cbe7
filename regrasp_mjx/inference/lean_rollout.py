"""The planning rollout of one query compiled with numba (issue 31): the step, the shield's
alternatives, the rollout and one closed-loop step, as :func:`regrasp_mjx.inference.planner.make_planner`
and :func:`regrasp_mjx.inference.closed_loop.make_stepper` run them for a batch.

The network (members averaged) and the ego-centric observation
(:mod:`regrasp_mjx.inference.lean_network`), the step with its continuous collision test
(:mod:`regrasp_mjx.envs.lean_collision`; poses: :mod:`regrasp_mjx.envs.lean_geometry`), the jaws of
a policy that opens them on the way (:mod:`regrasp_mjx.envs.lean_jaw`: opened before the first step
whose start leaves the sweep its margin, as the environment opens them), the shield's alternatives in
the same order with the same random draws (:func:`regrasp_mjx.envs.shield.shield_candidates`, drawn
once for every step of the horizon), the success test, the trajectory. Nothing is allocated per step:
the network's layers, the observation and the member actions use buffers made once per query, poses
are tuples. The state every call reads is :attr:`~regrasp_mjx.inference.lean_planner.LeanPlanner.state`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from regrasp_mjx.envs import lean_collision
from regrasp_mjx.envs.lean_collision import Capsules, collides, fixed_ends, make_scratch, motion_collides
from regrasp_mjx.envs.lean_geometry import angle, canonical, qexp, qmul, relative, unit
from regrasp_mjx.envs.lean_jaw import Jaws, as_jaws, open_jaws, opens_here, own_capsules, sweep_keeps, sweep_points
from regrasp_mjx.inference.lean_network import buffers, member_actions, observe

# ---- the step and the rollout (regrasp_mjx.envs.env.RegraspEnv.step, regrasp_mjx.envs.rollout.rollout) -----


class Setup(NamedTuple):
    """What every step of one query reads and nothing in it changes, made once per query by
    :func:`setup` in compiled code (numba builds and passes a named tuple there natively; only one
    passed in from Python is typed field by field, hence the plain-tuple state)."""

    net: tuple  # (kernels, biases, layers, mean, std) of the members
    geo: lean_collision.Capsules  # where the jaws open on the way, with the query's own tool capsules
    jaws: Jaws | None  # the jaws' opening on the way (their capsules opened, the sweep's check points)
    consts: np.ndarray  # max_dp, max_drot, clearance, success tolerances [m, rad]
    fixed: lean_collision.Fixed  # the query's needle and grasping tool placed
    scratch: tuple  # make_scratch's arrays (its first also the sweep's)
    general: bool
    shield: bool
    needle: tuple  # (p, q): position and unit quaternion, tuples of float32 values
    goal: tuple
    goal_in_needle: tuple  # the goal in the needle's frame
    radii: tuple  # the needle's radius and wire radius [m]
    buffers: tuple  # lean_network.buffers': what a step of the network and the shield write into


@njit(cache=True)
def setup(state, needle, goal, radii):
    """:class:`Setup` of one query: the state (:attr:`LeanPlanner.state`), the needle's and the
    goal's poses ``[7]`` and the radii ``[2]`` [m], each rounded to float32 as the JAX path takes them."""
    net, geo, consts, _, varies, general, _, shield, jaws = state
    jaws = as_jaws(jaws)
    geo = Capsules(own_capsules(jaws, geo[0]), *geo[1:])  # jaws that open on the way open in a copy
    radii = (f32(radii[0]), f32(radii[1]))
    needle, goal = pose(needle), pose(goal)
    fixed = fixed_ends(geo, varies, *needle, *radii)
    goal_in_needle = relative(*goal, *needle)
    scratch, work = make_scratch(geo.tool_local, sweep_points(jaws)), buffers(net[3], net[1])
    return Setup(net, geo, jaws, consts, fixed, scratch, general, shield, needle, goal, goal_in_needle, radii, work)


@njit(cache=True)
def _step(s, ee_p, ee_q, action):
    """One step of the float32 ``action`` from the pose ``ee`` (``s``: the query's :class:`Setup`,
    its capsules with the jaws where they are): the new pose, whether the swept motion collides,
    whether it reached the goal, and its translation [m]."""
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
def f32(x):
    """A float64 rounded to float32 and back (the JAX path holds its state in float32)."""
    return np.float64(np.float32(x))


@njit(cache=True)
def pose(v):
    """``(p, q)`` of a 7-vector, each number rounded to float32 first, ``q`` normalised."""
    p = (f32(v[0]), f32(v[1]), f32(v[2]))
    return p, unit((f32(v[3]), f32(v[4]), f32(v[5]), f32(v[6])))


@njit(cache=True)
def _decide(s, noise_t, ee_p, ee_q):
    """One step of the policy from the pose ``ee`` (``s``: the query's :class:`Setup`, its jaws where
    :func:`~regrasp_mjx.envs.lean_jaw.opens_here` left them): the members' mean action (into ``s.buffers[4]``) and, with
    ``s.shield``, where it collides, the first free alternative (``noise_t``: this step's
    perturbations); returns :func:`_step`'s outcome of the action taken. The jaws are opened (or
    not) before it, whatever the action: every alternative moves with them where they are."""
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
def closed_loop_step(state, needle, ee, goal, radii, t, stop_scale, opened, out):
    """One closed-loop step (:func:`regrasp_mjx.inference.closed_loop.make_stepper` for one query) from the
    estimates ``needle``, ``ee``, ``goal`` ``[7]`` (rounded to float32 as the JAX path takes them)
    with the jaws ``opened`` or not: ``out[:7]`` the pose to command next, ``out[7:13]`` the action
    (zero, and ``ee`` kept, where the estimate is within ``stop_scale`` of the success tolerances of
    the goal) and ``out[13]`` 1 where the jaws are open for the motion (0: at the scene's opening).
    Returns whether the estimate is at the goal."""
    s = setup(state, needle, goal, radii)
    consts, noise = state[2], state[6]
    if opened:  # opened by an earlier step
        open_jaws(s.jaws, s.geo.tool_local)
    ee_p, ee_q = pose(ee)
    p, q = relative(ee_p, ee_q, *s.needle)
    gn_p, gn_q = s.goal_in_needle
    ex, ey, ez = gn_p[0] - p[0], gn_p[1] - p[1], gn_p[2] - p[2]
    if math.sqrt(ex * ex + ey * ey + ez * ez) <= stop_scale * consts[3] and angle(gn_q, q) <= stop_scale * consts[4]:
        out[:3] = ee_p
        out[3:7] = ee_q
        out[7:13] = 0.0
        out[13] = 1.0 if opened else 0.0
        return True
    opened = opened or opens_here(s.jaws, s.geo, s.fixed, ee_p, ee_q, s.scratch[0])
    pos, quat, _, _, _ = _decide(s, noise[t], ee_p, ee_q)
    for r in range(3):
        out[r] = f32(pos[r])
    for r in range(4):
        out[3 + r] = f32(quat[r])
    for j in range(6):
        out[7 + j] = min(max(s.buffers[4][j], np.float32(-1.0)), np.float32(1.0))
    out[13] = 1.0 if opened else 0.0
    return False


@njit(cache=True)
def _keeps(j, margin, geo, fixed, ee_p, ee_q, ends):
    """:func:`~regrasp_mjx.envs.lean_jaw.sweep_keeps` with the margin ``margin`` [m] in place of the
    environment's; False where the jaws stay (``j`` None)."""
    if j is None:
        return False
    own = Jaws(j.base_deg, j.open_deg, j.rows, j.opened, j.sweep, j.turn, j.slack, margin)
    return sweep_keeps(own, geo, fixed, ee_p, ee_q, ends)


@njit(cache=True)
def opening_keeps(state, needle, ee, radii, margin):
    """Whether opening the jaws from the scene's opening to ``jaw_open_deg`` at the pose ``ee`` ``[7]``,
    the tool holding still, keeps ``margin`` [m] from the needle ``needle`` ``[7]`` (radii ``[2]`` m)
    and the grasping tool: the environment's sweep test (the same check points and slack) with a
    margin of the caller's (the closed loop's: the environment's plus its view's error,
    :class:`~regrasp_mjx.inference.camera_loop.CameraLoop`). Poses rounded to float32 as the JAX path
    takes them; False for a policy whose jaws stay."""
    s = setup(state, needle, needle, radii)
    ee_p, ee_q = pose(ee)
    return _keeps(s.jaws, margin, s.geo, s.fixed, ee_p, ee_q, s.scratch[0])


@njit(cache=True)
def rollout(state, needle, start, goal, radii, outcome):
    """The rollout of one query (poses and radii rounded to float32 first, as the JAX path takes
    them) into ``outcome[:7]``: ``start_valid, success, collision, time_out, steps, path_length
    [m], discounted return`` (``rewards``: a step's, a collision's, a success's reward and gamma).
    ``state``: :attr:`LeanPlanner.state`. Returns ``(poses[steps + 1, 7], actions[steps, 6],
    opened_at)`` (float32, as the JAX planner returns them: every number of the state is float32
    already; ``opened_at`` the step the jaws opened before, -1: never)."""
    rewards, noise = state[3], state[6]
    s = setup(state, needle, goal, radii)
    horizon = noise.shape[0]
    poses = np.empty((horizon + 1, 7), np.float32)
    actions = np.empty((horizon, 6), np.float32)
    for r in range(7):
        poses[0, r] = f32(start[r])
    ee_p, ee_q = pose(start)
    # the start at the scene's opening, as the environment's reset tests it
    valid = not collides(s.geo, s.fixed, ee_p, ee_q, s.scratch[0], s.scratch[1], s.consts[2])
    outcome[0] = 1.0 if valid else 0.0
    if not valid:
        outcome[2] = 1.0
        return poses[:1], actions[:0], -1
    length = 0.0
    steps = 0
    shut, opened_at = True, -1  # the jaws at the scene's opening, where they open on the way
    for t in range(horizon):
        if shut and opens_here(s.jaws, s.geo, s.fixed, ee_p, ee_q, s.scratch[0]):
            shut, opened_at = False, t
        pos, quat, collision, success, dl = _decide(s, noise[t], ee_p, ee_q)
        act = s.buffers[4]
        # the state as the JAX path keeps it, in float32 (the two paths' rounding drifts apart less)
        ee_p = (f32(pos[0]), f32(pos[1]), f32(pos[2]))
        ee_q = (f32(quat[0]), f32(quat[1]), f32(quat[2]), f32(quat[3]))
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
    return poses[: steps + 1], actions[:steps], opened_at
