"""Where a batched environment step's time goes: the continuous collision test's parts switched off
one at a time (not verdicts to use: a probe), and optionally a profile of the whole step.

Each variant steps ``bench_env``'s random-action rollout (B environments, 100 steps, one jitted scan)
and reports ms per step; ``--profile`` traces one rollout of the full test and sums the GPU's kernel
and copy time per step, with the busiest kernels.

    python experiments/probe_continuous.py --batch 32768 --profile --out experiments/results/continuous/subtree

``--count`` instead counts, on the same rollout, which test settles each step: its end pose in a
collision, the end pose clear by each capsule's ``v_t`` (what stands in for the root), every pair
clear by ``v_t`` at the step's start or its end (a stand-in from both ends, not in the package), the
root interval, or else the walk; as shares of all steps.

    python experiments/probe_continuous.py --count --batch 4096 --steps 60 --out experiments/results/continuous/stand_ins
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from regrasp_mjx.core import geometry
from regrasp_mjx.core.atomic import machine, write_json
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.world import continuous

sys.path.insert(0, str(Path(__file__).parent))
from bench_env import make_rollout, set_walk  # noqa: E402  (beside this script)

FULL = continuous.motion_collides


def _root_only(gathered: bool):
    """The root interval tested (gathered or on every lane), its halves never walked."""

    def motion_collides(bound_fn, motion, fastest, margin, share=None, known=None, proved=None):
        def lane(batched):
            def one(motion, fastest, pending):
                h0 = jnp.float32(0.5)
                ok, stop = continuous._verdict(*bound_fn(motion, h0, h0), h0, fastest, margin)
                return pending & ~ok & stop

            return one

        pending = ~known & ~proved
        if gathered:
            return known | continuous._gathered(lane, continuous.ROOT_SHARE)(motion, fastest, pending)
        return known | lane(False)(motion, fastest, pending)

    return motion_collides


def _end_only(bound_fn, motion, fastest, margin, share=None, known=None, proved=None):
    return known


def _walk_free(bound_fn, motion, fastest, margin, share=None, known=None, proved=None):
    """Every part run, the halves' walk replaced by nothing (its lanes still gathered)."""
    saved = continuous._halves_lane
    continuous._halves_lane = lambda bound_fn, margin, batched: lambda motion, fastest, pending: pending & (fastest < 0)
    try:
        return FULL(bound_fn, motion, fastest, margin, share, known, proved)
    finally:
        continuous._halves_lane = saved


VARIANTS = {
    "full": FULL,
    "halves' rounds, no walk": _walk_free,
    "root gathered, no halves": _root_only(True),
    "root on every lane, no halves": _root_only(False),
    "end pose only": _end_only,
}


def time_variant(batch: int, steps: int, rollouts: int, seed: int) -> tuple[float, float]:
    env = RegraspEnv(EnvConfig(check_actions=False))
    rollout = make_rollout(env, batch, steps)
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(jax.random.PRNGKey(seed)))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for k in jax.random.split(jax.random.PRNGKey(seed + 1), rollouts):
        out = rollout(k)
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / (rollouts * steps) * 1e3, compile_s


def profile(batch: int, steps: int, seed: int, top: int = 25) -> dict:
    """One rollout of the full test traced: per step, the GPU's busy time by kind and the busiest kernels."""
    env = RegraspEnv(EnvConfig(check_actions=False))
    rollout = make_rollout(env, batch, steps)
    jax.block_until_ready(rollout(jax.random.PRNGKey(seed)))
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder, create_perfetto_trace=True):
            t0 = time.perf_counter()
            jax.block_until_ready(rollout(jax.random.PRNGKey(seed + 1)))
            wall = time.perf_counter() - t0
        trace = next(Path(folder).rglob("*.json.gz"))
        events = json.loads(gzip.decompress(trace.read_bytes()))["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    busy, count, kernels = collections.Counter(), collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") != "X" or "GPU" not in names.get(e.get("pid"), ""):
            continue
        kind = "copy" if "memcpy" in e["name"].lower() or "Memcpy" in e["name"] else "kernel"
        busy[kind] += e.get("dur", 0)
        count[kind] += 1
        kernels[e["name"]] += e.get("dur", 0)
    per = lambda us: round(us / steps / 1e3, 4)  # noqa: E731  us -> ms per step
    return {
        "wall_ms_per_step": round(wall / steps * 1e3, 4),
        "gpu_ms_per_step": {k: per(v) for k, v in busy.items()},
        "events_per_step": {k: round(v / steps, 1) for k, v in count.items()},
        "top_kernels_ms_per_step": {k: per(v) for k, v in kernels.most_common(top)},
        "processes": sorted(set(names.values())),
    }


COUNTS = ("ends in a collision", "end pose by v_t", "start or end pose by v_t, per pair", "root interval", "walk")


def count_settled(batch: int, steps: int, seed: int) -> dict[str, float]:
    """The share of a random-action rollout's steps each test settles (module docstring); the shares
    overlap but for the walk's (the steps none of the others settles)."""
    env = RegraspEnv(EnvConfig(check_actions=False))

    def settled(es, a):  # one environment's step, as RegraspEnv.move tests it
        dp, rotvec = a[:3] * env.max_dp, a[3:] * env.max_drot
        placed = env._place_others(es.needle_pos, es.needle_quat)
        end_quat = geometry.quat_mul(geometry.quat_from_rotvec(rotvec), es.ee_quat)
        end = env._gaps(placed, es.ee_pos + dp, end_quat)
        speed = jnp.linalg.norm(dp) + jnp.linalg.norm(rotvec) * env.levers
        by = lambda d: d.reshape(speed.shape[0], -1) - speed[:, None] - env.clearance  # noqa: E731
        start = by(env._gaps(placed, es.ee_pos, es.ee_quat))
        ends_in = jnp.any(end < env.clearance)
        either = jnp.all(jnp.maximum(by(end), start) >= continuous.SLACK)
        half = jnp.float32(0.5)
        _, low = env._bounds_along((placed, es.ee_pos, es.ee_quat, dp, rotvec), half, half)
        root = jnp.all(low - env.clearance >= continuous.SLACK)
        end_ok = jnp.all(by(end) >= continuous.SLACK)
        return jnp.stack([ends_in, end_ok, either, root, ~(ends_in | either | root)])

    shares = lambda states, actions: jnp.mean(jax.vmap(settled)(states, actions), axis=0)  # noqa: E731
    per_step = make_rollout(env, batch, steps, record=shares)(jax.random.PRNGKey(seed))[3]
    return {name: round(float(v), 4) for name, v in zip(COUNTS, jnp.mean(per_step, axis=0))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=32768)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--rollouts", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--walk", default=None, help="the test's XLA walk, as bench_env.py --walks names one (default: the module's)"
    )
    p.add_argument("--profile", action="store_true")
    p.add_argument("--count", action="store_true", help="count which test settles each step (no timing)")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    if args.count:
        result = {"machine": f"{machine()}; jax {jax.__version__}", "batch": args.batch, "steps": args.steps}
        result |= {"seed": args.seed, "shares": count_settled(args.batch, args.steps, args.seed)}
        print(json.dumps(result, indent=1))
        if args.out:
            write_json(Path(args.out) / f"count_{args.batch}x{args.steps}.json", result)
        return
    if args.walk is not None and args.walk.startswith("kernel"):
        p.error("--walk: the variants replace parts of the XLA walk; accepted: chunk or DEPTH:HEAD:TAIL_DEPTH")
    # the XLA walk, which the variants take apart (on a GPU the package tests with the kernel)
    walk = set_walk(args.walk or f"{continuous.SUBTREE_DEPTH}:{continuous.HEAD_STEPS}:{continuous.TAIL_DEPTH}")
    result = {"machine": f"{machine()}; jax {jax.__version__}", "batch": args.batch, "walk": walk, "variants": {}}
    print(result["machine"], flush=True)
    # the first program timed in a process runs slow (seen on an H100: 1.64 against 1.07 ms a step for
    # the same test): one discarded run first
    time_variant(args.batch, args.steps, 1, args.seed)
    for name, fn in VARIANTS.items():
        continuous.motion_collides = fn
        ms, compile_s = time_variant(args.batch, args.steps, args.rollouts, args.seed)
        result["variants"][name] = {"ms_per_step": round(ms, 4), "env_steps_per_s": args.batch / ms * 1e3}
        print(f"{name:32s} {ms:8.4f} ms/step  {args.batch / ms * 1e3:14,.0f} env-steps/s (compile {compile_s:.1f} s)")
    continuous.motion_collides = FULL
    if args.profile:
        result["profile"] = profile(args.batch, args.steps, args.seed)
        print(json.dumps(result["profile"], indent=1))
    if args.out:
        write_json(Path(args.out) / f"probe_continuous_{args.batch}.json", result)


if __name__ == "__main__":
    main()
