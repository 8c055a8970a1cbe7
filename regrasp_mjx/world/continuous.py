"""The continuous collision test of a motion: free only where every pose along it is proved clear.

A motion moves the regrasping end-effector from ``(p0, q0)`` along ``p(s) = p0 + s dp``,
``q(s) = exp(s w) q0``, s in [0, 1] (an environment step; and OMPL's interpolation, position linear
and orientation slerped, is the same curve with ``w`` the shortest rotation vector of ``q1 q0^-1``).

Conservative advancement by bisection (the standard continuous test, as FCL's): an interval of
half-width h about s_m is proved clear when every pair's distance has a lower bound over the whole
interval, from its pose at s_m alone, of at least the clearance margin m (:func:`interval_low`, two
bounds, the larger taken):

- the motion bound: a point of tool capsule t at ``x`` in the end-effector frame moves at most
  ``v_t = |dp| + |w| L_t`` per unit s (``L_t`` its farthest end point from the end-effector's origin,
  :func:`levers`), so the pair's distance falls by at most ``h v_t``;
- the directional bound (a separating plane, second order in h): with ``n`` the unit vector between
  the pair's closest points, the capsules are at least ``sep`` apart along n (support functions of
  their segments, less the radii; ``sep`` = the distance where n is exact, a lower bound for any n),
  and a point ``r`` from the end-effector's origin at s_m moves along n by at most
  ``h |(dp + w x r) . n| + rho (phi^2 / 2 + phi^3 / 6)`` within the interval (``phi = h |w|``,
  ``rho`` its distance from the rotation axis; Rodrigues' formula: the first-order term exact, the
  rest bounded), largest at a segment's end point. A jaw sliding along the wire, which the motion
  bound proves only in tests of ~ (clearance / v_t) of the step each, is proved by one.

Otherwise the pose at s_m is tested at m itself (below: a pose collides, the motion collides) and the
interval is halved, down to the size where no tool point moves more than :data:`RESOLUTION` within
half an interval, depth first, left half first; an interval not proved clear there, or a step not
proved clear within :data:`MAX_TESTS` interval tests, is reported colliding (a planner's longer
motion: each of the steps that replay it, :func:`pieces`). So:

- a motion reported free keeps every pair at >= m along all of it (within the capsule model,
  which holds the true wire: ``Scene.needle_error_bound``);
- a motion is reported colliding where some pose along it comes within RESOLUTION of m, or where
  it stays so close to m, moving towards or turning about the wire, that MAX_TESTS tests cannot
  prove it (conservative).

The verdict is a function of the motion alone (the intervals are visited in one fixed order), so the MJX
environment (:func:`regrasp_mjx.world.continuous_walk.motion_collides`; on a GPU one Pallas kernel,
:mod:`~regrasp_mjx.world.walk_kernel`), the host checker
(:meth:`regrasp_mjx.envs.host.HostChecker.motion_collides`) and the compiled one
(:func:`regrasp_mjx.envs.lean_collision.motion_collides`) give the same verdicts. A test that proves
more than the root interval's (e.g. the end pose clear by ``v_t``, which implies the midpoint
clear by ``v_t / 2``) may stand in for it; a pair culled by the motion bound alone (the compiled
test's bounding spheres) is proved as both bounds would prove it.

Intervals are named by ``(k, i)``: level k, ``[i / 2^k, (i + 1) / 2^k]``, midpoint
``(2 i + 1) / 2^(k + 1)`` and half-width ``1 / 2^(k + 1)``, exact in floating point.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.core.geometry import dot3

# the finest a motion is cut: no tool point moves more than this within half an interval [m]
RESOLUTION = 1e-6

# added to every raised threshold [m] against rounding in the poses (far below any clearance)
SLACK = 1e-9

# the most interval tests a motion may take to be proved clear; one that needs more (a motion that
# stays within a few microns of the margin, moving towards or turning about it) is reported colliding.
# It bounds the batched test's work: a vmapped while loop runs as long as its slowest lane.
MAX_TESTS = 32

# a planner's motion between two states (OMPL's edges, the straight line) is tested as the
# environment steps that replay it (regrasp_mjx.planning.episodes.path_to_actions): cut into the
# fewest equal pieces within the default action bounds, each piece a step with a step's budget, so
# that a path a planner calls free replays free
STEP_DP = EnvConfig().max_dp_mm * 1e-3
STEP_DROT = math.radians(EnvConfig().max_drot_deg)


def pieces(dp, rotvec, max_dp: float = STEP_DP, max_drot: float = STEP_DROT) -> int:
    """The fewest equal steps of a motion ``(dp, rotvec)`` whose every translation axis is at most
    ``max_dp`` and every rotation-vector axis at most ``max_drot``."""
    size = max(float(np.abs(dp).max()) / max_dp, float(np.abs(rotvec).max()) / max_drot)
    return max(1, math.ceil(size - 1e-9))


def levers(tool_ends: np.ndarray) -> np.ndarray:
    """Each tool capsule's farthest end point from the end-effector's origin [m] (``[T, 2, 3]``
    end points in the end-effector frame -> ``[T]``): the lever of its rotation."""
    return np.linalg.norm(np.asarray(tool_ends, np.float64), axis=-1).max(axis=-1)


def interval_low(tool, origin, other, gap, d, h, dp, rotvec, levers, xp=jnp):
    """The least each pair's signed distance can be anywhere in the interval of half-width ``h``
    about a pose of a motion (module docstring: the larger of the motion and the directional
    bounds), from the pose's capsules: ``tool [T, 2, 3]`` the tool capsules' end points and
    ``origin [3]`` the end-effector's origin there, ``other [O, 2, 3]`` the counted capsules'
    end points, ``gap [T, O, 3]`` each pair's closest-point vector (tool side minus other side,
    :func:`regrasp_mjx.core.geometry.segment_gap`) and ``d [T, O]`` its signed distance (the gap's
    length less both radii); ``dp``, ``rotvec`` the motion (per unit s), ``levers [T]``.

    ``xp``: ``jax.numpy`` (traced, float32) or ``numpy`` (float64, the host checker). Elementwise
    arithmetic only (:func:`~regrasp_mjx.core.geometry.dot3`, no reductions over pairs): on a GPU
    it fuses into the kernel that computes the distances, and no float32 contraction runs in TF32."""
    length = xp.sqrt(dot3(gap, gap))
    moved = d - h * (xp.sqrt(dot3(dp, dp)) + xp.sqrt(dot3(rotvec, rotvec)) * levers)[:, None]
    n = gap / xp.maximum(length, 1e-30)[..., None]  # any unit vector gives a valid bound; 0 none
    along = lambda tool_side: (dot3(tool_side[:, None, 0], n), dot3(tool_side[:, None, 1], n))  # noqa: E731  [T, O]
    t0, t1 = along(tool)
    o0, o1 = dot3(other[None, :, 0], n), dot3(other[None, :, 1], n)
    sep = xp.minimum(t0, t1) - xp.maximum(o0, o1) - (length - d)
    r = tool - origin  # [T, 2, 3] from the end-effector's origin
    v0, v1 = along(dp + xp.cross(rotvec, r))
    turn = xp.sqrt(dot3(rotvec, rotvec))
    axis = rotvec / xp.maximum(turn, 1e-30)
    off = r - dot3(r, axis)[..., None] * axis  # [T, 2, 3] off the rotation axis
    rho = xp.sqrt(xp.maximum(dot3(off[:, 0], off[:, 0]), dot3(off[:, 1], off[:, 1])))  # [T]
    phi = h * turn
    bend = rho * phi * phi * (0.5 + phi / 6.0)
    return xp.maximum(moved, sep - h * xp.maximum(xp.abs(v0), xp.abs(v1)) - bend[:, None])


def motion_collides_host(bound_at, fastest: float, margin: float) -> bool:
    """:func:`~regrasp_mjx.world.continuous_walk.motion_collides` in plain Python (float64), for the host checker:
    ``bound_at(s, h, reach)`` returns every pair's signed distance at pose s and its lower bound over the interval of
    half-width h (:func:`interval_low`), where pairs farther than ``reach`` [m] may be reported at
    ``reach`` for both (a distance query may stop there: ``reach`` exceeds m by the motion bound)."""
    fastest = float(fastest)
    stack, tests = [(0, 0)], 0
    while stack:
        k, i = stack.pop()
        tests += 1
        h = math.ldexp(1.0, -(k + 1))
        d, low = bound_at((2 * i + 1) * h, h, margin + h * fastest + 2 * SLACK)
        if np.all(np.asarray(low) - margin >= SLACK):
            continue
        if np.any(np.asarray(d) < margin) or h * fastest <= RESOLUTION or tests >= MAX_TESTS:
            return True
        stack += [(k + 1, 2 * i + 1), (k + 1, 2 * i)]
    return False
