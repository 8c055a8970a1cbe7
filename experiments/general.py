"""The generalist (issue 15) on general1000 and paper300, bare and shielded, broken down by R and alpha*.

    python experiments/general.py --policy seed0=runs/gen/seed0/policy --policy seed1=runs/gen/seed1/policy \\
        --policy seed2=runs/gen/seed2/policy --policy specialist= --out experiments/results/general

Each policy is planned through ``Policy.plan`` (as deployed) on every problem of the test sets it was
trained for: a general policy on ``general1000`` (1000 problems from the full ranges of
``config.GENERAL_TASK``) and on paper300; a specialist (empty FOLDER: the shipped default) on
paper300 only, since it refuses other needles and goal grasps. Writes ``NAME.md`` (the table, and
bare success on general1000 by needle radius and by goal angle alpha*, mean over the general
policies) and ``NAME.json`` (the rows, and each general policy's per-problem bare outcome with the
problem's R and alpha*, which ``notebooks/04_policy.ipynb`` draws as a heat map).
"""

from __future__ import annotations

import argparse
import json
import math

import jax
import numpy as np

from regrasp_mjx.atomic import write_results
from regrasp_mjx.evaluate import plan_testset
from regrasp_mjx.policy import load_policy
from regrasp_mjx.rollout import summarize
from regrasp_mjx.sampling import GENERAL1000, PAPER300, load_testset

R_BINS_MM = (4.0, 6.0, 8.0, 10.0, 12.0)
ALPHA_BINS_RAD = tuple(10 * math.pi / 9 + k * (math.pi / 3) / 4 for k in range(5))  # [10pi/9, 13pi/9] in 4


def binned(success: np.ndarray, values: np.ndarray, edges) -> list[float]:
    idx = np.clip(np.digitize(values, edges) - 1, 0, len(edges) - 2)
    return [float(success[idx == b].mean()) if np.any(idx == b) else float("nan") for b in range(len(edges) - 1)]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", action="append", required=True, metavar="NAME=FOLDER", help="empty FOLDER: shipped")
    p.add_argument("--testset", default=str(GENERAL1000), help="the general test set (default general1000)")
    p.add_argument("--out", default=None)
    p.add_argument("--name", default="general")
    args = p.parse_args(argv)
    general, _ = load_testset(args.testset)
    paper, _ = load_testset(PAPER300)
    rows, per_problem = [], {}
    for item in args.policy:
        name, _, folder = item.partition("=")
        policy = load_policy(folder or None)
        sets = {"general1000": general, "paper300": paper} if policy.general else {"paper300": paper}
        for sname, episodes in sets.items():
            for shield in (False, True):
                out = plan_testset(policy, episodes, shield)
                rollout = "shielded" if shield else "bare"
                rows.append(
                    {"policy": name, "folder": folder or "shipped", "testset": sname, **summarize(out, rollout)}
                )
                print(json.dumps(rows[-1]), flush=True)
                if sname == "general1000" and not shield:
                    per_problem[name] = np.asarray(out.success, bool)
    radius_mm = np.asarray(general.needle_radius) * 1e3
    alpha = np.asarray(general.goal_grasp)[:, 0]
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [
        f"Machine: {jax.default_backend()} ({jax.devices()[0].device_kind}); planned through Policy.plan; "
        f"general1000 = `{args.testset}`.",
        "",
        "| policy | test set | rollout | success | collision | time-out | path (mm) | steps |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['testset']} | {r['rollout']} | {r['success_rate']:.3f} | {r['collision_rate']:.3f} | "
            f"{r['time_out_rate']:.3f} | {fmt(r['path_length_mm'])} | {fmt(r['steps'])} |"
        )
    breakdown = {}
    if per_problem:
        success = np.mean([v for v in per_problem.values()], axis=0)  # mean over the general policies
        by_r, by_alpha = binned(success, radius_mm, R_BINS_MM), binned(success, alpha, ALPHA_BINS_RAD)
        counts_r = np.histogram(radius_mm, R_BINS_MM)[0].tolist()
        counts_a = np.histogram(alpha, ALPHA_BINS_RAD)[0].tolist()
        breakdown = {"by_radius_mm": [R_BINS_MM, by_r, counts_r], "by_alpha_rad": [ALPHA_BINS_RAD, by_alpha, counts_a]}
        lines += [
            "",
            f"Bare success on general1000 by needle radius, mean over {', '.join(per_problem)}:",
            "",
            "| R (mm) | " + " | ".join(f"{a:g}-{b:g}" for a, b in zip(R_BINS_MM[:-1], R_BINS_MM[1:])) + " |",
            "| --- |" + " ---: |" * len(by_r),
            "| success | " + " | ".join(f"{v:.3f}" for v in by_r) + " |",
            "| problems | " + " | ".join(str(c) for c in counts_r) + " |",
            "",
            "Bare success on general1000 by goal angle alpha* (degrees), same policies:",
            "",
            "| alpha* (deg) | "
            + " | ".join(
                f"{math.degrees(a):.0f}-{math.degrees(b):.0f}" for a, b in zip(ALPHA_BINS_RAD[:-1], ALPHA_BINS_RAD[1:])
            )
            + " |",
            "| --- |" + " ---: |" * len(by_alpha),
            "| success | " + " | ".join(f"{v:.3f}" for v in by_alpha) + " |",
            "| problems | " + " | ".join(str(c) for c in counts_a) + " |",
        ]
    print("\n".join(lines))
    extra = {
        "breakdown": breakdown,
        "per_problem": {
            "needle_radius_mm": radius_mm.tolist(),
            "goal_alpha_rad": alpha.tolist(),
            "bare_success": {k: v.astype(int).tolist() for k, v in per_problem.items()},
        },
    }
    write_results(args.out, args.name, lines, {"rows": rows, **extra})


if __name__ == "__main__":
    main()
