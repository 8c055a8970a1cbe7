"""The collision model for one query, compiled with numba (the lean planner's and the OMPL planners'
``checker="lean"``): the counted pairs' capsules (:meth:`regrasp_mjx.world.scene.Scene.distance_fn`'s),
placed for a needle once per query and tested for one end-effector pose, or one motion, at a time.

A collision test needs only whether the closest counted pair comes nearer than a threshold, not
its distance, so each pair is first bounded from below by its capsules' bounding spheres (a few
flops), the needle's 56 chords are bounded as a whole and in groups of :data:`CHORD_GROUP`, and
the first pair below the threshold ends the test: the verdict of the minimum over every pair with a
fraction of the work (tests/test_lean_planner.py checks it against the closest pair).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit, types
from numba.experimental import structref

from regrasp_mjx.envs.lean_geometry import matrix, point_distance, qexp, qmul, rotate, segment_distance, segment_gap
from regrasp_mjx.world.continuous import MAX_TESTS, RESOLUTION
from regrasp_mjx.world.continuous import SLACK as MOTION_SLACK

# chords per bounding capsule in the collision test (7 x 8 for the MJCF's 56; measured fastest of
# 4, 7, 8 and 14 with experiments/bench_plan.py)
CHORD_GROUP = 7

# lower bounds are computed in floating point: this much is taken off them against rounding, so a
# bound never skips a pair whose exact distance is below the threshold
BOUND_SLACK = 1e-12


@njit(cache=True)
def _norm(ends, i, k):
    """The length of end point ``k`` of capsule ``i``."""
    return math.sqrt(ends[i, k, 0] * ends[i, k, 0] + ends[i, k, 1] * ends[i, k, 1] + ends[i, k, 2] * ends[i, k, 2])


@njit(cache=True)
def _sphere_gap(mid, i, cx, cy, cz):
    """Distance of ``mid[i]`` to the point ``(cx, cy, cz)``."""
    x, y, z = mid[i, 0] - cx, mid[i, 1] - cy, mid[i, 2] - cz
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def _place(local, i, pos, m, scale, out):
    """``out[i] = pos + m @ (scale * local[i])`` for both end points of capsule i."""
    for k in range(2):
        w = rotate(m, scale * local[i, k, 0], scale * local[i, k, 1], scale * local[i, k, 2])
        out[i, k, 0], out[i, k, 1], out[i, k, 2] = pos[0] + w[0], pos[1] + w[1], pos[2] + w[2]


@njit(cache=True)
def _midpoints(ends, mid, half):
    for i in range(ends.shape[0]):
        dx, dy, dz = ends[i, 1, 0] - ends[i, 0, 0], ends[i, 1, 1] - ends[i, 0, 1], ends[i, 1, 2] - ends[i, 0, 2]
        for r in range(3):
            mid[i, r] = 0.5 * (ends[i, 0, r] + ends[i, 1, r])
        half[i] = 0.5 * math.sqrt(dx * dx + dy * dy + dz * dz)


# ---- the collision model (regrasp_mjx.world.scene.distance_fn) -----------------------------------------


class Capsules(NamedTuple):
    """The counted pairs' capsules (``Scene.capsule_frames``: every regrasping capsule t paired with
    every counted one o, pair ``t * O + o``) as the compiled loops take them, radii rounded as
    ``Scene.distance_fn`` holds them (float32), and the needle's chords' bounds in its own frame
    (at the scene's radius; a query moves and scales them)."""

    tool_local: np.ndarray  # [T, 2, 3] end points in the regrasping end-effector frame
    tool_half: np.ndarray  # [T] half lengths
    other_local: np.ndarray  # [O, 2, 3] in the needle frame (chords) or e_g (the grasping tool)
    on_needle: np.ndarray  # [O] bool
    pair_index: np.ndarray  # [T, O] -> pair
    radii: np.ndarray  # [T * O] summed radii at the scene's needle
    tool_radii: np.ndarray  # [T * O] the tool capsule's radius
    inflation: np.ndarray  # [T * O] a chord's growth over the wire at the scene's radius
    radius0: float  # the scene's needle radius [m]
    plain: np.ndarray  # the others that are not chords
    chords: np.ndarray  # [C] the chords along the arc
    group_size: int
    group_axis: np.ndarray  # [G, 2, 3] each group's first chord start to last chord end
    group_reach: np.ndarray  # [G] the farthest chord end from that axis
    group_centre: np.ndarray  # [G, 3] the axis' midpoint
    group_ball: np.ndarray  # [G] the farthest chord end from that centre
    needle_centre: np.ndarray  # [3] the centre of the chords' bounding box
    needle_ball: float  # the farthest chord end from it


class Fixed(NamedTuple):
    """What stays fixed over a query: the others' capsules placed, their bounds, and summed radii."""

    other: np.ndarray  # [O, 2, 3] in e_g
    sums: np.ndarray  # [T * O] summed radii of each pair at the query's needle
    other_mid: np.ndarray  # [O, 3]
    other_half: np.ndarray  # [O]
    groups: np.ndarray  # [G, 2, 3] the group axes placed
    reach: np.ndarray  # [G]
    centre: np.ndarray  # [G, 3]
    ball: np.ndarray  # [G]
    group_sums: np.ndarray  # [T, G] the largest summed radius of tool capsule t with group g's chords
    needle: tuple  # (x, y, z, r): a sphere holding every chord
    needle_sums: np.ndarray  # [T] the largest summed radius of tool capsule t with any chord


def capsules(frames: Any, needle_radius: float, group_size: int = CHORD_GROUP) -> Capsules:
    """:class:`Capsules` of a scene's ``capsule_frames`` and needle radius [m]."""
    f = frames
    n_tools, n_others = len(f.tool_ends), len(f.other_ends)
    f32 = lambda x: np.asarray(x, np.float32).astype(np.float64)  # noqa: E731
    per_pair = lambda tool, other: (tool[:, None] + other[None, :]).ravel()  # noqa: E731
    ends = f.other_ends[f.chords]  # [C, 2, 3] along the arc
    starts = np.arange(0, len(ends), group_size)
    axis = np.stack([ends[starts, 0], ends[np.minimum(starts + group_size, len(ends)) - 1, 1]], axis=1)
    centre = axis.mean(axis=1)
    reach, ball = np.zeros(len(starts)), np.zeros(len(starts))
    for g, first in enumerate(starts):
        points = ends[first : first + group_size].reshape(-1, 3)
        reach[g] = max(point_distance(axis, g, *p) for p in points)
        ball[g] = np.linalg.norm(points - centre[g], axis=1).max()
    points = ends.reshape(-1, 3)
    needle_centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return Capsules(
        tool_local=np.asarray(f.tool_ends, np.float64),
        tool_half=0.5 * np.linalg.norm(f.tool_ends[:, 1] - f.tool_ends[:, 0], axis=-1),
        other_local=np.asarray(f.other_ends, np.float64),
        on_needle=np.asarray(f.on_needle, bool),
        pair_index=np.arange(n_tools * n_others).reshape(n_tools, n_others),
        radii=f32(per_pair(f.tool_radii, f.other_radii)),
        tool_radii=f32(per_pair(f.tool_radii, np.zeros(n_others))),
        inflation=f32(per_pair(np.zeros(n_tools), f.inflation)),
        radius0=float(np.float32(needle_radius)),
        plain=np.flatnonzero(~np.asarray(f.on_needle)),
        chords=np.asarray(f.chords, np.int64),
        group_size=int(group_size),
        group_axis=axis,
        group_reach=reach,
        group_centre=centre,
        group_ball=ball,
        needle_centre=needle_centre,
        needle_ball=float(np.linalg.norm(points - needle_centre, axis=1).max()),
    )


@njit(cache=True)
def fixed_ends(geo, varies, needle_p, needle_q, radius, wire):
    """:class:`Fixed` for a needle at ``(needle_p, needle_q)`` (tuples) of ``radius`` and ``wire``
    radius [m]: the chords and their bounds moved (and scaled to its radius where the task varies
    needles), each pair's summed radius."""
    scale = radius / geo.radius0 if varies else 1.0
    m = matrix(needle_q)
    other = geo.other_local.copy()  # the grasping tool's are already in the world (e_g) frame
    for o in range(other.shape[0]):
        if geo.on_needle[o]:
            _place(geo.other_local, o, needle_p, m, scale, other)
    other_mid, other_half = np.empty((other.shape[0], 3)), np.empty(other.shape[0])
    _midpoints(other, other_mid, other_half)
    sums = geo.radii.copy()
    n_tools, n_groups = geo.pair_index.shape[0], geo.group_axis.shape[0]
    if varies:
        for t in range(n_tools):
            for o in range(geo.pair_index.shape[1]):
                k = geo.pair_index[t, o]
                grown = wire + geo.inflation[k] * scale if geo.on_needle[o] else geo.radii[k] - geo.tool_radii[k]
                sums[k] = geo.tool_radii[k] + grown
    groups = np.empty_like(geo.group_axis)
    centre = np.empty_like(geo.group_centre)
    group_sums = np.zeros((n_tools, n_groups))
    needle_sums = np.zeros(n_tools)
    for g in range(n_groups):
        _place(geo.group_axis, g, needle_p, m, scale, groups)
        c = rotate(m, scale * geo.group_centre[g, 0], scale * geo.group_centre[g, 1], scale * geo.group_centre[g, 2])
        centre[g, 0], centre[g, 1], centre[g, 2] = needle_p[0] + c[0], needle_p[1] + c[1], needle_p[2] + c[2]
        for i in range(g * geo.group_size, min((g + 1) * geo.group_size, geo.chords.shape[0])):
            for t in range(n_tools):
                group_sums[t, g] = max(group_sums[t, g], sums[geo.pair_index[t, geo.chords[i]]])
        for t in range(n_tools):
            needle_sums[t] = max(needle_sums[t], group_sums[t, g])
    c = geo.needle_centre
    c = rotate(m, scale * c[0], scale * c[1], scale * c[2])
    needle = (needle_p[0] + c[0], needle_p[1] + c[1], needle_p[2] + c[2], scale * geo.needle_ball)
    reach, ball = scale * geo.group_reach, scale * geo.group_ball
    return Fixed(other, sums, other_mid, other_half, groups, reach, centre, ball, group_sums, needle, needle_sums)


@njit(cache=True)
def collides(geo, fixed, ee_p, ee_q, tool, tool_mid, threshold):
    """Whether the smallest signed distance over the counted pairs is below ``threshold`` for one
    end-effector pose (``ee_p`` a 3-tuple, ``ee_q`` a unit 4-tuple; ``tool`` ``[T, 2, 3]`` and
    ``tool_mid`` ``[T, 3]``: scratch space for the regrasping tool's end points and midpoints).

    The same verdict as comparing the minimum over every pair, found with less work: a pair is
    skipped when its bounding spheres keep it at least ``threshold`` apart; the needle's chords
    when a sphere holding them all does, then group by group by a sphere and a bounding capsule;
    the first pair below the threshold ends the search."""
    return interval_collides(geo, fixed, ee_p, ee_q, tool, tool_mid, threshold, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


@njit(cache=True)
def interval_collides(geo, fixed, ee_p, ee_q, tool, tool_mid, threshold, h, dp, w):
    """:func:`collides` of the interval of half-width ``h`` about the pose (``h`` 0: the pose
    alone) of the motion ``(dp, w)`` (per unit s): False proves every pair at or above ``threshold``
    over the whole interval by :func:`regrasp_mjx.world.continuous.interval_low`'s bounds (its
    verdict): the motion bound culls (each tool capsule t's threshold raised by ``h (|dp| + |w|
    L_t)``, what the bounding spheres test), the directional bound decides a pair the motion bound
    leaves below."""
    f = fixed
    m = matrix(ee_q)
    n_tools = geo.tool_local.shape[0]
    for t in range(n_tools):
        _place(geo.tool_local, t, ee_p, m, 1.0, tool)
        for r in range(3):
            tool_mid[t, r] = 0.5 * (tool[t, 0, r] + tool[t, 1, r])
    move = math.sqrt(dp[0] * dp[0] + dp[1] * dp[1] + dp[2] * dp[2])
    turn = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    for t in range(n_tools):
        below = threshold
        bend = 0.0
        if h > 0.0:  # its end point farthest from the end-effector's origin moves the most
            lever = max(_norm(geo.tool_local, t, 0), _norm(geo.tool_local, t, 1))
            below += h * (move + turn * lever) + MOTION_SLACK
            bend = _bend(tool, t, ee_p, w, turn, h)
        clear = geo.tool_half[t] + below + BOUND_SLACK  # a pair whose bound reaches this is clear
        for o in geo.plain:
            k = geo.pair_index[t, o]
            gap = _sphere_gap(tool_mid, t, f.other_mid[o, 0], f.other_mid[o, 1], f.other_mid[o, 2])
            if gap - f.other_half[o] - f.sums[k] >= clear:
                continue
            if _pair_below(tool, t, f.other, o, f.sums[k], below, threshold, ee_p, h, dp, w, bend):
                return True
        if _sphere_gap(tool_mid, t, f.needle[0], f.needle[1], f.needle[2]) - f.needle[3] - f.needle_sums[t] >= clear:
            continue
        for g in range(f.groups.shape[0]):
            gap = _sphere_gap(tool_mid, t, f.centre[g, 0], f.centre[g, 1], f.centre[g, 2])
            if gap - f.ball[g] - f.group_sums[t, g] >= clear:
                continue
            if segment_distance(tool, t, f.groups, g) - f.reach[g] - f.group_sums[t, g] - BOUND_SLACK >= below:
                continue
            for c in range(g * geo.group_size, min((g + 1) * geo.group_size, geo.chords.shape[0])):
                o = geo.chords[c]
                k = geo.pair_index[t, o]
                if _pair_below(tool, t, f.other, o, f.sums[k], below, threshold, ee_p, h, dp, w, bend):
                    return True
    return False


@njit(cache=True)
def _bend(tool, t, ee_p, w, turn, h):
    """The second-order part of the directional bound for tool capsule t: its end points' largest
    distance from the rotation axis through ``ee_p``, times ``phi^2 (1/2 + phi/6)``, phi = h |w|."""
    if turn == 0.0:
        return 0.0
    ax, ay, az = w[0] / turn, w[1] / turn, w[2] / turn
    rho = 0.0
    for k in range(2):
        rx, ry, rz = tool[t, k, 0] - ee_p[0], tool[t, k, 1] - ee_p[1], tool[t, k, 2] - ee_p[2]
        c = rx * ax + ry * ay + rz * az
        rx, ry, rz = rx - c * ax, ry - c * ay, rz - c * az
        rho = max(rho, math.sqrt(rx * rx + ry * ry + rz * rz))
    phi = h * turn
    return rho * phi * phi * (0.5 + phi / 6.0)


@njit(cache=True)
def _pair_below(tool, t, other, o, sums, below, threshold, ee_p, h, dp, w, bend):
    """Whether pair (t, o) is not proved at or above ``threshold``: its distance below ``below``
    (the motion bound's raised threshold) and, over an interval (``h`` > 0), its directional bound
    too (:func:`regrasp_mjx.world.continuous.interval_low`)."""
    x, y, z = segment_gap(tool, t, other, o)
    length = math.sqrt(x * x + y * y + z * z)
    if length - sums >= below:
        return False
    if h == 0.0 or length == 0.0:
        return True
    nx, ny, nz = x / length, y / length, z / length
    a0 = tool[t, 0, 0] * nx + tool[t, 0, 1] * ny + tool[t, 0, 2] * nz
    a1 = tool[t, 1, 0] * nx + tool[t, 1, 1] * ny + tool[t, 1, 2] * nz
    b0 = other[o, 0, 0] * nx + other[o, 0, 1] * ny + other[o, 0, 2] * nz
    b1 = other[o, 1, 0] * nx + other[o, 1, 1] * ny + other[o, 1, 2] * nz
    fall = 0.0
    for k in range(2):
        rx, ry, rz = tool[t, k, 0] - ee_p[0], tool[t, k, 1] - ee_p[1], tool[t, k, 2] - ee_p[2]
        vx = dp[0] + w[1] * rz - w[2] * ry
        vy = dp[1] + w[2] * rx - w[0] * rz
        vz = dp[2] + w[0] * ry - w[1] * rx
        fall = max(fall, abs(vx * nx + vy * ny + vz * nz))
    return min(a0, a1) - max(b0, b1) - sums - h * fall - bend - threshold < MOTION_SLACK


@njit(cache=True)
def make_scratch(tool_local, rows=0):
    """The scratch arrays a collision test writes, for tool capsules ``tool_local`` ``[T, 2, 3]``:
    the tool's end points (at least ``rows`` of them: room for the jaws' sweep,
    :func:`regrasp_mjx.envs.lean_jaw.sweep_keeps`) and midpoints, and the continuous test's stack of
    intervals (depth first: at most one more than the halvings, far under 64)."""
    ends = np.empty((max(tool_local.shape[0], rows), 2, 3))
    return ends, np.empty((tool_local.shape[0], 3)), np.zeros((64, 2), np.int64)


# ---- what a compiled call takes: many arrays as one ----------------------------------------------


@structref.register
class _HeldType(types.StructRef):
    """numba's type of :class:`Held`."""

    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


class Held(structref.StructRefProxy):
    """A tuple of arrays (its ``state``) held in one native object: a compiled call unboxes it as
    one pointer, where numba unboxes a tuple array by array (about 0.08 us each; the lean planner's
    state has some 30)."""


structref.define_proxy(Held, _HeldType, ["state"])


@njit(cache=True)
def hold(state):
    """``Held(state)``, made in compiled code (``Held(...)`` from Python would compile uncached)."""
    return Held(state)


@njit(cache=True)
def motion_collides(geo, fixed, p0, q0, dp, w, threshold, tool, tool_mid, stack):
    """Whether the motion ``(p0 + s dp, exp(s w) q0)``, s in [0, 1] (tuples; ``q0`` unit), comes
    below ``threshold`` anywhere: :func:`regrasp_mjx.world.continuous_walk.motion_collides`' verdict, each
    interval proved by one :func:`interval_collides` at its midpoint (``stack``: ``[64, 2]`` int64
    scratch): the root's midpoint first, which proves most steps in one test; where it does not, the end
    pose is tested for a collision before the halves (a step into the needle usually ends in it)."""
    move, turn = (
        math.sqrt(dp[0] * dp[0] + dp[1] * dp[1] + dp[2] * dp[2]),
        math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]),
    )
    lever = 0.0
    for t in range(geo.tool_local.shape[0]):
        lever = max(lever, _norm(geo.tool_local, t, 0), _norm(geo.tool_local, t, 1))
    fastest = move + turn * lever
    stack[0, 0], stack[0, 1] = 0, 0
    n, tests = 1, 0
    while n > 0:
        n -= 1
        tests += 1
        k, i = stack[n, 0], stack[n, 1]
        h = math.ldexp(1.0, -(k + 1))
        s = (2 * i + 1) * h
        at = (p0[0] + s * dp[0], p0[1] + s * dp[1], p0[2] + s * dp[2])
        at_q = qmul(qexp(s * w[0], s * w[1], s * w[2]), q0)
        if not interval_collides(geo, fixed, at, at_q, tool, tool_mid, threshold, h, dp, w):
            continue
        if h * fastest <= RESOLUTION or tests >= MAX_TESTS or n + 2 > stack.shape[0]:
            return True
        if k == 0:  # the root not proved: the end pose first (a collision there ends the test)
            end_q = qmul(qexp(w[0], w[1], w[2]), q0)
            if collides(geo, fixed, (p0[0] + dp[0], p0[1] + dp[1], p0[2] + dp[2]), end_q, tool, tool_mid, threshold):
                return True
        if collides(geo, fixed, at, at_q, tool, tool_mid, threshold):
            return True
        stack[n, 0], stack[n, 1] = k + 1, 2 * i + 1
        stack[n + 1, 0], stack[n + 1, 1] = k + 1, 2 * i
        n += 2
    return False
