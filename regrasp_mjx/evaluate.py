"""``python -m regrasp_mjx.evaluate``: a policy on a test set, as the paper's Tables I and II count.

    python -m regrasp_mjx.evaluate                                  # the shipped policy, paper300
    python -m regrasp_mjx.evaluate --policy runs/fast/policy --testset my.npz --json

Plans go through the collision shield (``Policy.plan``'s default; ``--no-shield`` rolls the bare
policy out, as training evaluates it). Success, collision and time-out rates of one pass over the
test set (no retries); planning time of
one query at a time (compiled and warmed up first; the wall time from the poses to the whole
trajectory, numpy in and out), mean and median; batched throughput (all queries in one call,
repeated, plans/s); path length in mm over the successes. Planning runs on JAX's default device:
``JAX_PLATFORMS=cpu taskset -c 0 python -m regrasp_mjx.evaluate`` times one CPU core.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np

from regrasp_mjx.config import ConfigError
from regrasp_mjx.policy import DEFAULT_POLICY, PolicyError, load_policy, shipped_policies
from regrasp_mjx.rollout import summarize
from regrasp_mjx.sampling import PAPER300, TestsetError, load_testset

DEFAULT_TESTSET = PAPER300


def episode_poses(ep) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Needle, start and goal poses ``[N, 7]`` of test-set rows (the inputs of ``Policy.plan``)."""
    cat = lambda p, q: np.concatenate([p, q], axis=1)  # noqa: E731
    return (
        cat(ep.needle_pos, ep.needle_quat),
        cat(ep.start_pos, ep.start_quat),
        cat(ep.goal_pos, ep.goal_quat),
    )


def episode_needles(ep) -> dict[str, np.ndarray]:
    """The needles of test-set rows as ``Policy.plan`` takes them (``needle_radius_mm``, ``wire_radius_mm``)."""
    return {
        "needle_radius_mm": np.asarray(ep.needle_radius, np.float64) * 1e3,
        "wire_radius_mm": np.asarray(ep.wire_radius, np.float64) * 1e3,
    }


def plan_testset(policy, episodes, shield: bool):
    """Test-set rows planned through ``Policy.plan`` (each with its own needle): one batched
    ``Plan`` (a colliding start counts as a collision)."""
    return policy.plan(*episode_poses(episodes), check_grasp=False, shield=shield, **episode_needles(episodes))


def outcomes(policy, episodes) -> dict[str, dict]:
    """A loaded policy planned on the problems through ``Policy.plan``, bare and shielded."""
    return {
        name: summarize(plan_testset(policy, episodes, shield), name)
        for name, shield in (("bare", False), ("shielded", True))
    }


def evaluate(
    policy,
    episodes,
    timed_queries: int | None = None,
    batch_repeats: int = 5,
    batch_size: int | None = None,
    shield: bool = True,
) -> dict:
    """The numbers of one policy on one test set (see the module docstring). The throughput batch
    repeats the test set's queries up to ``batch_size``; ``timed_queries=0`` and
    ``batch_repeats=0`` skip the timings."""
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes)
    n = len(needle)

    def run(needle, start, goal, rows=slice(None)):
        kw = {k: v[rows] for k, v in needles.items()}
        return policy.plan(needle, start, goal, check_grasp=False, shield=shield, **kw)

    plan = run(needle, start, goal)
    rows = np.arange(batch_size or n) % n
    big = (needle[rows], start[rows], goal[rows], rows)
    batch_s = float("nan")
    if batch_repeats:
        if len(rows) != n:
            run(*big)  # compiles the batched program (the test-set pass above compiled its own size)
        t0 = time.perf_counter()
        for _ in range(batch_repeats):
            run(*big)
        batch_s = (time.perf_counter() - t0) / batch_repeats
    times = []
    if timed_queries != 0:
        run(needle[0], start[0], goal[0], 0)  # compiles the one-query program
        for i in range(min(n, timed_queries or n)):
            t0 = time.perf_counter()
            run(needle[i], start[i], goal[i], i)
            times.append(time.perf_counter() - t0)
    ok = plan.success
    return {
        "problems": n,
        "success_rate": float(ok.mean()),
        "collision_rate": float((plan.collision | ~plan.start_valid).mean()),
        "time_out_rate": float(plan.time_out.mean()),
        "invalid_starts": int((~plan.start_valid).sum()),
        "path_length_mm": float(plan.path_length_mm[ok].mean()) if ok.any() else None,
        "steps_mean": float(plan.steps[ok].mean()) if ok.any() else None,
        "planning_time_ms_mean": 1e3 * float(np.mean(times)) if times else None,
        "planning_time_ms_median": 1e3 * float(np.median(times)) if times else None,
        "timed_queries": len(times),
        "batch_plans_per_s": len(rows) / batch_s,
        "batch_size": len(rows),
        "ensemble": policy.members,
        "shield": shield,
        "device": str(jax.devices()[0].device_kind),
        "backend": jax.default_backend(),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.evaluate", description=__doc__.splitlines()[0])
    p.add_argument(
        "--policy",
        default=None,
        help=f"policy folder, or a shipped name ({', '.join(shipped_policies())}; default: the shipped one, {DEFAULT_POLICY})",
    )
    p.add_argument("--testset", default=str(DEFAULT_TESTSET), help="test set .npz (default paper300)")
    p.add_argument("--queries", type=int, default=None, help="time only the first N single queries")
    p.add_argument("--repeats", type=int, default=5, help="repeats of the batched call")
    p.add_argument(
        "--batch-size", type=int, default=None, help="queries per batched call (test set repeated; default its size)"
    )
    p.add_argument("--no-shield", action="store_true", help="roll the bare policy out (no collision shield)")
    p.add_argument(
        "--clearance-mm",
        type=float,
        default=None,
        help="collision margin: a pose collides closer than this to the needle or the other tool "
        "(default: the policy's own, 0 for the shipped ones)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    try:
        policy = load_policy(args.policy)
        if args.clearance_mm is not None:
            policy = policy.with_env(clearance_mm=args.clearance_mm)
        episodes, _ = load_testset(args.testset)
    except (PolicyError, TestsetError, ConfigError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    r = evaluate(policy, episodes, args.queries, args.repeats, args.batch_size, shield=not args.no_shield)
    r["policy"] = str(args.policy or DEFAULT_POLICY)
    r["clearance_mm"] = policy.env_config.clearance_mm
    r["testset"] = args.testset
    if args.json:
        print(json.dumps(r))
        return 0
    path = "-" if r["path_length_mm"] is None else f"{r['path_length_mm']:.2f} mm"
    print(
        f"{r['policy']} on {r['testset']} ({r['problems']} problems, {r['backend']}: {r['device']}; "
        f"shield {'on' if r['shield'] else 'off'}, clearance margin {r['clearance_mm']:g} mm)\n"
        f"  success {r['success_rate']:.3f}  collision {r['collision_rate']:.3f}  time-out {r['time_out_rate']:.3f}\n"
        + (
            f"  planning time per query: mean {r['planning_time_ms_mean']:.2f} ms, median "
            f"{r['planning_time_ms_median']:.2f} ms ({r['timed_queries']} queries, one at a time)\n"
            if r["timed_queries"]
            else ""
        )
        + (f"  batched: {r['batch_plans_per_s']:,.0f} plans/s (batch {r['batch_size']})\n" if args.repeats else "")
        + f"  path length {path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
