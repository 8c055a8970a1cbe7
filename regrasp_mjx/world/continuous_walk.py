"""The continuous collision test of a motion (:mod:`regrasp_mjx.world.continuous`: its definition and
host form) in JAX, jit/vmap-able: one lane's walk of dyadic intervals (:func:`motion_collides`), and
its batched forms with their tuning (the lanes the root test leaves pending gathered into rounds, a
subtree of intervals tested in one call). On a GPU the walk may run as one Pallas kernel instead
(:mod:`regrasp_mjx.world.walk_kernel`, which steps it with :func:`_advance`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from regrasp_mjx.world.continuous import MAX_TESTS, RESOLUTION, SLACK

# the share of a vmapped batch whose halves are tested in one round (:func:`_pending_lanes`): the
# lanes the root interval leaves pending are gathered into rounds of this many, so that a batch pays
# for its grazing lanes alone; more pending lanes take more rounds (the same verdicts)
PENDING_SHARE = 1 / 16

# the share of a vmapped batch whose root intervals are tested in one round where the end pose has
# proved the other lanes (:func:`motion_collides`' ``proved``); the halves then gather
# PENDING_SHARE of these lanes
ROOT_SHARE = 1 / 4

# whether a vmapped batch's walk takes WALK_CHUNK steps a loop iteration (:func:`_halves`); None:
# where a loop iteration's test waits for an accelerator (not on a CPU, which loops step by step)
UNROLLED: bool | None = None
WALK_CHUNK = 4  # best of 2, 4 and 8 at 512 and 32,768 lanes on an H100 (issue 44, fifteenth session)
# or, where not None, a subtree of this many levels below the walk's interval a loop iteration,
# tested in one call (:func:`_subtree_step`)
SUBTREE_DEPTH: int | None = 2
# on an accelerator: this many subtree steps for every lane the root left pending, unrolled; then the
# lanes whose walk goes on, gathered TAIL_SHARE of those at a time, a subtree of TAIL_DEPTH levels a
# loop iteration (0: every step in one loop on the pending lanes)
HEAD_STEPS = 2
TAIL_SHARE = 1 / 8
TAIL_DEPTH = 3


class Walk(NamedTuple):
    """A lane's walk of intervals (depth first, left half first): at interval ``(k, i)`` (level k,
    :mod:`regrasp_mjx.world.continuous`), ``tests`` taken so far, whether it has found a
    ``collision``, and whether it is still ``active``."""

    k: jax.Array
    i: jax.Array
    tests: jax.Array
    collision: jax.Array
    active: jax.Array


def motion_collides(
    bound_fn,
    motion,
    fastest: jax.Array,
    margin: float,
    share: float | None = None,
    known: jax.Array | None = None,
    proved: jax.Array | None = None,
) -> jax.Array:
    """Whether the motion collides (:mod:`regrasp_mjx.world.continuous`), in JAX: one lane's test, jit/vmap-able.

    ``bound_fn(motion, s, h) -> (d [P], low [P])``: every counted pair's signed distance at the pose
    s of the motion ``motion`` (a pytree of arrays: the lane's poses and placed capsules) and its
    lower bound over the interval of half-width h about it (:func:`~regrasp_mjx.world.continuous.interval_low`);
    ``fastest``: the largest ``v_t``. The root interval is tested, then its halves where it is not proved, walked
    depth first (:func:`_halves`).

    Vmapped, the halves run on the lanes the root left pending alone, gathered ``share`` of the
    batch at a time (:func:`_pending_lanes`): a vmapped loop runs as many iterations as its slowest
    lane, and every lane would pay for the few that graze the wire (``share`` None:
    :data:`PENDING_SHARE`, read when traced). The verdicts are those of the lane-by-lane test.

    ``known``: True where the motion is already known to collide (its end pose does, say): the
    verdict then, and its halves are not walked (a step into the wire is what takes the most tests:
    its approach proved interval by interval up to where it collides).

    ``proved``: True where a test that proves more than the root's has proved the motion clear (its
    end pose clear of the margin by each capsule's ``v_t``, which bounds the whole step from s = 1:
    the root's own bound from the midpoint then holds too, continuous's docstring): the verdict then, and
    the root is tested on the other lanes alone, gathered :data:`ROOT_SHARE` of the batch at a time
    (on a random-action batch the end pose proves about 80 % of the steps, and the root's
    directional bound is the step's costliest arithmetic)."""
    share = PENDING_SHARE if share is None else share
    fastest = jnp.asarray(fastest, jnp.float32)
    known = jnp.bool_(False) if known is None else known
    halves = _gathered(lambda batched: _halves_lane(bound_fn, margin, batched), share)

    def from_root(batched: bool):
        def lane(motion, fastest, pending):
            h0 = jnp.float32(0.5)
            ok, stop = _verdict(*bound_fn(motion, h0, h0), h0, fastest, margin)
            return pending & ((~ok & stop) | halves(motion, fastest, pending & ~ok & ~stop))

        return lane

    if proved is None:
        return known | from_root(False)(motion, fastest, ~known)
    return known | _gathered(from_root, ROOT_SHARE)(motion, fastest, ~known & ~proved)


def _verdict(d, low, h, fastest, margin):
    """An interval of half-width h whose midpoint has distances d and lower bound low: proved clear,
    or to stop at."""
    proved = jnp.all(low - margin >= SLACK)
    stop = jnp.any(d < margin) | (h * fastest <= RESOLUTION)
    return proved, stop


def _halves_lane(bound_fn, margin: float, batched: bool):
    """``halves(motion, fastest, pending)``: whether the root's halves, tested depth first where
    ``pending``, fail to be proved. ``batched`` (vmapped on an accelerator, where each loop
    iteration waits for the device): :data:`HEAD_STEPS` subtree steps unrolled, then the lanes whose
    walk goes on gathered :data:`TAIL_SHARE` at a time (:func:`_tail_lane`): a walk's length is set
    by its slowest lane, and after the first levels a few lanes are left."""

    def one(motion, fastest, pending):
        bound_at = lambda s, h: bound_fn(motion, s, h)  # noqa: E731
        if not (batched and SUBTREE_DEPTH is not None and HEAD_STEPS):
            return _halves(bound_at, fastest, margin, pending, batched)
        c = _walk_start(pending)
        for _ in range(HEAD_STEPS):
            c = _subtree_step(bound_at, fastest, margin, c, SUBTREE_DEPTH)
        tail = _gathered(lambda batched: _tail_lane(bound_fn, margin), TAIL_SHARE)
        return c.collision | tail(motion, fastest, c.k, c.i, c.tests, c.active)

    return one


def _tail_lane(bound_fn, margin: float):
    """``tail(motion, fastest, k, i, tests, pending)``: the walk from interval ``(k, i)`` with
    ``tests`` taken, where ``pending``, to its end, :data:`TAIL_DEPTH` levels a loop iteration."""

    def one(motion, fastest, k, i, tests, pending):
        def step(c):
            return _subtree_step(lambda s, h: bound_fn(motion, s, h), fastest, margin, c, TAIL_DEPTH)

        return jax.lax.while_loop(lambda c: c.active, step, Walk(k, i, tests, jnp.bool_(False), pending)).collision

    return one


def _walk_start(pending: jax.Array) -> Walk:
    """The walk's state at the root's left half, the root tested."""
    return Walk(jnp.int32(1), jnp.int32(0), jnp.int32(1), jnp.bool_(False), pending)


def _gathered(make_lane, share: float):
    """``make_lane(batched)(*args, pending) -> bool`` (False where not ``pending``) as one lane's
    function whose vmap runs the pending lanes alone, ``share`` of the batch a round
    (:func:`_pending_lanes`); ``batched``: whether the lane function runs vmapped on an accelerator
    (:data:`UNROLLED`)."""
    fn = jax.custom_batching.custom_vmap(make_lane(False))

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        grow = lambda x, batched: x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))  # noqa: E731
        args = tuple(jax.tree.map(grow, a, b) for a, b in zip(args, in_batched))
        lane = make_lane(jax.default_backend() != "cpu" if UNROLLED is None else UNROLLED)
        return _pending_lanes(jax.vmap(lane), args, axis_size, share), True

    return fn


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


def _halves(bound_at, fastest, margin: float, pending: jax.Array, batched: bool = False) -> jax.Array:
    """Whether the root's halves, tested depth first where ``pending``, fail to be proved: the walk
    of :func:`~regrasp_mjx.world.continuous.motion_collides_host` without its stack (:func:`_advance`), an
    interval a step. ``batched`` (on a GPU each loop iteration waits for the device): a subtree of
    :data:`SUBTREE_DEPTH` levels a loop iteration, tested at once and walked in one replay
    (:func:`_subtree_step`); or, where that is None, :data:`WALK_CHUNK` steps, unrolled."""

    def step(c):
        h = jnp.ldexp(jnp.float32(1.0), -(c.k + 1))
        proved, stop = _verdict(*bound_at((2 * c.i + 1).astype(jnp.float32) * h, h), h, fastest, margin)
        return _advance(c, c.active, proved, stop)

    def chunk(c):
        if batched and SUBTREE_DEPTH is not None:
            return _subtree_step(bound_at, fastest, margin, c, SUBTREE_DEPTH)
        for _ in range(WALK_CHUNK if batched else 1):
            c = step(c)
        return c

    return jax.lax.while_loop(lambda c: c.active, chunk, _walk_start(pending)).collision


def _preorder(depth: int) -> list[tuple[int, int, int]]:
    """A subtree of ``depth`` levels below its root, in the walk's order (depth first, left first):
    ``(levels below the root, index within that level, parent's position or -1)``."""
    nodes: list[tuple[int, int, int]] = []

    def visit(a: int, b: int, parent: int) -> None:
        nodes.append((a, b, parent))
        here = len(nodes) - 1
        if a < depth:
            visit(a + 1, 2 * b, here)
            visit(a + 1, 2 * b + 1, here)

    visit(0, 0, -1)
    return nodes


def _subtree_step(bound_at, fastest, margin: float, c: Walk, depth: int) -> Walk:
    """The walk ``c`` (:class:`Walk`) from interval ``(k, i)`` through the subtree
    of ``depth`` levels below it, where active: every interval of the subtree tested at once (one
    call, not a chain of them), then the walk's path through them replayed. The walk visits the
    intervals whose ancestors (within the subtree) all split, in order, counting tests, up to the
    first event: a stop (collision), a split at the test budget (collision), or a split on the
    subtree's last level (the walk goes on at its left half). Without an event the subtree is
    proved and the walk climbs on from ``(k, i)``, as :func:`_advance` after a proof. The same
    intervals, verdicts and test counts as :func:`_advance` an interval at a time: a subtree's
    intervals past its first event are tested and not used."""
    k, i, tests, collision, go = c
    nodes = _preorder(depth)
    a = jnp.asarray([n[0] for n in nodes], jnp.int32)
    kk, ii = k + a, (i << a) + jnp.asarray([n[1] for n in nodes], jnp.int32)
    h = jnp.ldexp(jnp.float32(1.0), -(kk + 1))
    proved, stop = jax.vmap(lambda s, h: _verdict(*bound_at(s, h), h, fastest, margin))(
        (2 * ii + 1).astype(jnp.float32) * h, h
    )
    split = ~proved & ~stop
    reach, count, found = [], tests, jnp.bool_(False)
    k_next, i_next, hit = k, i, jnp.bool_(False)
    for j, (level, _, parent) in enumerate(nodes):
        reach.append(jnp.bool_(True) if parent < 0 else reach[parent] & split[parent])
        count = count + reach[j]
        ends = (~proved[j] & stop[j]) | (split[j] & (count >= MAX_TESTS))  # the walk's collision here
        event = reach[j] & ~found & (ends | (split[j] & (level == depth)))
        hit = hit | (event & ends)
        k_next = jnp.where(event, kk[j] + 1, k_next)  # a split on the last level: its left half
        i_next = jnp.where(event, 2 * ii[j], i_next)
        tests = jnp.where(event, count, tests)
        found = found | event
    up = jax.lax.population_count(i ^ (i + 1)) - 1  # proved: climb as _advance does
    k_next = jnp.where(found, k_next, k - up)
    i_next = jnp.where(found, i_next, (i >> up) + 1)
    tests = jnp.where(found, tests, count)
    finished = hit | (~found & (k_next == 0))
    collision = collision | (go & hit)
    return Walk(
        jnp.where(go, k_next, k),
        jnp.where(go, i_next, i),
        jnp.where(go, tests, c.tests),
        collision,
        go & ~finished,
    )


def _advance(c: Walk, go, proved, stop) -> Walk:
    """One step of the walk ``c`` (:class:`Walk`) where ``go``, at interval
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
    return Walk(jnp.where(go, k_next, k), jnp.where(go, i_next, i), tests, collision, active & ~finished)
