"""The continuous test as one Pallas kernel (issue 44): the same verdicts as the XLA walk, lane by lane.

On a GPU the environment tests its steps with :mod:`regrasp_mjx.world.walk_kernel`; here, on the CPU,
the same kernel runs in Pallas's interpreter (the same program, its arithmetic done by XLA's CPU
backend) and is compared with the XLA walk that CPUs step with. The GPU's own verdicts were checked on
655,360 steps (experiments/RESULTS.md, "Verdicts"; experiments/results/continuous/kernel/)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.world import continuous_walk, walk_kernel
from tests.test_continuous import ACTION, NEEDLE, START, _state, random_steps

BATCH, STEPS = 256, 8


@pytest.fixture(scope="module")
def env():
    return RegraspEnv(EnvConfig())


def _kernel(env, margin=None):
    f = env.scene.capsule_frames
    return walk_kernel.make_kernel(f.tool_ends, f.tool_radii, env.levers, env.clearance if margin is None else margin)


def _random_steps(env, record):
    return random_steps(env, BATCH, STEPS, record, key=4)


def test_the_kernel_gives_the_xla_walks_verdicts_lane_by_lane(env, monkeypatch):
    # every lane pending (its root and walk tested, no end pose standing in): 2,048 steps, both
    # verdicts, walks of one test to past 8; a kernel at a margin 10 um larger differs on a few lanes
    # (9 when written: the comparison can fail)
    monkeypatch.setattr(walk_kernel, "KERNEL", False)
    kernels = {"env": _kernel(env), "wider": _kernel(env, env.clearance + 1e-5)}

    def record(state, actions):
        states = state.pipeline_state

        def lane(es, a):
            dp, rotvec = a[:3] * env.max_dp, a[3:] * env.max_drot
            placed = env._place_others(es.needle_pos, es.needle_quat)
            fastest = jnp.max(jnp.linalg.norm(dp) + jnp.linalg.norm(rotvec) * env.levers)
            motion = (placed, es.ee_pos, es.ee_quat, dp, rotvec)
            xla = continuous_walk.motion_collides(env._bounds_along, motion, fastest, env.clearance)
            return xla, placed[0][0], jnp.broadcast_to(placed[1], placed[0].shape[1:2]), dp, rotvec, fastest

        xla, ends, radii, dp, rotvec, fastest = jax.vmap(lane)(states, actions)
        args = (ends, radii, states.ee_pos, states.ee_quat, dp, rotvec, fastest, jnp.ones(BATCH, jnp.bool_))
        return xla, {k: walk_kernel.walk_tests(kernel, *args, interpret=True) for k, kernel in kernels.items()}

    xla, by_kernel = _random_steps(env, record)
    (collides, tests), (wider, _) = by_kernel["env"], by_kernel["wider"]
    xla, collides, tests, wider = (np.asarray(x) for x in (xla, collides, tests, wider))
    np.testing.assert_array_equal(collides, xla)
    assert 0.05 < xla.mean() < 0.5
    assert tests.min() == 1 and tests.max() > 8 and (tests > 1).mean() > 0.01
    assert (wider != xla).sum() > 0 and (wider >= xla).all()  # a wider margin only adds collisions


def test_the_environment_steps_alike_with_the_kernel(env, monkeypatch):
    # RegraspEnv.step with the kernel (on the lanes neither end pose decides) against the XLA walk:
    # the same collisions, rewards and next poses on every step
    def stepped(kernel: bool):
        monkeypatch.setattr(walk_kernel, "KERNEL", kernel)
        record = lambda state, action: _outcome(jax.vmap(env.step)(state, action))  # noqa: E731
        return _random_steps(env, record)

    with_kernel, without = stepped(True), stepped(False)
    for a, b in zip(with_kernel, without):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    collision = np.asarray(with_kernel[0])
    assert 0 < collision.sum() < collision.size


def _outcome(state):
    es = state.pipeline_state
    return state.metrics["collision"], state.reward, es.ee_pos, es.ee_quat


@pytest.mark.parametrize(
    "action,collides",
    [(ACTION, True), (np.array([1.0, 0, 0, 0, 0, 0]), False)],
)
def test_steps_beside_the_wire_by_hand(action, collides, monkeypatch):
    # paper300 row 161's start, 8 um from the wire: its graze between the poses the environment once
    # checked (tests/test_continuous.py), and a straight step along x clear of it (along -x or y it
    # collides); the
    # kernel's step and the XLA walk's give the verdicts written here
    verdicts = []
    for kernel in (True, False):
        monkeypatch.setattr(walk_kernel, "KERNEL", kernel)
        fresh = RegraspEnv(EnvConfig())
        moved = jax.jit(fresh.step)(_state(fresh, NEEDLE, START), jnp.asarray(action, jnp.float32))
        verdicts.append(float(moved.metrics["collision"]))
    assert verdicts == [float(collides)] * 2


def test_seeds_by_environments_step_alike_with_the_kernel(env, monkeypatch):
    # a training program vmaps its seeds over its environments: the kernel's rule then runs under a
    # second vmap (on a GPU, one kernel call with the seeds as a second grid axis)
    def collisions(kernel: bool):
        monkeypatch.setattr(walk_kernel, "KERNEL", kernel)

        @jax.jit
        def run(key):
            state = jax.vmap(jax.vmap(env.reset))(jax.random.split(key, 2 * 64).reshape(2, 64, 2))
            out = []
            for t in range(4):
                action = jax.random.uniform(jax.random.fold_in(key, t), (2, 64, 6), minval=-1.0, maxval=1.0)
                state = jax.vmap(jax.vmap(env.step))(state, action)
                out.append(state.metrics["collision"])
            return jnp.stack(out)

        return np.asarray(run(jax.random.PRNGKey(0)))

    with_kernel, without = collisions(True), collisions(False)
    np.testing.assert_array_equal(with_kernel, without)
    assert 0 < without.sum() < without.size
