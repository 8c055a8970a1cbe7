"""The gymnasium vector env's speed against the raw MJX env's (issue 49: at least half of it at a
batch of 4,096 on one H100).

Raw: ``bench_env``'s rollout (``AutoResetWrapper(VmapWrapper(RegraspEnv))``, random actions drawn
on the device, 100 steps in one jitted ``lax.scan``, nothing back to the host but three sums).
gymnasium: ``make_vec("regrasp_mjx/NeedleRegrasp-v0", num_envs=B, vectorization_mode="vector_entry_point")``
stepped from Python with actions made before the clock starts, every step's observation dict,
rewards, flags and infos on the host as numpy arrays (what a learner gets), in each autoreset
mode (same-step draws a new problem for every ended episode; the raw rollout restores its first).
A third row steps the raw env one jitted step per call (what any step-at-a-time API must do), so
the table tells the vector env's own cost from the cost of leaving the scan. Compile time is
excluded; env-steps/s = B * steps / wall.

    python experiments/bench_gym.py --batch-sizes 4096 --out experiments/results/gym
"""

from __future__ import annotations

import argparse
import time

import gymnasium
import jax
import numpy as np
from bench_env import bench_mjx
from brax.envs.wrappers.training import AutoResetWrapper, VmapWrapper

import regrasp_mjx  # noqa: F401  (registers the ids)
from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.envs.env import RegraspEnv


def bench_step_calls(batch: int, steps: int, repeats: int, seed: int) -> dict:
    """The raw env stepped as a step API must step it: one jitted step per call (device actions,
    nothing back to the host, dispatched ahead), under the same wrappers as the scan."""
    wrapped = AutoResetWrapper(VmapWrapper(RegraspEnv(EnvConfig())))
    step = jax.jit(wrapped.step)
    actions = jax.random.uniform(jax.random.PRNGKey(seed), (steps, batch, 6), minval=-1.0, maxval=1.0)
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(seed), batch))
    jax.block_until_ready(step(state, actions[0]))  # compiles
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for a in actions:
            state = step(state, a)
        jax.block_until_ready(state.reward)
        walls.append(time.perf_counter() - t0)
    wall = min(walls)
    return {
        "backend": "raw MJX env, one jitted step per call",
        "batch": batch,
        "steps": steps,
        "repeats": repeats,
        "wall_s": round(wall, 4),
        "env_steps_per_s": batch * steps / wall,
    }


def bench_vector(batch: int, steps: int, repeats: int, mode: str, seed: int) -> dict:
    envs = gymnasium.make_vec(
        "regrasp_mjx/NeedleRegrasp-v0", num_envs=batch, vectorization_mode="vector_entry_point", autoreset_mode=mode
    )
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, batch, 6)).astype(np.float32)
    t0 = time.perf_counter()
    envs.reset(seed=seed)
    envs.step(actions[0])  # compiles
    compile_s = time.perf_counter() - t0
    walls, ended = [], 0
    for r in range(repeats):
        envs.reset(seed=seed + r)
        t0 = time.perf_counter()
        for a in actions:
            _, _, terminated, truncated, _ = envs.step(a)
            ended += int(np.sum(terminated | truncated))
        walls.append(time.perf_counter() - t0)
    wall = min(walls)
    return {
        "backend": f"gymnasium vector ({mode})",
        "batch": batch,
        "steps": steps,
        "repeats": repeats,
        "compile_s": round(compile_s, 2),
        "wall_s": round(wall, 4),
        "env_steps_per_s": batch * steps / wall,
        "episodes_ended": ended,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch-sizes", default="4096")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (the fastest counts)")
    p.add_argument("--modes", default="same_step,next_step,disabled")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    rows = []
    for b in (int(x) for x in args.batch_sizes.split(",")):
        raw = bench_mjx(EnvConfig(), b, args.steps, args.repeats, args.seed)
        raw["backend"] = "raw MJX env (scan)"
        rows.append(raw)
        print(raw, flush=True)
        calls = bench_step_calls(b, args.steps, args.repeats, args.seed)
        calls["of_raw"] = calls["env_steps_per_s"] / raw["env_steps_per_s"]
        rows.append(calls)
        print(calls, flush=True)
        for mode in args.modes.split(","):
            row = bench_vector(b, args.steps, args.repeats, mode, args.seed)
            row["of_raw"] = row["env_steps_per_s"] / raw["env_steps_per_s"]
            rows.append(row)
            print(row, flush=True)
    where = machine()
    lines = [
        f"{where}, jax {jax.__version__}; {args.steps} steps of random actions, fastest of {args.repeats}",
        "",
        "| env | batch | env-steps/s | x raw |",
        "| --- | ---: | ---: | ---: |",
        *(
            f"| {r['backend']} | {r['batch']:,} | {r['env_steps_per_s']:,.0f} | {r.get('of_raw', 1.0):.2f} |"
            for r in rows
        ),
    ]
    write_results(args.out, "bench_gym", lines, {"machine": where, "args": vars(args), "rows": rows})
    print("\n".join(lines))


if __name__ == "__main__":
    main()
