"""The continuous collision test of a motion: free only where every pose along it is proved clear.

A motion moves the regrasping end-effector from ``(p0, q0)`` along ``p(s) = p0 + s dp``,
``q(s) = exp(s w) q0``, s in [0, 1] (an environment step; and OMPL's interpolation, position linear
and orientation slerped, is the same curve with ``w`` the shortest rotation vector of ``q1 q0^-1``).
A point of tool capsule t at ``x`` in the end-effector frame moves at most
``v_t = |dp| + |w| L_t`` per unit s, ``L_t`` the farthest end point of t from the end-effector's
origin (:func:`levers`), so every counted pair's signed distance d(s) is v_t-Lipschitz in s.

Conservative advancement by bisection (the standard continuous test, as FCL's): an interval of
half-width h about s_m is clear when every pair keeps ``d(s_m) >= m + h v_t`` (m the clearance
margin; one pose test with each tool capsule's threshold raised). Otherwise the pose at s_m is
tested at m itself (below: a pose collides, the motion collides) and the interval is halved, down
to the size where no tool point moves more than :data:`RESOLUTION` within half an interval, depth
first, left half first; an interval not proved clear there, or a step not proved clear within
:data:`MAX_TESTS` interval tests, is reported colliding (a planner's longer motion: each of the
steps that replay it, :func:`pieces`). So:

- a motion reported free keeps every pair at >= m along all of it (within the capsule model,
  which holds the true wire: ``Scene.needle_error_bound``);
- a motion is reported colliding where some pose along it comes within RESOLUTION of m, or where
  it stays so close to m for so long that MAX_TESTS tests cannot prove it (conservative: at full
  speed, a jaw sliding along the wire closer than about 0.05 mm for a whole step).

The verdict is a function of the motion alone (the intervals are visited in one fixed order), so the MJX
environment (:func:`motion_collides`, here), the host checker
(:meth:`regrasp_mjx.host.HostChecker.motion_collides`) and the compiled one
(:func:`regrasp_mjx.lean_collision.motion_collides`) give the same verdicts. A test that proves
more than the root interval's (e.g. the end pose clear by ``v_t``, which implies the midpoint
clear by ``v_t / 2``) may stand in for it.

Intervals are named by ``(k, i)``: level k, ``[i / 2^k, (i + 1) / 2^k]``, midpoint
``(2 i + 1) / 2^(k + 1)`` and half-width ``1 / 2^(k + 1)``, exact in floating point.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.config import EnvConfig

# the finest a motion is cut: no tool point moves more than this within half an interval [m]
RESOLUTION = 1e-6

# added to every raised threshold [m] against rounding in the poses (far below any clearance)
SLACK = 1e-9

# the most interval tests a motion may take to be proved clear; one that needs more (a motion that
# stays within about v / (2 MAX_TESTS) of the margin for much of its length) is reported colliding.
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


def max_levels(max_speed: float) -> int:
    """The most halvings a motion whose tool points move at most ``max_speed`` [m per unit s] can
    take before no point moves more than :data:`RESOLUTION` within half an interval (a static bound
    for the JAX stack)."""
    return max(0, math.ceil(math.log2(max(max_speed, RESOLUTION) / RESOLUTION)))


def motion_collides(dist_at, speed: jax.Array, margin: float, levels: int, few: int = 0) -> jax.Array:
    """Whether the motion collides (module docstring), in JAX: one lane's test, jit/vmap-able.

    ``dist_at(s, pairs=None) -> [P]``: every counted pair's signed distance at the pose s of the
    motion (of the pair indices ``pairs`` alone where given);
    ``speed [P]``: each pair's ``v_t`` (its tool capsule's); ``levels``: a static bound on the
    halvings (:func:`max_levels` of the largest speed a motion can have). The root interval is
    tested for every lane; its halves only where it is not proved, in a ``while_loop`` (a vmapped
    batch runs as many iterations as its slowest lane needs).

    A pair proved clear over an interval is proved over each of its halves (its distance at a
    half's midpoint is at least ``m + h v`` less ``h v / 2``), so the halves need only the pairs the
    root did not prove. With ``few > 0``, a lane whose root left at most ``few`` pairs unproved
    tests only those: the same verdict for a fraction of the work; the other lanes test every pair."""
    speed = jnp.asarray(speed, jnp.float32)
    fastest = jnp.max(speed)

    def verdict(d, h, v):
        proved = jnp.all(d - margin >= h * v + SLACK)
        stop = jnp.any(d < margin) | (h * fastest <= RESOLUTION)
        return proved, stop

    h0 = jnp.float32(0.5)
    root = dist_at(h0)
    proved, stop = verdict(root, h0, speed)
    pending = ~proved & ~stop
    collision = ~proved & stop
    if few > 0:
        slack = root - margin - h0 * speed
        idx = jnp.argsort(slack)[:few]  # the pairs the root left unproved first
        small = jnp.sum(slack < SLACK) <= few
        collision = collision | _halves(lambda s: dist_at(s, idx), speed[idx], verdict, levels, pending & small)
        return collision | _halves(dist_at, speed, verdict, levels, pending & ~small)
    return collision | _halves(dist_at, speed, verdict, levels, pending)


def _halves(dist_at, speed, verdict, levels: int, pending: jax.Array) -> jax.Array:
    """Whether the root's halves, tested depth first where ``pending``, fail to be proved."""
    size = levels + 2  # depth-first: each halving adds at most one pending interval
    stack = jnp.zeros((size, 2), jnp.int32).at[0].set(jnp.array([1, 1])).at[1].set(jnp.array([1, 0]))
    rows = jnp.arange(size)[:, None]

    def body(c):
        stack, n, tests, collision, _ = c
        top = n - 1
        k, i = stack[top, 0], stack[top, 1]
        h = jnp.ldexp(jnp.float32(1.0), -(k + 1))
        proved, stop = verdict(dist_at((2 * i + 1).astype(jnp.float32) * h), h, speed)
        tests = tests + 1
        split = ~proved & ~stop
        # proved: pop it; split: its right half in its place and its left half on top
        halves = jnp.where(rows == top, jnp.stack([k + 1, 2 * i + 1]), jnp.stack([k + 1, 2 * i]))
        stack = jnp.where(split & ((rows == top) | (rows == n)), halves, stack)
        n = jnp.where(proved, n - 1, jnp.where(split, n + 1, n))
        collision = collision | (~proved & stop) | (split & (tests >= MAX_TESTS))
        return stack, n, tests, collision, ~collision & (n > 0)

    init = (stack, jnp.int32(2), jnp.int32(1), jnp.bool_(False), pending)
    return jax.lax.while_loop(lambda c: c[4], body, init)[3]


def motion_collides_host(dist_at, speed: np.ndarray, margin: float) -> bool:
    """:func:`motion_collides` in plain Python (float64), for the host checker: ``dist_at(s, reach)``
    returns every pair's signed distance at pose s, where pairs farther than ``reach`` [m] may be
    reported at ``reach`` (a distance query may stop there)."""
    speed = np.asarray(speed, np.float64)
    fastest = float(speed.max()) if speed.size else 0.0
    stack, tests = [(0, 0)], 0
    while stack:
        k, i = stack.pop()
        tests += 1
        h = math.ldexp(1.0, -(k + 1))
        d = np.asarray(dist_at((2 * i + 1) * h, margin + h * fastest + 2 * SLACK))
        if np.all(d - margin >= h * speed + SLACK):
            continue
        if np.any(d < margin) or h * fastest <= RESOLUTION or tests >= MAX_TESTS:
            return True
        stack += [(k + 1, 2 * i + 1), (k + 1, 2 * i)]
    return False
