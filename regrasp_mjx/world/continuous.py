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
(:meth:`regrasp_mjx.envs.host.HostChecker.motion_collides`) and the compiled one
(:func:`regrasp_mjx.envs.lean_collision.motion_collides`) give the same verdicts. A test that proves
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

from regrasp_mjx.core.config import EnvConfig

# the finest a motion is cut: no tool point moves more than this within half an interval [m]
RESOLUTION = 1e-6

# added to every raised threshold [m] against rounding in the poses (far below any clearance)
SLACK = 1e-9

# the most interval tests a motion may take to be proved clear; one that needs more (a motion that
# stays within about v / (2 MAX_TESTS) of the margin for much of its length) is reported colliding.
# It bounds the batched test's work: a vmapped while loop runs as long as its slowest lane.
MAX_TESTS = 32

# the share of a vmapped batch whose halves are tested in one round (:func:`_pending_lanes`): the
# lanes the root interval leaves pending are gathered into rounds of this many, so that a batch pays
# for its grazing lanes alone; more pending lanes take more rounds (the same verdicts)
PENDING_SHARE = 1 / 16

# whether a vmapped batch's walk takes WALK_CHUNK steps a loop iteration (:func:`_halves`); None:
# where a loop iteration's test waits for an accelerator (not on a CPU, which loops step by step)
UNROLLED: bool | None = None
WALK_CHUNK = 8


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


def motion_collides(dist_fn, motion, speed: jax.Array, margin: float, share: float | None = None) -> jax.Array:
    """Whether the motion collides (module docstring), in JAX: one lane's test, jit/vmap-able.

    ``dist_fn(motion, s) -> [P]``: every counted pair's signed distance at the pose s of the motion
    ``motion`` (a pytree of arrays: the lane's poses and placed capsules); ``speed [P]``: each pair's
    ``v_t`` (its tool capsule's). The root interval is tested for every lane; its halves only where
    it is not proved, walked depth first (:func:`_halves`).

    Vmapped, the halves run on the lanes the root left pending alone, gathered ``share`` of the
    batch at a time (:func:`_pending_lanes`): a vmapped loop runs as many iterations as its slowest
    lane, and every lane would pay for the few that graze the wire (``share`` None:
    :data:`PENDING_SHARE`, read when traced). The verdicts are those of the lane-by-lane test."""
    share = PENDING_SHARE if share is None else share
    speed = jnp.asarray(speed, jnp.float32)
    fastest = jnp.max(speed)
    h0 = jnp.float32(0.5)
    proved, stop = _verdict(dist_fn(motion, h0), h0, speed, fastest, margin)
    halves = _halves_fn(dist_fn, margin, share)
    return (~proved & stop) | halves(motion, speed, fastest, ~proved & ~stop)


def _verdict(d, h, v, fastest, margin):
    """An interval of half-width h whose midpoint has distances d: proved clear, or to stop at."""
    proved = jnp.all(d - margin >= h * v + SLACK)
    stop = jnp.any(d < margin) | (h * fastest <= RESOLUTION)
    return proved, stop


def _halves_fn(dist_fn, margin: float, share: float):
    """``halves(motion, speed, fastest, pending)``: whether the root's halves, tested depth first
    where ``pending``, fail to be proved; vmapped, on the pending lanes alone."""

    def lane(batched: bool):
        def one(motion, speed, fastest, pending):
            return _halves(lambda s: dist_fn(motion, s), speed, fastest, margin, pending, batched)

        return one

    halves = jax.custom_batching.custom_vmap(lane(batched=False))

    @halves.def_vmap
    def _rule(axis_size, in_batched, *args):
        grow = lambda x, batched: x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))  # noqa: E731
        args = tuple(jax.tree.map(grow, a, b) for a, b in zip(args, in_batched))
        unrolled = lane(batched=jax.default_backend() != "cpu" if UNROLLED is None else UNROLLED)
        return _pending_lanes(jax.vmap(unrolled), args, axis_size, share), True

    return halves


def _pending_lanes(batched, args, size: int, share: float) -> jax.Array:
    """``batched(*args)`` (its last argument the lanes' ``pending``, its result False where not
    pending) computed on the pending lanes alone, ``ceil(share size)`` lanes a round, as many rounds
    as there are pending lanes to fill (none where none is)."""
    pending = args[-1]
    lanes = max(1, min(size, math.ceil(share * size)))
    if lanes == size:
        return batched(*args)
    rounds = -(-size // lanes)
    count = jnp.sum(pending)
    # the pending lanes' indices first, then `size` (out of range: gathers clip, scatters drop)
    order = jnp.nonzero(pending, size=rounds * lanes, fill_value=size)[0].reshape(rounds, lanes)

    def body(carry):
        k, out = carry
        rows = order[k]
        sub = jax.tree.map(lambda x: jnp.take(x, rows, axis=0, mode="clip"), args)
        result = batched(*sub[:-1], sub[-1] & (rows < size))
        return k + 1, out.at[rows].set(result, mode="drop")

    init = (jnp.int32(0), jnp.zeros(size, jnp.bool_))
    return jax.lax.while_loop(lambda c: c[0] * lanes < count, body, init)[1]


def _halves(dist_at, speed, fastest, margin: float, pending: jax.Array, batched: bool = False) -> jax.Array:
    """Whether the root's halves, tested depth first where ``pending``, fail to be proved: the walk
    of :func:`motion_collides_host` without its stack (:func:`_advance`), an interval a step.
    ``batched``: :data:`WALK_CHUNK` steps a loop iteration, unrolled (on a GPU each iteration's test
    waits for the device; a lane done within a chunk idles to its end)."""

    def step(c):
        h = jnp.ldexp(jnp.float32(1.0), -(c[0] + 1))
        proved, stop = _verdict(dist_at((2 * c[1] + 1).astype(jnp.float32) * h), h, speed, fastest, margin)
        return _advance(c, c[4], proved, stop)

    def chunk(c):
        for _ in range(WALK_CHUNK if batched else 1):
            c = step(c)
        return c

    init = (jnp.int32(1), jnp.int32(0), jnp.int32(1), jnp.bool_(False), pending)
    return jax.lax.while_loop(lambda c: c[4], chunk, init)[3]


def _advance(c, go, proved, stop):
    """One step of the walk ``c = (k, i, tests, collision, active)`` where ``go``, at interval
    ``(k, i)`` whose test gave ``proved`` and ``stop``. In a depth-first, left-first walk of dyadic
    intervals the one after a proved ``(k, i)`` follows from it alone: climb the levels of i's
    trailing ones (right halves, done) and step right; a split goes to its left half."""
    k, i, tests, collision, active = c
    tests = tests + go
    split = go & ~proved & ~stop
    collision = collision | (go & ~proved & stop) | (split & (tests >= MAX_TESTS))
    up = jax.lax.population_count(i ^ (i + 1)) - 1  # i's trailing ones
    k_next = jnp.where(split, k + 1, k - up)
    i_next = jnp.where(split, 2 * i, (i >> up) + 1)
    finished = collision | (go & proved & (k_next == 0))  # k_next 0: the root's right half was done
    return jnp.where(go, k_next, k), jnp.where(go, i_next, i), tests, collision, active & ~finished


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
