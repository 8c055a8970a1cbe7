"""The continuous test's Pallas kernel against its XLA walk, lane by lane, on a random-action rollout.

Every step of ``bench_env.py``'s rollout (``reset`` of B environments from the paper's distributions,
uniformly random actions, auto-reset) is tested twice with every lane pending (the root and its walk,
neither end pose standing in): by :func:`regrasp_mjx.world.continuous_walk.motion_collides` (the XLA walk)
and by :mod:`regrasp_mjx.world.walk_kernel` (compiled for the GPU; Pallas's interpreter on a CPU).
Prints and writes how many verdicts differ and how many interval tests the kernel's walks took.

    python experiments/walk_kernel_check.py --batch 32768 --steps 20 --out experiments/results/continuous/kernel
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.atomic import machine, write_json
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.world import continuous, continuous_walk, walk_kernel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_env import make_rollout  # noqa: E402  (beside this script)


def check(batch: int, steps: int, seed: int) -> dict:
    """The two tests' verdicts on every step of the rollout, and the kernel's test counts."""
    walk_kernel.KERNEL = False  # the rollout itself steps with the XLA walk; the kernel is called below
    env = RegraspEnv(EnvConfig(check_actions=False))
    frames = env.scene.capsule_frames
    kernel = walk_kernel.make_kernel(frames.tool_ends, frames.tool_radii, env.levers, env.clearance)
    interpret = jax.default_backend() != "gpu"

    def lane(es, a):
        dp, rotvec = a[:3] * env.max_dp, a[3:] * env.max_drot
        placed = env._place_others(es.needle_pos, es.needle_quat)
        fastest = jnp.max(jnp.linalg.norm(dp) + jnp.linalg.norm(rotvec) * env.levers)
        xla = continuous_walk.motion_collides(
            env._bounds_along, (placed, es.ee_pos, es.ee_quat, dp, rotvec), fastest, env.clearance
        )
        ends, radii = placed
        return xla, ends[0], jnp.broadcast_to(radii, ends.shape[1:2]), dp, rotvec, fastest

    def record(states, actions):
        xla, ends, radii, dp, rotvec, fastest = jax.vmap(lane)(states, actions)
        every = jnp.ones(actions.shape[0], jnp.bool_)
        args = (ends, radii, states.ee_pos, states.ee_quat, dp, rotvec, fastest, every)
        collides, tests = walk_kernel.walk_tests(kernel, *args, interpret=interpret)
        return xla, collides, tests

    xla, kernel_says, tests = (
        np.asarray(x) for x in make_rollout(env, batch, steps, record)(jax.random.PRNGKey(seed))[3]
    )
    return {
        "lanes": int(xla.size),
        "verdicts_differ": int((xla != kernel_says).sum()),
        "collisions_xla": int(xla.sum()),
        "collisions_kernel": int(kernel_says.sum()),
        "tests_mean": round(float(tests.mean()), 4),
        "tests_p99": int(np.percentile(tests, 99)),
        "tests_max": int(tests.max()),
        "share_more_than_8_tests": round(float((tests > 8).mean()), 6),
        "lanes_with_32_tests_or_more": int((tests >= continuous.MAX_TESTS).sum()),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=32768)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="folder for walk_kernel_check_B.json")
    args = p.parse_args()
    result = {"machine": f"{machine()}; jax {jax.__version__}", "backend": jax.default_backend()}
    result |= {"batch": args.batch, "steps": args.steps, "seed": args.seed, "block": walk_kernel.BLOCK}
    result |= check(args.batch, args.steps, args.seed)
    for key, value in result.items():
        print(f"{key}: {value}", flush=True)
    if args.out:
        write_json(Path(args.out) / f"walk_kernel_check_{args.batch}.json", result)


if __name__ == "__main__":
    main()
