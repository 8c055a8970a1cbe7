"""One query at a time on one CPU core: the policy against RRT-Connect, timed side by side.

Every method plans the same queries in the same process, pinned to one core, in alternating order
(each repeat rotates which method goes first, so drift of the machine falls on all of them), and
the script prints each method's median per repeat, the median over all, and the ratio to the first
method. Methods: the shipped policy through ``Policy.plan`` as a user calls it (shielded, the
grasp-library check on) on the lean path (numba, :mod:`regrasp_mjx.inference.lean_planner`, the default for
one query on the CPU) and on the JAX path (one compiled rollout per query, numpy in and out), the
lean planner's compiled call alone (``LeanPlanner``: the same checks and rollout, no ``Plan``
built), and OMPL RRT-Connect (forward and reverse, with and without 0.2 s of
shortcutting, range ``--range-mm``; collision checks with CPU MuJoCo, the same model, and again
with ``checker="lean"``: the same pairs in compiled code, one call per motion). Problems
that collide at the start or goal under the host checker are left out for every method.

    python experiments/bench_plan.py --core 0 --out experiments/results/bench_plan
"""

from __future__ import annotations

import argparse
import os

# One core, before JAX starts its thread pools: what one query costs where nothing else runs.
if __name__ == "__main__":
    _core = argparse.ArgumentParser(add_help=False)
    _core.add_argument("--core", type=int, default=0)
    os.sched_setaffinity(0, {_core.parse_known_args()[0].core})
    os.environ.setdefault("JAX_PLATFORMS", "cpu")

import time
from datetime import date

import jax
import numpy as np

from regrasp_mjx.core.atomic import dumps, machine, write_results
from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.inference.grasps import GraspLibrary
from regrasp_mjx.inference.plans import NO_LIBRARY
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.queries import TaskSpec
from regrasp_mjx.inference.robustness import policy_hash
from regrasp_mjx.planning.ompl_planner import OmplPlanner, PlannerConfig
from regrasp_mjx.world.sampling import episode_needles, episode_poses, load_testset


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--core", type=int, default=0, help="the CPU core this process is pinned to (default 0)")
    p.add_argument("--policy", default=None, help="a shipped name or policy folder (default: the shipped default)")
    p.add_argument("--testset", default="paper300", help="a shipped name or .npz (default paper300)")
    p.add_argument("--queries", type=int, default=100, help="queries per method and repeat (default 100)")
    p.add_argument("--repeats", type=int, default=5, help="rounds over all methods (default 5)")
    p.add_argument("--range-mm", type=float, default=PlannerConfig.rrt_range_mm, help="RRT-Connect's range, mm")
    p.add_argument("--seed", type=int, default=0, help="OMPL's seed")
    p.add_argument("--out", default=None, help="folder for bench_plan.md and bench_plan.json")
    p.add_argument("--no-rrt", action="store_true", help="time the policy's paths only (no OMPL needed)")
    args = p.parse_args()
    if args.queries < 1 or args.repeats < 1:
        p.error("--queries and --repeats are accepted as integers >= 1")
    policy = load_policy(args.policy)
    episodes, _ = load_testset(args.testset)
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes)
    clear = HostChecker().clear_episodes(episodes)[: args.queries]

    def policy_query(engine):
        def query(i):
            kw = {k: v[i] for k, v in needles.items()}
            plan = policy.plan(needle[i], start[i], goal[i], engine=engine, **kw)
            return bool(plan.success), float(plan.path_length_mm)

        return query

    lean = policy.lean(True)
    tasks = [policy.task_ranges.vector(TaskSpec.of({k: v[i] for k, v in needles.items()})) for i in range(len(needle))]
    library = GraspLibrary.default().unit_arrays if not policy.general else NO_LIBRARY

    def lean_core(i):
        out = lean(needle[i], start[i], goal[i], tasks[i], library)
        return bool(out.outcome[1] > 0), float(out.outcome[5] * 1e3)

    def rrt(direction, simplify, kind="mujoco"):
        cfg = PlannerConfig(
            "RRTConnect", direction, budget_s=10.0, simplify_s=simplify, rrt_range_mm=args.range_mm, checker=kind
        )
        planner = OmplPlanner(cfg, HostChecker(), seed=args.seed)
        base = planner.checker  # the scene's needle; each query's own below

        def query(i):
            planner.checker = base.for_needle(episodes.needle_radius[i], episodes.wire_radius[i])
            r = planner.plan(needle[i], start[i], goal[i])
            return r.solved, r.path_length_mm

        return query

    name = args.policy or "default"
    methods = {
        f"policy `{name}`, shielded, lean path (`Policy.plan`)": policy_query("lean"),
        f"policy `{name}`, shielded, JAX path (`Policy.plan`)": policy_query("jax"),
        "its compiled query alone (`LeanPlanner` called: checks, grasp library, rollout; no `Plan`)": lean_core,
    }
    if not args.no_rrt:
        for kind in ("mujoco", "lean"):
            for simplify in (0.0, 0.2):
                for direction in ("forward", "reverse"):
                    label = f"RRT-Connect ({direction[0].upper()})" + (" + 0.2 s shortcutting" if simplify else "")
                    methods[label + (", lean checker" if kind == "lean" else "")] = rrt(direction, simplify, kind)
    for query in methods.values():  # compile and warm up outside the timing
        query(clear[0])
    times = {m: [] for m in methods}
    outcome = {m: [] for m in methods}
    order = list(methods)
    for r in range(args.repeats):
        for m in order[r % len(order) :] + order[: r % len(order)]:
            per_query = []
            for i in clear:
                t0 = time.perf_counter()
                ok, length = methods[m](i)
                per_query.append(time.perf_counter() - t0)
                if r == 0:
                    outcome[m].append((ok, length))
            times[m].append(per_query)
            print(dumps({"repeat": r, "method": m, "median_ms": 1e3 * float(np.median(per_query))}), flush=True)
    first = float(np.median(times[order[0]]))
    rows = []
    for m in order:
        t = np.asarray(times[m])
        ok = np.array([o for o, _ in outcome[m]])
        rows.append(
            {
                "method": m,
                "success_rate": float(ok.mean()),
                "path_length_mm": float(np.mean([length for o, length in outcome[m] if o])) if ok.any() else None,
                "median_ms": 1e3 * float(np.median(t)),
                "mean_ms": 1e3 * float(t.mean()),
                "median_ms_per_repeat": [round(1e3 * float(np.median(x)), 4) for x in t],
                "ratio_to_first": float(np.median(t)) / first,
            }
        )
    meta = {
        "machine": machine(devices=False),
        "core": args.core,
        "date": date.today().isoformat(),
        "policy": name,
        "policy_hash": policy_hash(args.policy),
        "testset": args.testset,
        "queries": len(clear),
        "repeats": args.repeats,
        "range_mm": args.range_mm,
        "jax": jax.__version__,
    }
    lines = [
        f"{meta['machine']}, pinned to core {args.core}; {meta['date']}; policy `{name}` (hash "
        f"{meta['policy_hash']}); {len(clear)} queries of {args.testset} per method and repeat, {args.repeats} "
        f"repeats in rotating order; RRT-Connect range {args.range_mm:g} mm, 10 s budget.",
        "",
        "| method | success | path (mm) | median (ms) | mean (ms) | medians per repeat (ms) | time / policy's |",
        "| --- | ---: | ---: | ---: | ---: | --- | ---: |",
    ]
    for row in rows:
        path = "-" if row["path_length_mm"] is None else f"{row['path_length_mm']:.2f}"
        lines.append(
            f"| {row['method']} | {row['success_rate']:.3f} | {path} | {row['median_ms']:.3f} | {row['mean_ms']:.3f} | "
            f"{', '.join(f'{x:.3f}' for x in row['median_ms_per_repeat'])} | {row['ratio_to_first']:.1f}x |"
        )
    print("\n".join(lines))
    write_results(args.out, "bench_plan", lines, {**meta, "rows": rows})


if __name__ == "__main__":
    main()
