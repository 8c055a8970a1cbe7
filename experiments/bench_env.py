"""Environment throughput: MJX (batched, one jitted scan) against CPU MuJoCo on one thread.

A rollout is ``reset`` of B environments from the paper's distributions (collision-free starts
redrawn) and ``T`` steps of uniformly random actions in one ``lax.scan``, under brax's
``AutoResetWrapper(VmapWrapper(env))``; env-steps/s = B * T * rollouts / wall time, compile time
excluded and printed apart. The CPU row steps the same MDP (:class:`regrasp_mjx.envs.host.HostEnv`, same
continuous collision test, observation and reward) one problem at a time on one thread, restarting a problem when it
ends, as the auto-reset does.

    python experiments/bench_env.py --batch-sizes 1024,8192,32768 --out experiments/results
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.wrappers.training import AutoResetWrapper, VmapWrapper

from regrasp_mjx.core.atomic import machine, write_json, write_text
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.host import HostEnv
from regrasp_mjx.world import continuous_walk, walk_kernel
from regrasp_mjx.world.testsets import make_testset

POSE_FIELDS = ("needle_pos", "needle_quat", "start_pos", "start_quat")
# the fewest poses a step's continuous test looks at (its end pose and its midpoint): the raw CPU
# row's C calls per step, so that its rate bounds any one-thread implementation from above
RAW_CALLS = 2


def make_rollout(env: RegraspEnv, batch: int, steps: int):
    """The rollout (module docstring) as one jitted function of a key: the sums of rewards, episode
    ends and successes."""
    wrapped = AutoResetWrapper(VmapWrapper(env))

    @jax.jit
    def rollout(key):
        k_reset, k_act = jax.random.split(key)
        state = wrapped.reset(jax.random.split(k_reset, batch))

        def body(state, k):
            action = jax.random.uniform(k, (batch, env.action_size), minval=-1.0, maxval=1.0)
            state = wrapped.step(state, action)
            return state, (jnp.sum(state.reward), jnp.sum(state.done), jnp.sum(state.metrics["success"]))

        _, (reward, done, success) = jax.lax.scan(body, state, jax.random.split(k_act, steps))
        return jnp.sum(reward), jnp.sum(done), jnp.sum(success)

    return rollout


KERNEL_SIZES = (walk_kernel.BLOCK, walk_kernel.NUM_WARPS)  # the module's: ``kernel`` alone asks for them


def set_walk(walk: str | None) -> str:
    """The continuous test's walk on an accelerator (read when the step is traced): ``kernel[:BLOCK[:WARPS]]``
    (one Pallas kernel, :mod:`regrasp_mjx.world.walk_kernel`, BLOCK lanes a program on WARPS warps), ``chunk``
    (WALK_CHUNK intervals one after another a loop iteration) or ``DEPTH:HEAD:TAIL_DEPTH``
    (SUBTREE_DEPTH, HEAD_STEPS, TAIL_DEPTH), the XLA walks; None: the module's. Returns it as such a string."""
    walk_kernel.KERNEL = None if walk is None else walk.startswith("kernel")
    if walk is not None and walk.startswith("kernel"):
        sizes = [int(x) for x in walk.split(":")[1:]]
        walk_kernel.BLOCK, walk_kernel.NUM_WARPS = sizes + list(KERNEL_SIZES)[len(sizes) :]
    if walk_kernel.use_kernel():
        return f"kernel:{walk_kernel.BLOCK}:{walk_kernel.NUM_WARPS}"
    if walk == "chunk":
        continuous_walk.SUBTREE_DEPTH = None
    elif walk is not None:
        continuous_walk.SUBTREE_DEPTH, continuous_walk.HEAD_STEPS, continuous_walk.TAIL_DEPTH = (
            int(x) for x in walk.split(":")
        )
    if continuous_walk.SUBTREE_DEPTH is None:
        return "chunk"
    return f"{continuous_walk.SUBTREE_DEPTH}:{continuous_walk.HEAD_STEPS}:{continuous_walk.TAIL_DEPTH}"


def bench_mjx(
    config: EnvConfig,
    batch: int,
    steps: int,
    rollouts: int,
    seed: int,
    share: float | None = None,
    root_share: float | None = None,
    walk: str | None = None,
) -> dict:
    share = continuous_walk.PENDING_SHARE if share is None else share
    root_share = continuous_walk.ROOT_SHARE if root_share is None else root_share
    continuous_walk.PENDING_SHARE, continuous_walk.ROOT_SHARE = share, root_share  # read when the step is traced
    walk = set_walk(walk)
    env = RegraspEnv(config)
    rollout = make_rollout(env, batch, steps)
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(jax.random.PRNGKey(seed)))
    compile_s = time.perf_counter() - t0
    keys = jax.random.split(jax.random.PRNGKey(seed + 1), rollouts)
    t0 = time.perf_counter()
    for k in keys:
        out = rollout(k)
    reward, done, success = jax.block_until_ready(out)
    wall = time.perf_counter() - t0
    return {
        "backend": jax.default_backend(),
        "batch": batch,
        "steps": steps,
        "rollouts": rollouts,
        "check_actions": config.check_actions,
        "pending_share": share,
        "root_share": root_share,
        "walk": walk,
        "compile_s": round(compile_s, 2),
        "wall_s": round(wall, 4),
        "env_steps_per_s": batch * steps * rollouts / wall,
        "episodes_ended_last_rollout": int(done),
    }


def bench_cpu(config: EnvConfig, total_steps: int, steps: int, seed: int, raw: bool = False) -> dict:
    """The same MDP on CPU MuJoCo, one thread (:class:`HostEnv`), restarting a problem when it ends;
    ``raw``: the C work of a step alone, :data:`RAW_CALLS` x (mj_kinematics + mj_collision) with no
    Python MDP, an upper bound for any one-thread CPU implementation (so the ratio against it is the
    conservative one)."""
    env = HostEnv(config)
    problems = make_testset(64, seed, config)
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(total_steps, 6))
    model, data, scene = env.checker.model, env.checker.data, env.checker.scene
    qpos = [scene.qpos(*(np.asarray(getattr(problems, f)[i]) for f in POSE_FIELDS)) for i in range(len(problems))]
    t0 = time.perf_counter()
    for i in range(total_steps * RAW_CALLS if raw else 0):  # the C calls alone, on states made before
        data.qpos[:] = qpos[i % len(qpos)]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
    n = total_steps if raw else 0
    while n < total_steps:
        problem = problems.row((n // steps) % len(problems))
        env.reset_from(problem)
        for _ in range(steps):
            _, _, done, _ = env.step(actions[n % total_steps])
            n += 1
            if done:
                env.reset_from(problem)
    wall = time.perf_counter() - t0
    return {
        "backend": "cpu-mujoco-1-thread" + ("-raw" if raw else ""),
        "steps": n,
        "wall_s": round(wall, 3),
        "env_steps_per_s": n / wall,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch-sizes", default="1024,8192,32768")
    p.add_argument("--steps", type=int, default=100, help="steps per rollout (the paper's horizon)")
    p.add_argument("--rollouts", type=int, default=5)
    p.add_argument("--cpu-steps", type=int, default=20000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--also-checked",
        action="store_true",
        help="also time the largest batch with check_actions=True (the NaN check)",
    )
    p.add_argument(
        "--pending-shares",
        default=None,
        help="comma-separated shares of a batch whose pending lanes the continuous test gathers a round "
        f"(regrasp_mjx.world.continuous_walk.PENDING_SHARE, default {continuous_walk.PENDING_SHARE:g}; 1 = none gathered)",
    )
    p.add_argument(
        "--root-shares",
        default=None,
        help="comma-separated shares of a batch whose root intervals are tested a round where the end pose has "
        f"not proved the step (regrasp_mjx.world.continuous_walk.ROOT_SHARE, default {continuous_walk.ROOT_SHARE:g})",
    )
    p.add_argument(
        "--walks",
        default=None,
        help="comma-separated walks of the continuous test on an accelerator: kernel[:BLOCK[:WARPS]] (one Pallas kernel, "
        "BLOCK lanes a program on WARPS warps), chunk (WALK_CHUNK intervals a loop "
        "iteration) or DEPTH:HEAD:TAIL_DEPTH (regrasp_mjx.world.continuous_walk.SUBTREE_DEPTH, HEAD_STEPS, TAIL_DEPTH); "
        "default: the module's",
    )
    p.add_argument("--out", default=None, help="folder for bench_env.json and bench_env.md")
    args = p.parse_args()

    config = EnvConfig(check_actions=False)
    where = f"{machine()}; jax {jax.__version__}"
    print(f"machine: {where}", flush=True)
    cpu = bench_cpu(config, args.cpu_steps, args.steps, args.seed)
    print(f"CPU MuJoCo, 1 thread, whole MDP step (HostEnv): {cpu['env_steps_per_s']:,.0f} env-steps/s", flush=True)
    raw = bench_cpu(config, args.cpu_steps, args.steps, args.seed, raw=True)
    print(f"CPU MuJoCo, 1 thread, kinematics+collision only: {raw['env_steps_per_s']:,.0f} env-steps/s", flush=True)
    rows = []
    sizes = [int(b) for b in args.batch_sizes.split(",")]
    shares = [float(x) for x in args.pending_shares.split(",")] if args.pending_shares else [None]
    roots = [float(x) for x in args.root_shares.split(",")] if args.root_shares else [None]
    walks = args.walks.split(",") if args.walks else [None]
    runs = [(b, config, sh, root, w) for b in sizes for sh in shares for root in roots for w in walks]
    if args.also_checked:
        runs.append((sizes[-1], EnvConfig(check_actions=True), shares[0], roots[0], walks[0]))
    for batch, cfg, share, root, walk in runs:
        r = bench_mjx(cfg, batch, args.steps, args.rollouts, args.seed, share, root, walk)
        r["ratio_vs_cpu"] = r["env_steps_per_s"] / cpu["env_steps_per_s"]
        r["ratio_vs_cpu_raw"] = r["env_steps_per_s"] / raw["env_steps_per_s"]
        rows.append(r)
        print(
            f"MJX {r['backend']} batch {batch:>6} share {r['pending_share']:<7g} root {r['root_share']:<6g} walk {r['walk']:6} check_actions={cfg.check_actions!s:5}: "
            f"{r['env_steps_per_s']:>14,.0f} env-steps/s  x{r['ratio_vs_cpu']:,.0f} vs CPU MDP step, "
            f"x{r['ratio_vs_cpu_raw']:,.0f} vs CPU C calls only "
            f"(compile {r['compile_s']} s)",
            flush=True,
        )
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(
            out / "bench_env.json",
            {"machine": where, "cpu": cpu, "cpu_raw": raw, "mjx": rows},
        )
        lines = [
            f"Machine: {where}",
            "",
            "| backend | batch | pending share | root share | walk | NaN check | env-steps/s | x CPU MDP step | x CPU C calls only | compile s |",
            "| --- | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: |",
            f"| CPU MuJoCo, 1 thread, MDP step (HostEnv) | 1 | - | - | - | no | {cpu['env_steps_per_s']:,.0f} | 1 | - | - |",
            f"| CPU MuJoCo, 1 thread, kinematics+collision only | 1 | - | - | - | no | {raw['env_steps_per_s']:,.0f} | - | 1 | - |",
        ]
        lines += [
            f"| MJX {r['backend']} | {r['batch']} | {r['pending_share']:g} | {r['root_share']:g} | {r['walk']} | {'yes' if r['check_actions'] else 'no'} | "
            f"{r['env_steps_per_s']:,.0f} | {r['ratio_vs_cpu']:,.0f} | {r['ratio_vs_cpu_raw']:,.0f} | {r['compile_s']} |"
            for r in rows
        ]
        write_text(out / "bench_env.md", "\n".join(lines) + "\n")
        print(f"wrote {out / 'bench_env.md'}")


if __name__ == "__main__":
    main()
