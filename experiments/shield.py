"""The planner's collision shield: success, collisions and planning time with and without it.

``Policy.plan`` replaces a policy action that would collide by the first collision-free one of a
fixed list of alternatives (the ensemble members' own actions, half the action, Gaussian
perturbations of it; ``regrasp_mjx.shield.shield_candidates``). This script measures what that does
for the shipped ensemble and for each of its member networks alone, on the paper's 300 problems
and on held-out sets drawn with seeds of their own, and times single queries on this machine
(the same machine for both, so the ratio is the point).

    JAX_PLATFORMS=cpu taskset -c 0 python experiments/shield.py --out experiments/results
"""

from __future__ import annotations

import argparse
import json

import jax

from regrasp_mjx.atomic import write_results
from regrasp_mjx.evaluate import DEFAULT_TESTSET, evaluate
from regrasp_mjx.policy import load_policy
from regrasp_mjx.sampling import load_testset
from regrasp_mjx.testset import make_testset


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", default=None, help="policy folder (default: the shipped one)")
    p.add_argument("--heldout", default="3000:2022", help="N:SEED of a held-out set drawn here (empty: none)")
    p.add_argument("--queries", type=int, default=100, help="single queries timed per setting (0: none)")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    shipped = load_policy(args.policy)
    sets = {"paper300": load_testset(DEFAULT_TESTSET)[0]}
    if args.heldout:
        n, seed = (int(x) for x in args.heldout.split(":"))
        sets[f"heldout{n}_seed{seed}"] = make_testset(n, seed, shipped.env_config)
    policies = {f"ensemble of {shipped.members}": shipped}
    if shipped.members > 1:
        policies.update({f"member {i}": shipped.member(i) for i in range(shipped.members)})
    rows = []
    for pname, policy in policies.items():
        for sname, episodes in sets.items():
            for shield in (False, True):
                timed = args.queries if sname == "paper300" else 0
                r = evaluate(policy, episodes, timed_queries=timed, batch_repeats=0, shield=shield)
                r.update(policy=pname, testset=sname)
                rows.append(r)
                print(json.dumps(r), flush=True)
    ms = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [
        f"Machine: {jax.default_backend()} ({jax.devices()[0].device_kind}), jax {jax.__version__}; planning time: one "
        f"query at a time, {args.queries} queries of paper300, median.",
        "",
        "| policy | test set | shield | success | collision | time-out | path (mm) | steps | planning time (ms) |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['testset']} | {'on' if r['shield'] else 'off'} | {r['success_rate']:.3f} | "
            f"{r['collision_rate']:.3f} | {r['time_out_rate']:.3f} | {ms(r['path_length_mm'])} | "
            f"{ms(r['steps_mean'])} | {ms(r['planning_time_ms_median'])} |"
        )
    print("\n".join(lines))
    write_results(args.out, "shield", lines, rows)


if __name__ == "__main__":
    main()
