"""The regrasping jaws for one query, compiled with numba (the lean planner's, issue 67): the tool's
capsules with its jaws opened, and the proof that opening them, the tool holding still, keeps a
margin from the needle and the grasping tool.

The environment (:meth:`regrasp_mjx.envs.env.RegraspEnv.move`) opens the jaws of a policy trained to
(``EnvConfig.jaw_open_deg``) from the scene's opening to that one before the first step whose start
leaves the sweep ``jaw_open_margin_mm``; the sweep is proved by :func:`regrasp_mjx.world.jaw.sweep_fn`:
the jaws at :data:`~regrasp_mjx.world.jaw.SWEEP_STEPS` + 1 openings evenly between the two, their
least clearance less how far a jaw point moves between two of them (``reach * delta / 4``).
:func:`sweep_keeps` gives that verdict with the same check points and slack; the openings are fixed
(the scene's, ``jaw_open_deg``), so the check points' capsules are turned once per policy
(:func:`jaws`). A pair whose bounds keep it clear at every opening is skipped: a sphere and, for the
needle's chord groups, a capsule around the jaw at the middle check point, grown by the farthest a
jaw point turns from there (:attr:`Jaws.turn`).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from regrasp_mjx.envs.lean_collision import BOUND_SLACK
from regrasp_mjx.envs.lean_geometry import matrix, rotate, segment_distance
from regrasp_mjx.world import jaw


class Jaws(NamedTuple):
    """A policy's jaws that open on the way as the compiled loops take them: the jaw capsules
    opened and the sweep's check points. A policy whose jaws stay has None instead: numba prunes
    every branch on it (:func:`as_jaws`, :func:`opens_here`), so its loops compile to the code they
    had before the jaws opened (a flag tested at every step cost the default's plan 10 %). A query
    opens the jaws in its own copy of the tool's capsules (:func:`own_capsules`, :func:`open_jaws`):
    no second set of capsules to choose from at every step."""

    base_deg: float  # the scene's opening
    open_deg: float  # jaw_open_deg
    rows: np.ndarray  # [J] the jaw capsules' rows in Capsules.tool_local
    opened: np.ndarray  # [J, 2, 3] the jaw capsules at open_deg (e_r)
    sweep: np.ndarray  # [A, J, 2, 3] the jaws at each check point of the opening sweep (e_r)
    turn: float  # the farthest a jaw point moves from the middle check point to any other [m]
    slack: float  # how far a jaw point moves between two check points, reach * delta / 4 [m]
    margin: float  # the room the sweep must keep to open [m]


def jaws(scene: Any, open_deg: float | None, margin: float) -> Jaws | None:
    """:class:`Jaws` of a scene (a :class:`~regrasp_mjx.world.scene.Scene`), its opening on the way
    ``open_deg`` (None: they never open, and None is returned) and the margin [m] (rounded to
    float32, as the environment's comparison takes it)."""
    if open_deg is None:
        return None
    base = float(scene.config.jaw_angle_deg)
    rows = jaw.jaw_rows(scene)
    # the check points of sweep_fn from the scene's opening to open_deg: the same fractions and slack
    angles = base + (open_deg - base) * np.linspace(0.0, 1.0, jaw.SWEEP_STEPS + 1)
    sweep = np.ascontiguousarray(np.stack([jaw.opened_ends(scene, a)[rows] for a in angles]))
    reach = jaw.jaw_reach(scene)
    slack = reach * math.radians(abs(open_deg - base) / jaw.SWEEP_STEPS) / 4.0
    middle = angles[len(angles) // 2]
    # a point r from the hinge turned by x moves 2 r sin(x / 2) <= r x; the jaws turn by half the change
    turn = reach * math.radians(max(middle - angles[0], angles[-1] - middle) / 2.0)
    opened = np.ascontiguousarray(jaw.opened_ends(scene, open_deg)[rows])
    return Jaws(base, float(open_deg), rows, opened, sweep, turn, slack, float(np.float32(margin)))


@njit(cache=True)
def as_jaws(j):
    """:class:`Jaws` of its fields as a plain tuple (a query's state), or None (jaws that stay)."""
    if j is None:
        return None
    return Jaws(*j)


@njit(cache=True)
def own_capsules(j, tool_local):
    """The tool's capsules ``[T, 2, 3]`` a query works with: its own copy where the jaws open on the
    way (:func:`open_jaws` writes into it), else the policy's shared ones."""
    if j is None:
        return tool_local
    return tool_local.copy()


@njit(cache=True)
def sweep_points(j):
    """How many check points the opening sweep has (0: the jaws stay)."""
    if j is None:
        return 0
    return j.sweep.shape[0]


@njit(cache=True)
def open_jaws(j, tool_local):
    """The jaws opened to ``j.open_deg`` in a query's own tool capsules ``tool_local`` ``[T, 2, 3]``
    (:func:`own_capsules`; turning about the hinge keeps every end point's distance from it and every
    capsule's length: the levers and half lengths stay); nothing where they stay (``j`` None)."""
    if j is None:
        return
    for jj in range(j.rows.shape[0]):
        tool_local[j.rows[jj]] = j.opened[jj]


@njit(cache=True)
def opens_here(j, geo, fixed, ee_p, ee_q, ends):
    """Whether the environment's rule (:meth:`regrasp_mjx.envs.env.RegraspEnv.move`) opens the jaws
    before a step from the pose ``(ee_p, ee_q)``: the sweep keeps its margin there (:func:`sweep_keeps`;
    where it does they open in ``geo``, the query's capsules); never where they stay (``j`` None)."""
    if j is None:
        return False
    if not sweep_keeps(j, geo, fixed, ee_p, ee_q, ends):
        return False
    open_jaws(j, geo.tool_local)
    return True


@njit(cache=True)
def _place(local, a, j, pos, m, out, i):
    """``out[i] = pos + m @ local[a, j]`` for both end points."""
    for k in range(2):
        w = rotate(m, local[a, j, k, 0], local[a, j, k, 1], local[a, j, k, 2])
        out[i, k, 0], out[i, k, 1], out[i, k, 2] = pos[0] + w[0], pos[1] + w[1], pos[2] + w[2]


@njit(cache=True)
def _below(ends, middle, turn, step, other, o, sums, below):
    """Whether the jaw at some check point (``ends`` ``[A, 2, 3]``) comes nearer counted capsule
    ``other[o]`` than ``below`` (its surface distance: the axes' less ``sums``): the verdict of every
    check point's distance, found with fewer. The middle check point's less ``turn`` bounds them all
    (one distance, not A, for most pairs); a check point's less ``step`` per check point between
    bounds its neighbours' (a jaw point moves at most ``step`` from one to the next), so those it
    keeps at or above ``below`` are not computed."""
    if segment_distance(ends, middle, other, o) - sums - turn - BOUND_SLACK >= below:
        return False
    a = 0
    while a < ends.shape[0]:
        room = segment_distance(ends, a, other, o) - sums - below
        if room < 0.0:
            return True
        a += 1 + int((room - BOUND_SLACK) / step) if room > BOUND_SLACK else 1
    return False


@njit(cache=True)
def sweep_keeps(j, geo, fixed, ee_p, ee_q, ends):
    """Whether opening the jaws from the scene's opening to ``j.open_deg`` at the pose ``(ee_p,
    ee_q)`` (tuples, ``ee_q`` unit) keeps ``j.margin``: :func:`regrasp_mjx.world.jaw.sweep_fn`'s least
    clearance less its slack, at or above the margin, for every jaw, check point and counted capsule
    (``fixed``: :func:`~regrasp_mjx.envs.lean_collision.fixed_ends` of the query's needle; ``ends``
    ``[>= A, 2, 3]`` scratch for one jaw's check points placed)."""
    f = fixed
    below = j.margin + j.slack  # a pair whose surface distance keeps this keeps the margin
    step = 2.0 * j.slack  # how far a jaw point moves from one check point to the next (the slack is half)
    m = matrix(ee_q)
    n_points = j.sweep.shape[0]
    middle = n_points // 2
    for jj in range(j.rows.shape[0]):
        t = j.rows[jj]
        for a in range(n_points):
            _place(j.sweep, a, jj, ee_p, m, ends, a)
        # a sphere about the middle check point's axis midpoint holds the jaw's axis at every check point
        cx = 0.5 * (ends[middle, 0, 0] + ends[middle, 1, 0])
        cy = 0.5 * (ends[middle, 0, 1] + ends[middle, 1, 1])
        cz = 0.5 * (ends[middle, 0, 2] + ends[middle, 1, 2])
        clear = geo.tool_half[t] + j.turn + below + BOUND_SLACK  # a pair whose bound reaches this is clear
        for o in geo.plain:
            k = geo.pair_index[t, o]
            if _gap(f.other_mid, o, cx, cy, cz) - f.other_half[o] - f.sums[k] >= clear:
                continue
            if _below(ends[:n_points], middle, j.turn, step, f.other, o, f.sums[k], below):
                return False
        if (
            math.sqrt(_sq(f.needle[0] - cx, f.needle[1] - cy, f.needle[2] - cz)) - f.needle[3] - f.needle_sums[t]
            >= clear
        ):
            continue
        for g in range(f.groups.shape[0]):
            if _gap(f.centre, g, cx, cy, cz) - f.ball[g] - f.group_sums[t, g] >= clear:
                continue
            # the group's bounding capsule against the middle check point's axis, less the turn
            near = segment_distance(ends, middle, f.groups, g) - f.reach[g] - f.group_sums[t, g] - j.turn
            if near - BOUND_SLACK >= below:
                continue
            for c in range(g * geo.group_size, min((g + 1) * geo.group_size, geo.chords.shape[0])):
                o = geo.chords[c]
                if _below(ends[:n_points], middle, j.turn, step, f.other, o, f.sums[geo.pair_index[t, o]], below):
                    return False
    return True


@njit(cache=True)
def _sq(x, y, z):
    return x * x + y * y + z * z


@njit(cache=True)
def _gap(points, i, cx, cy, cz):
    """Distance of ``points[i]`` to ``(cx, cy, cz)``."""
    return math.sqrt(_sq(points[i, 0] - cx, points[i, 1] - cy, points[i, 2] - cz))
