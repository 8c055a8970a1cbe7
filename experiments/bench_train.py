"""Throughput of the training program: env-steps/s and updates/s of one jitted iteration at several
env counts and seed counts, with peak device memory.

An iteration is what ``python -m regrasp_mjx.train`` runs between host steps: ``num_envs`` x 100
exploration steps per seed, the buffer inserts, ``updates_per_iteration`` DDPG+BC updates per seed.
Demonstrations are stand-ins (random transitions; throughput does not depend on their values).
Compile time excluded; ``--iterations`` timed after one warm-up.

    python experiments/bench_train.py --envs 128,512,2048,8192 --seeds 1,3,8 --out experiments/results
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.agents.ddpg_bc.config import make_config
from regrasp_mjx.agents.ddpg_bc.train import Learner


def bench(num_envs: int, seeds: int, updates: int, iterations: int) -> dict:
    cfg = make_config("fast", num_envs=num_envs, num_seeds=seeds, updates_per_iteration=updates)
    learner = Learner(cfg)
    rng = np.random.default_rng(0)
    n = 20_000
    demos = {
        "obs": jnp.asarray(rng.normal(size=(n, 21)), jnp.float32),
        "action": jnp.asarray(rng.uniform(-1, 1, (n, 6)), jnp.float32),
        "reward": jnp.full((n,), -0.02, jnp.float32),
        "next_obs": jnp.asarray(rng.normal(size=(n, 21)), jnp.float32),
        "terminal": jnp.zeros((n,), jnp.float32),
    }
    ts = learner.init(demos)
    t0 = time.perf_counter()
    ts, m, out, _ = learner.iteration(ts, jnp.float32(0.3))
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(iterations):
        ts, m, out, _ = learner.iteration(ts, jnp.float32(0.3))
    jax.block_until_ready(out)
    dt = (time.perf_counter() - t0) / iterations
    stats = jax.devices()[0].memory_stats() or {}
    return {
        "num_envs": num_envs,
        "seeds": seeds,
        "updates_per_iteration": updates,
        "iteration_ms": 1e3 * dt,
        "env_steps_per_s": seeds * num_envs * cfg.env.horizon / dt,
        "updates_per_s": seeds * updates / dt,
        "peak_memory_gb": stats.get("peak_bytes_in_use", float("nan")) / 1e9,
        "compile_s": compile_s,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", default="128,512,2048,8192")
    p.add_argument("--seeds", default="1,3,8")
    p.add_argument("--updates", type=int, default=200)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    rows = []
    for seeds in (int(s) for s in args.seeds.split(",")):
        for envs in (int(e) for e in args.envs.split(",")):
            if seeds > 1 and envs != 512:
                continue  # seeds are compared at the fast preset's 512 envs
            r = bench(envs, seeds, args.updates, args.iterations)
            rows.append(r)
            print(json.dumps(r), flush=True)
    device = jax.devices()[0].device_kind
    lines = [
        f"Device: {device} ({jax.device_count()} visible), jax {jax.__version__}; updates per iteration "
        f"{args.updates}, batch 256, horizon 100.",
        "",
        "| seeds | envs per seed | iteration (ms) | env-steps/s | updates/s | peak memory (GB) | compile (s) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['seeds']} | {r['num_envs']} | {r['iteration_ms']:.1f} | {r['env_steps_per_s']:,.0f} | "
            f"{r['updates_per_s']:,.0f} | {r['peak_memory_gb']:.2f} | {r['compile_s']:.1f} |"
        )
    print("\n".join(lines))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench_train.md").write_text("\n".join(lines) + "\n")
        (out / "bench_train.json").write_text(json.dumps({"device": device, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
