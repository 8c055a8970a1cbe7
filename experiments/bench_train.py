"""Throughput of the training program: env-steps/s and updates/s of one jitted iteration at several
env counts, seed counts and device counts, with peak device memory.

An iteration is what ``python -m regrasp_mjx.train`` runs between host steps: ``num_envs`` x 100
exploration steps per seed, the buffer inserts, ``updates_per_iteration`` DDPG+BC updates per seed.
With ``--devices 1,2`` every setting is also run data parallel over 2 GPUs (``num_envs`` in total,
split; gradients averaged every update), and the 2-to-1 ratio is printed for each.
Demonstrations are stand-ins (random transitions; throughput does not depend on their values).
Compile time excluded; ``--iterations`` timed after one warm-up.

    python experiments/bench_train.py --envs 128,512,2048,8192 --seeds 1,3,8 --out experiments/results
    python experiments/bench_train.py --envs 512,8192,32768 --seeds 1 --devices 1,2 --out results/x2
    python experiments/bench_train.py --envs 512 --seeds 4,8 --devices 1 --out results/x2_members1   # then
    python experiments/bench_train.py --envs 512 --seeds 4,8 --devices 2 --out results/x2_members2   # seeds split
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.agents.ddpg_bc.config import make_config
from regrasp_mjx.agents.ddpg_bc.learner import Learner
from regrasp_mjx.core.atomic import dumps, write_results


def bench(num_envs: int, seeds: int, updates: int, iterations: int, devices: int = 1, shard: str = "auto") -> dict:
    # The buffer holds at least two iterations of transitions (flashbax refuses a bigger insert).
    buffer = max(1_000_000, 2 * num_envs * 100)
    cfg = make_config(
        "fast",
        num_envs=num_envs,
        num_seeds=seeds,
        updates_per_iteration=updates,
        devices=devices,
        buffer_size=buffer,
        shard=shard,
    )
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
    peak = max((d.memory_stats() or {}).get("peak_bytes_in_use", float("nan")) for d in jax.devices()[:devices])
    return {
        "devices": devices,
        "shard": learner.shard,
        "num_envs": num_envs,
        "seeds": seeds,
        "updates_per_iteration": updates,
        "iteration_ms": 1e3 * dt,
        "env_steps_per_s": seeds * num_envs * cfg.env.horizon / dt,
        "updates_per_s": seeds * updates / dt,
        "peak_memory_gb": peak / 1e9,  # the most on one device
        "compile_s": compile_s,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", default="128,512,2048,8192", help="environments per seed (all devices together)")
    p.add_argument("--seeds", default="1,3,8", help="seed counts (more than one: at 512 envs only)")
    p.add_argument("--devices", default="1", help="device counts, e.g. 1,2")
    p.add_argument(
        "--shard",
        default="auto",
        choices=("auto", "members", "envs"),
        help="how several devices share the work (TrainConfig.shard): auto = whole seeds per device when "
        "they divide evenly, else data parallel",
    )
    p.add_argument("--updates", type=int, default=200)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    rows = []
    for seeds in (int(s) for s in args.seeds.split(",")):
        for envs in (int(e) for e in args.envs.split(",")):
            if seeds > 1 and envs != 512:
                continue  # seeds are compared at the fast preset's 512 envs
            for devices in (int(d) for d in args.devices.split(",")):
                r = bench(envs, seeds, args.updates, args.iterations, devices, args.shard)
                rows.append(r)
                print(dumps(r), flush=True)
    device = jax.devices()[0].device_kind
    lines = [
        f"Device: {device} ({jax.device_count()} visible), jax {jax.__version__}; updates per iteration "
        f"{args.updates}, batch 256, horizon 100.",
        "",
        "| devices | shard | seeds | envs per seed | iteration (ms) | env-steps/s | updates/s | peak memory per device (GB) "
        "| compile (s) | vs 1 device |",
        "| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        base = next(
            (b for b in rows if b["devices"] == 1 and (b["seeds"], b["num_envs"]) == (r["seeds"], r["num_envs"])), None
        )
        ratio = f"{base['iteration_ms'] / r['iteration_ms']:.2f}x" if base and r["devices"] > 1 else "-"
        lines.append(
            f"| {r['devices']} | {r['shard']} | {r['seeds']} | {r['num_envs']} | {r['iteration_ms']:.1f} | {r['env_steps_per_s']:,.0f} | "
            f"{r['updates_per_s']:,.0f} | {r['peak_memory_gb']:.2f} | {r['compile_s']:.1f} | {ratio} |"
        )
    print("\n".join(lines))
    write_results(args.out, "bench_train", lines, {"device": device, "rows": rows})


if __name__ == "__main__":
    main()
