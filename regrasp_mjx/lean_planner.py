"""One query on one CPU core without XLA: the planning rollout compiled with numba (issue 31).

``Policy.plan`` of one query on the CPU spends most of its time around the XLA program, not in
it: dispatch, argument handling, and a while loop whose every small op is a runtime thunk. The
compute is tiny (a few matrix-vector products and at most 240 capsule distances per sub-step,
about seven steps), so this module runs the same rollout as :func:`regrasp_mjx.planner.make_planner` for one
query, as plain loops compiled once by numba: the network (members averaged), the ego-centric
observation, the step with its collision sub-steps, the shield's alternatives in the same order
with the same random draws (:func:`regrasp_mjx.shield.shield_candidates`, drawn once here for
every step of the horizon), the success test, the trajectory. A collision test needs only whether the closest pair comes
nearer than the margin, not its distance: the needle's 56 chords are checked in groups of
:data:`CHORD_GROUP` behind a bounding capsule each, and the first pair below the margin ends the
test, which gives the same verdict as the minimum over every pair with a fraction of the work.

It mirrors the JAX path, which stays the reference (batches, the GPU, camera-frame queries and
the joint-limit check given PSM bases go there): geometry in float64 here against float32 there,
the network in float32 in both. ``experiments/bench_plan.py --agreement`` found the same verdict on
every problem of paper300, held-out 3000 and general1000, and actions equal to 2.1e-5 in plans that
end before the horizon (1.8e-4 at the end of a 100-step time-out); tests/test_lean_planner.py
checks the same on samples.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import numpy as np
from numba import njit

from regrasp_mjx.env import RegraspEnv
from regrasp_mjx.planner import PlanArrays
from regrasp_mjx.rollout import Rollout
from regrasp_mjx.shield import candidate_noise, step_key

# chords per bounding capsule in the collision test (7 x 8 for the MJCF's 56; measured fastest of
# 4, 7, 8 and 14 with experiments/bench_plan.py)
CHORD_GROUP = 7

# ---- pose algebra (wxyz quaternions, as regrasp_mjx.geometry and jaxlie) ---------------------------


@njit(cache=True, fastmath=False)
def _qmul(a, b):
    out = np.empty(4)
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]
    return out


@njit(cache=True)
def _conj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


@njit(cache=True)
def _canonical(q):
    return -q if q[0] < 0.0 else q


@njit(cache=True)
def _qexp(v):
    """jaxlie's ``SO3.exp``: the Taylor branch below its float32 epsilon, as the JAX path takes it."""
    th2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    if th2 < 1e-5:
        real = 1.0 - th2 / 8.0 + th2 * th2 / 384.0
        imag = 0.5 - th2 / 48.0 + th2 * th2 / 3840.0
    else:
        th = math.sqrt(th2)
        real = math.cos(0.5 * th)
        imag = math.sin(0.5 * th) / th
    return np.array([real, imag * v[0], imag * v[1], imag * v[2]])


@njit(cache=True)
def _matrix(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    m = np.empty((3, 3))
    m[0, 0] = 1 - 2 * (y * y + z * z)
    m[0, 1] = 2 * (x * y - w * z)
    m[0, 2] = 2 * (x * z + w * y)
    m[1, 0] = 2 * (x * y + w * z)
    m[1, 1] = 1 - 2 * (x * x + z * z)
    m[1, 2] = 2 * (y * z - w * x)
    m[2, 0] = 2 * (x * z - w * y)
    m[2, 1] = 2 * (y * z + w * x)
    m[2, 2] = 1 - 2 * (x * x + y * y)
    return m


@njit(cache=True)
def _relative(ap, aq, bp, bq):
    """``T_a_b``: pose b seen from frame a (both in one frame), quaternion canonical."""
    m = _matrix(aq)
    d = bp - ap
    p = m.T @ d
    return p, _canonical(_qmul(_conj(aq), bq))


@njit(cache=True)
def _angle(q1, q2):
    d = _qmul(q1, _conj(q2))
    return 2.0 * math.atan2(math.sqrt(d[1] * d[1] + d[2] * d[2] + d[3] * d[3]), abs(d[0]))


@njit(cache=True)
def _from_matrix(m):
    """The unit quaternion (w >= 0) of a rotation matrix (Shepperd's method: the largest of the four
    squares first, for accuracy)."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.empty(4)
    if tr > m[0, 0] and tr > m[1, 1] and tr > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + tr)
        q[0], q[1], q[2], q[3] = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q[0], q[1], q[2], q[3] = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q[0], q[1], q[2], q[3] = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q[0], q[1], q[2], q[3] = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return _canonical(q / math.sqrt(q @ q))


@njit(cache=True)
def _goal_pose(needle, alpha, depth, theta, phi, radius):
    """The goal end-effector pose (e_g) of a goal grasp on a needle: ``needle ∘ grasp_pose(...)``
    (:func:`regrasp_mjx.geometry.grasp_pose`, paper eq. 3, and ``compose``)."""
    off = np.array(
        [depth * math.cos(phi), depth * math.sin(phi) * math.cos(theta), depth * math.sin(phi) * math.sin(theta)]
    )
    pos = np.array([0.0, radius * math.cos(alpha), radius * math.sin(alpha)]) + off
    z = -off / math.sqrt(off @ off)
    tangent = np.array([0.0, -math.sin(alpha), math.cos(alpha)])
    x = tangent - (tangent @ z) * z
    if math.sqrt(x @ x) < 1e-6:  # the jaws along the wire: the needle-plane normal instead
        x_n = np.array([1.0, 0.0, 0.0])
        x = x_n - (x_n @ z) * z
    x = x / math.sqrt(x @ x)
    y = np.array([z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]])
    rot = np.empty((3, 3))
    rot[:, 0], rot[:, 1], rot[:, 2] = x, y, z
    q_n = needle[3:] / math.sqrt(needle[3:] @ needle[3:])
    goal = np.empty(7)
    goal[:3] = needle[:3] + _matrix(q_n) @ pos
    goal[3:] = _canonical(_qmul(q_n, _from_matrix(rot)))
    return goal


# ---- observation and network ------------------------------------------------------------------


@njit(cache=True)
def _observe(general, needle_p, needle_q, ee_p, ee_q, goal_p, goal_q, radius, wire):
    obs = np.empty(37 if general else 21, np.float32)
    obs[0:3] = needle_p
    obs[3:7] = _canonical(needle_q)
    obs[7:10] = ee_p
    obs[10:14] = _canonical(ee_q)
    p, q = _relative(ee_p, ee_q, needle_p, needle_q)
    obs[14:17] = p
    obs[17:21] = q
    if general:
        p, q = _relative(goal_p, goal_q, needle_p, needle_q)
        obs[21:24] = p
        obs[24:28] = q
        p, q = _relative(ee_p, ee_q, goal_p, goal_q)
        obs[28:31] = p
        obs[31:35] = q
        obs[35] = radius
        obs[36] = wire
    return obs


@njit(cache=True, fastmath=True)
def _dense(x, kernel, bias, relu):
    """``x @ kernel + bias`` (float32), as rows of the kernel added in (inputs that ReLU zeroed are
    skipped: about half of them), then ReLU if asked. Faster here than BLAS's gemv at this size."""
    out = bias.copy()
    for i in range(kernel.shape[0]):
        xi = x[i]
        if xi != 0.0:
            for j in range(kernel.shape[1]):
                out[j] += xi * kernel[i, j]
    if relu:
        for j in range(out.shape[0]):
            out[j] = max(out[j], np.float32(0.0))
    return out


@njit(cache=True)
def _member_actions(kernels, biases, layers, mean, std, obs):
    """``[members, 6]`` float32: each member's ``tanh(MLP(clip((obs - mean) / std, +-5)))``."""
    members = mean.shape[0]
    out = np.empty((members, 6), np.float32)
    for m in range(members):
        x = (obs - mean[m]) / std[m]
        x = np.minimum(np.maximum(x, np.float32(-5.0)), np.float32(5.0))
        for k in range(layers):
            i = m * layers + k
            x = _dense(x, kernels[i], biases[i], k < layers - 1)
        out[m] = np.tanh(x)
    return out


# ---- collision model (regrasp_mjx.scene.distance_fn) ---------------------------------------------


@njit(cache=True)
def _segment_distance(e, i, f, j):
    """Ericson's closest points of segments ``e[i]`` and ``f[j]`` (``[., 2, 3]`` end points), as
    :func:`regrasp_mjx.scene.segment_distance`; scalar code, nothing allocated."""
    d1x, d1y, d1z = e[i, 1, 0] - e[i, 0, 0], e[i, 1, 1] - e[i, 0, 1], e[i, 1, 2] - e[i, 0, 2]
    d2x, d2y, d2z = f[j, 1, 0] - f[j, 0, 0], f[j, 1, 1] - f[j, 0, 1], f[j, 1, 2] - f[j, 0, 2]
    rx, ry, rz = e[i, 0, 0] - f[j, 0, 0], e[i, 0, 1] - f[j, 0, 1], e[i, 0, 2] - f[j, 0, 2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    ee = d2x * d2x + d2y * d2y + d2z * d2z
    b = d1x * d2x + d1y * d2y + d1z * d2z
    c = d1x * rx + d1y * ry + d1z * rz
    ff = d2x * rx + d2y * ry + d2z * rz
    denom = a * ee - b * b
    s = 0.0
    if denom > 1e-9 * a * ee:
        s = min(max((b * ff - c * ee) / denom, 0.0), 1.0)
    t = (b * s + ff) / ee
    if t < 0.0:
        s = min(max(-c / a, 0.0), 1.0)
        t = 0.0
    elif t > 1.0:
        s = min(max((b - c) / a, 0.0), 1.0)
        t = 1.0
    x = rx + d1x * s - d2x * t
    y = ry + d1y * s - d2y * t
    z = rz + d1z * s - d2z * t
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def _point_distance(seg, i, pts, j, end):
    """Distance of the end point ``pts[j, end]`` to the segment ``seg[i]`` (scalar code)."""
    dx, dy, dz = seg[i, 1, 0] - seg[i, 0, 0], seg[i, 1, 1] - seg[i, 0, 1], seg[i, 1, 2] - seg[i, 0, 2]
    px, py, pz = pts[j, end, 0] - seg[i, 0, 0], pts[j, end, 1] - seg[i, 0, 1], pts[j, end, 2] - seg[i, 0, 2]
    s = min(max((px * dx + py * dy + pz * dz) / (dx * dx + dy * dy + dz * dz), 0.0), 1.0)
    x, y, z = px - s * dx, py - s * dy, pz - s * dz
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def _place(local, pos, m, scale, out):
    """``out = pos + m @ (scale * local)`` for every end point of ``local`` ``[n, 2, 3]``."""
    for i in range(local.shape[0]):
        _place_one(local, i, pos, m, scale, out)


@njit(cache=True)
def _place_one(local, i, pos, m, scale, out):
    """``_place`` of ``local[i]`` alone."""
    for k in range(2):
        x, y, z = scale * local[i, k, 0], scale * local[i, k, 1], scale * local[i, k, 2]
        for r in range(3):
            out[i, k, r] = pos[r] + m[r, 0] * x + m[r, 1] * y + m[r, 2] * z


@njit(cache=True)
def _fixed_ends(geo, varies, needle_p, needle_m, radius, wire):
    """The world end points of the needle's and the grasping tool's capsules (fixed for a query),
    each pair's summed radius (the needle's chords scaled to its radius where the task varies
    needles), and the bounding capsules of the chord groups: for group g its axis ``groups[g]``
    (the first chord's start to the last one's end), ``reach[g]`` (the farthest chord end from that
    axis: every chord lies within it, distance to a segment being convex) and ``group_sums[t, g]``
    (the largest summed radius of tool capsule t with the group's chords)."""
    other_local, other_on_needle, pair_index, radii, tool_radii, inflation0, radius0 = geo[1:8]
    chords, group_size = geo[9], geo[10]
    scale = radius / radius0 if varies else 1.0
    other = other_local.copy()  # the grasping tool's are already in the world (e_g) frame
    for o in range(other_local.shape[0]):
        if other_on_needle[o]:
            _place_one(other_local, o, needle_p, needle_m, scale, other)
    sums = radii.copy()
    if varies:
        for t in range(pair_index.shape[0]):
            for o in range(pair_index.shape[1]):
                k = pair_index[t, o]
                grown = wire + inflation0[k] * scale if other_on_needle[o] else radii[k] - tool_radii[k]
                sums[k] = tool_radii[k] + grown
    n_groups = (chords.shape[0] + group_size - 1) // group_size
    groups = np.empty((n_groups, 2, 3))
    reach = np.zeros(n_groups)
    group_sums = np.zeros((pair_index.shape[0], n_groups))
    for g in range(n_groups):
        first, last = g * group_size, min((g + 1) * group_size, chords.shape[0]) - 1
        for r in range(3):
            groups[g, 0, r] = other[chords[first], 0, r]
            groups[g, 1, r] = other[chords[last], 1, r]
        for c in range(first, last + 1):
            for end in range(2):
                reach[g] = max(reach[g], _point_distance(groups, g, other, chords[c], end))
            for t in range(pair_index.shape[0]):
                group_sums[t, g] = max(group_sums[t, g], sums[pair_index[t, chords[c]]])
    return other, sums, groups, reach, group_sums


@njit(cache=True)
def _collides(geo, fixed, ee_p, ee_q, tool, threshold):
    """Whether the smallest signed distance over the counted pairs is below ``threshold`` for one
    end-effector pose (``tool``: scratch space for the regrasping tool's end points).

    The same verdict as comparing the minimum over every pair, found with less work: a chord
    group's bounding capsule is checked first, and its chords only when that could come closer
    than the threshold; the first pair below it ends the search."""
    tool_local, pair_index, plain, chords, group_size = geo[0], geo[3], geo[8], geo[9], geo[10]
    other, sums, groups, reach, group_sums = fixed
    _place(tool_local, ee_p, _matrix(ee_q), 1.0, tool)
    for t in range(tool_local.shape[0]):
        for o in plain:
            if _segment_distance(tool, t, other, o) - sums[pair_index[t, o]] < threshold:
                return True
        for g in range(groups.shape[0]):
            # a lower bound of the group's chords' distances (less 1e-12 m against rounding)
            if _segment_distance(tool, t, groups, g) - reach[g] - group_sums[t, g] - 1e-12 >= threshold:
                continue
            for c in range(g * group_size, min((g + 1) * group_size, chords.shape[0])):
                o = chords[c]
                if _segment_distance(tool, t, other, o) - sums[pair_index[t, o]] < threshold:
                    return True
    return False


# ---- the step and the rollout (regrasp_mjx.env.RegraspEnv.step, regrasp_mjx.rollout.rollout) -----


@njit(cache=True)
def _step(geo, consts, fixed, tool, needle_p, needle_q, ee_p, ee_q, gn_p, gn_q, action):
    """One step: the new pose, whether the swept motion collides, whether it reached the goal,
    and its translation [m]."""
    max_dp, max_drot, substeps, clearance, tol_pos, tol_rot = (
        consts[0],
        consts[1],
        consts[2],
        consts[3],
        consts[4],
        consts[5],
    )
    a = np.minimum(np.maximum(action.astype(np.float64), -1.0), 1.0)
    a = a.astype(np.float32).astype(np.float64)  # the JAX path steps the float32 action
    dp = a[:3] * max_dp
    rotvec = a[3:] * max_drot
    n = int(substeps)
    collision = False
    pos = ee_p
    quat = ee_q
    for k in range(1, n + 1):
        s = k / n
        pos = ee_p + s * dp
        quat = _qmul(_qexp(s * rotvec), ee_q)
        if _collides(geo, fixed, pos, quat, tool, clearance):
            collision = True
    quat = _canonical(quat)
    p, q = _relative(pos, quat, needle_p, needle_q)
    d = gn_p - p
    distance = math.sqrt(d @ d)
    success = (not collision) and distance <= tol_pos and _angle(gn_q, q) <= tol_rot
    return pos, quat, collision, success, math.sqrt(dp @ dp)


@njit(cache=True)
def _plan(
    kernels, biases, layers, mean, std, geo, consts, rewards, varies, general, noise, shield, needle, start, goal, radii
):
    """The rollout of one query (poses and radii rounded to float32 first, as the JAX path takes
    them). Returns ``(outcome[7], poses[H+1, 7], actions[H, 6])``, outcome ``start_valid, success,
    collision, time_out, steps, path_length [m], discounted return`` (``rewards``: a step's, a
    collision's, a success's reward and gamma)."""
    needle = needle.astype(np.float32).astype(np.float64)
    start = start.astype(np.float32).astype(np.float64)
    goal = goal.astype(np.float32).astype(np.float64)
    radius = np.float64(np.float32(radii[0]))
    wire = np.float64(np.float32(radii[1]))
    horizon = noise.shape[0]
    poses = np.empty((horizon + 1, 7))
    actions = np.zeros((horizon, 6))
    poses[0] = start
    needle_p = needle[:3].copy()
    needle_q = needle[3:] / math.sqrt(needle[3:] @ needle[3:])
    ee_p = start[:3].copy()
    ee_q = start[3:] / math.sqrt(start[3:] @ start[3:])
    goal_p = goal[:3].copy()
    goal_q = goal[3:] / math.sqrt(goal[3:] @ goal[3:])
    fixed = _fixed_ends(geo, varies, needle_p, _matrix(needle_q), radius, wire)
    tool = np.empty_like(geo[0])
    gn_p, gn_q = _relative(goal_p, goal_q, needle_p, needle_q)
    outcome = np.zeros(7)
    valid = not _collides(geo, fixed, ee_p, ee_q, tool, consts[3])
    outcome[0] = 1.0 if valid else 0.0
    if not valid:
        outcome[2] = 1.0
        poses[1:] = start
        return outcome, poses, actions
    length = 0.0
    steps = 0
    members = mean.shape[0]
    for t in range(horizon):
        obs = _observe(general, needle_p, needle_q, ee_p, ee_q, goal_p, goal_q, radius, wire)
        own = _member_actions(kernels, biases, layers, mean, std, obs)
        a = own[0].copy()
        for m in range(1, members):
            a += own[m]
        if members > 1:
            a /= np.float32(members)
        pos, quat, collision, success, dl = _step(
            geo, consts, fixed, tool, needle_p, needle_q, ee_p, ee_q, gn_p, gn_q, a
        )
        if collision and shield:
            # the alternatives in shield_candidates' order: each member's own (an ensemble), half
            # the action, then the action plus the step's fixed noise, clipped; the first free one
            extra = members if members > 1 else 0
            for c in range(extra + 1 + noise.shape[1]):
                if c < extra:
                    cand = own[c].copy()
                elif c == extra:
                    cand = np.float32(0.5) * a
                else:
                    cand = np.minimum(np.maximum(a + noise[t, c - extra - 1], np.float32(-1.0)), np.float32(1.0))
                p2, q2, col2, suc2, dl2 = _step(
                    geo, consts, fixed, tool, needle_p, needle_q, ee_p, ee_q, gn_p, gn_q, cand
                )
                if not col2:
                    a, pos, quat, collision, success, dl = cand, p2, q2, col2, suc2, dl2
                    break
        # the state as the JAX path keeps it, in float32 (the two paths' rounding drifts apart less)
        ee_p, ee_q = pos.astype(np.float32).astype(np.float64), quat.astype(np.float32).astype(np.float64)
        length += dl
        steps = t + 1
        poses[steps, :3] = ee_p
        poses[steps, 3:] = ee_q
        actions[t] = np.minimum(np.maximum(a, np.float32(-1.0)), np.float32(1.0))
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
    for k in range(steps + 1, horizon + 1):
        poses[k] = poses[steps]
    return outcome, poses, actions


class LeanPlanner:
    """A policy's planning rollout for one query at a time on the CPU (see the module docstring).

    ``LeanPlanner(env_config, weights)`` with ``weights`` one ``(params, mean, std)`` per member (a
    ``Policy``'s); calling it with ``(needle[7], start[7], goal[7], radii[2])`` returns
    :class:`~regrasp_mjx.planner.PlanArrays` with a batch axis of one, as the JAX planner does.
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
                env.substeps,
                np.float32(env.clearance),
                np.float32(cfg.success_pos_mm * 1e-3),
                np.float32(math.radians(cfg.success_rot_deg)),
            ],
            np.float64,
        )
        self.geo = _geometry(env)
        kernels, biases, layers = [], [], None
        for params, _, _ in weights:
            names = sorted(params["params"], key=lambda n: int(n.rsplit("_", 1)[1]))
            layers = len(names)
            for name in names:
                kernels.append(np.ascontiguousarray(np.asarray(params["params"][name]["kernel"], np.float32)))
                biases.append(np.asarray(params["params"][name]["bias"], np.float32))
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

    def goal(self, needle: np.ndarray, grasp: np.ndarray, radius: float) -> np.ndarray:
        """The goal end-effector pose ``[7]`` (e_g) of a goal grasp ``(alpha*, d* [m], theta*, phi*)``
        on a needle of ``radius`` [m] at ``needle`` ``[7]``."""
        g = np.asarray(grasp, np.float64)
        return _goal_pose(np.asarray(needle, np.float64), g[0], g[1], g[2], g[3], float(radius))

    def __call__(self, needle: np.ndarray, start: np.ndarray, goal: np.ndarray, radii: np.ndarray) -> PlanArrays:
        f64 = lambda x: np.ascontiguousarray(x, np.float64).reshape(-1)  # noqa: E731
        outcome, poses, actions = _plan(
            *self.net, self.geo, self.consts, self.rewards, self.varies, self.general, self.noise, self.shield,
            f64(needle), f64(start), f64(goal), f64(radii),
        )  # fmt: skip
        valid, success, collision, time_out, steps, length, ret = outcome.tolist()
        one = lambda x, dtype: np.array([x], dtype)  # noqa: E731
        out = Rollout(
            start_valid=one(valid > 0, bool),
            success=one(success > 0, bool),
            collision=one(collision > 0, bool),
            time_out=one(time_out > 0, bool),
            steps=one(steps, np.int32),
            path_length_mm=one(length * 1e3, np.float32),
            discounted_return=one(ret, np.float32),
        )
        n = int(steps)  # the trajectory up to its end, float32 as the JAX planner returns it
        return PlanArrays(out, poses[None, : n + 1].astype(np.float32), actions[None, :n].astype(np.float32))


def _geometry(env: RegraspEnv) -> tuple:
    """The counted pairs' capsules (``Scene.capsule_frames``: every regrasping capsule paired with
    every counted one, pair ``t * O + o``) as the compiled loops take them, the radii rounded as
    ``Scene.distance_fn`` holds them (float32)."""
    f = env.scene.capsule_frames
    n_tools, n_others = len(f.tool_ends), len(f.other_ends)
    f32 = lambda x: np.asarray(x, np.float32).astype(np.float64)  # noqa: E731
    per_pair = lambda tool, other: (tool[:, None] + other[None, :]).ravel()  # noqa: E731
    return (
        f.tool_ends,
        f.other_ends,
        f.on_needle,
        np.arange(n_tools * n_others).reshape(n_tools, n_others),
        f32(per_pair(f.tool_radii, f.other_radii)),
        f32(per_pair(f.tool_radii, np.zeros(n_others))),
        f32(per_pair(np.zeros(n_tools), f.inflation)),
        float(np.float32(env.scene.config.needle_radius_mm * 1e-3)),
        np.flatnonzero(~f.on_needle),
        f.chords,
        CHORD_GROUP,
    )
