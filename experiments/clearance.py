"""From plan to robot: success at a clearance margin, each path's smallest clearance re-checked
finely, and whether the regrasping PSM can follow the plans (issue: dVRK kinematics and margin).

1. Margin table. For each margin m (mm) the shipped policy plans paper300 through
   ``Policy.with_env(clearance_mm=m)`` (a pose collides closer than m; the derived sub-step count
   then also rules out penetration between checks), bare and shielded, and BIT* (R) plans with the
   host checker at the same margin (10 s budget). Problems whose start or goal is already closer
   than m are left out (counted in ``valid``).
2. Clearance distribution. Every successful path is re-checked with CPU MuJoCo's ``mj_geomDistance``
   at ``--substeps`` poses per policy step (BIT*'s segments at the same spacing: 20 poses per
   0.5 mm or 3 degrees); per path the smallest clearance; the 1st percentile and median over paths,
   and the paths that penetrate (clearance < 0; with the conservative needle that is contact with
   the true wire or an under-estimate of its clearance by at most the needle model's bound,
   ``Scene.needle_error_bound``).
3. Reachability. The shipped policy's shielded plans (margin 0) as dVRK PSM joint trajectories
   (``regrasp_mjx.robot.dvrk``) for two placements of the regrasping arm's remote centre of motion (RCM):
   ``start`` puts it 0.12 m behind each problem's start pose on the tool's shaft (the arm starts
   at its neutral configuration, as when a surgeon has brought the tool there); ``fixed`` puts it
   where ``start`` would for the average start pose and keeps it for every problem (one port for
   the whole test set). The grasping arm's RCM is 0.12 m behind e_g (neutral). Reported: the share
   of plans whose every pose is within the joint limits, the joints that leave them, and the
   joint-space path length.

    python experiments/clearance.py --margins 0,0.05,0.1,0.2 --out experiments/results/clearance
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import numpy as np

from regrasp_mjx.core.atomic import dumps, write_results
from regrasp_mjx.envs import host
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.planning.ompl_planner import PlannerConfig
from regrasp_mjx.planning.pool import plan_all
from regrasp_mjx.robot import dvrk, psm_joints
from regrasp_mjx.world.sampling import DEFAULT_TESTSET, episode_poses, load_testset


def clearance_stats(values: list[float]) -> dict:
    v = np.asarray(values) * 1e3
    if len(v) == 0:
        return {"paths": 0}
    return {
        "paths": int(len(v)),
        "p1_mm": float(np.percentile(v, 1)),
        "median_mm": float(np.median(v)),
        "min_mm": float(v.min()),
        "penetrating": int((v < 0).sum()),
    }


def limit_aware(policy, needle: np.ndarray, start: np.ndarray, depth_mm: np.ndarray, base: np.ndarray) -> dict:
    """The shielded plans with one fixed port, the shield also keeping the joints within limits
    (``plan_from_camera(..., psm=..., respect_limits=True)``, the camera frame = e_g)."""
    identity = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (len(needle), 1))
    plan = policy.plan_from_camera(
        identity, start, needle, goal_depth_mm=depth_mm, check_grasp=False, psm={"regrasping_base": base}
    )
    ok = [j.all_reachable for j, s in zip(plan.joints, plan.success) if s]
    return {"success_rate": float(plan.success.mean()), "plans": len(ok), "all_reachable_share": float(np.mean(ok))}


def reachability(plan, start: np.ndarray) -> dict:
    """The plans' reachability from a port behind each start, and from one fixed port."""
    fixed = dvrk.base_behind(dvrk.average_pose(start))
    grasp = dvrk.inverse_kinematics(np.linalg.inv(dvrk.base_behind(np.r_[0, 0, 0, 1, 0, 0, 0])) @ np.eye(4))
    return {
        "grasping_arm_reachable": grasp.reachable,
        "grasping_arm_q": grasp.q.round(4).tolist(),
        "start": psm_joints.reachability(plan, lambda i: dvrk.base_behind(start[i])),
        "fixed": psm_joints.reachability(plan, fixed),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--margins", default="0,0.05,0.1,0.2")
    p.add_argument("--policy", default=None)
    p.add_argument("--testset", default=str(DEFAULT_TESTSET))
    p.add_argument("--substeps", type=int, default=20)
    p.add_argument("--budget-s", type=float, default=10.0)
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--limit", type=int, default=None, help="first N problems (a quick look)")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    episodes, _ = load_testset(args.testset)
    episodes = episodes.row(slice(args.limit))
    needle, start, goal = episode_poses(episodes)
    base = load_policy(args.policy)
    checker = host.HostChecker()  # measures distances; the margin does not enter
    rows, data = [], {"margins": {}}
    for m in (float(x) for x in args.margins.split(",")):
        policy = base.with_env(clearance_mm=m)
        gate = host.HostChecker(clearance_mm=m)
        valid = gate.clear_problems(needle, start, goal)
        entry = {"valid": len(valid), "substeps": RegraspEnv(policy.env_config).substeps}
        for shield in (False, True):
            plan = policy.plan(needle[valid], start[valid], goal[valid], check_grasp=False, shield=shield)
            name = "shielded" if shield else "bare"
            clear = [
                checker.path_clearance(needle[valid][j], plan.poses[j][: plan.steps[j] + 1], args.substeps)
                for j in np.nonzero(plan.success)[0]
            ]
            entry[name] = {"success_rate": float(plan.success.mean()), "clearance": clearance_stats(clear)}
            if shield and m == 0.0:
                data["reachability"] = reachability(plan, start[valid])
        options = {"planner": dataclasses.asdict(PlannerConfig(budget_s=args.budget_s)), "clearance_mm": m, "seed": 0}
        solved = {i: r or {} for i, r in plan_all(episodes, valid, options, args.workers, args.budget_s).items()}
        ok = [i for i in valid if solved.get(i, {}).get("solved")]
        clear = [checker.path_clearance(needle[i], np.asarray(solved[i]["poses"]), args.substeps) for i in ok]
        times = [solved[i]["plan_time_s"] for i in ok]
        entry["bitstar"] = {
            "success_rate": len(ok) / max(1, len(valid)),
            "plan_time_median_s": float(np.median(times)) if times else None,
            "clearance": clearance_stats(clear),
        }
        data["margins"][str(m)] = entry
        print(dumps({"clearance_mm": m, **entry}), flush=True)
        c = lambda e: e["clearance"]  # noqa: E731
        rows.append(
            f"| {m:g} | {entry['substeps']} | {entry['valid']} | {entry['bare']['success_rate']:.3f} | "
            f"{entry['shielded']['success_rate']:.3f} | {entry['bitstar']['success_rate']:.3f} | "
            + " | ".join(
                f"{c(entry[k]).get('p1_mm', float('nan')):.3f} / {c(entry[k]).get('median_mm', float('nan')):.3f}"
                f" ({c(entry[k]).get('penetrating', 0)})"
                for k in ("shielded", "bitstar")
            )
            + " |"
        )
    lines = [
        f"paper300, shipped policy and BIT* (R); clearance re-checked at {args.substeps} poses per step "
        "(CPU MuJoCo mj_geomDistance): 1st percentile / median of each path's smallest clearance, mm "
        "(paths that penetrate).",
        "",
        "| margin (mm) | env sub-steps | valid problems | policy bare | policy shielded | BIT* (R) | "
        "clearance, policy shielded | clearance, BIT* (R) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |",
        *rows,
    ]
    if "reachability" in data:
        r = data["reachability"]
        lines += ["", "Reachability of the shielded plans at margin 0 (dVRK PSM + LND joint limits):", ""]
        lines += [
            "| RCM placement | plans | whole path within limits | out-of-limit poses by joint | joint path, median |"
        ]
        lines += ["| --- | ---: | ---: | --- | --- |"]
        for name in ("start", "fixed"):
            x = r[name]
            jp = ", ".join(f"{k} {v:.2f}" for k, v in x["joint_path_median"].items())
            lines.append(
                f"| {name} | {x['plans']} | {x['all_reachable_share']:.3f} | {x['out_of_limit_poses_by_joint'] or '-'} | {jp} |"
            )
        # the reachability rows belong to margin 0: only when --margins holds it
        fixed = dvrk.base_behind(dvrk.average_pose(start))
        r["fixed, limit-aware shield"] = limit_aware(
            base.with_env(clearance_mm=0.0), needle, start, np.asarray(episodes.goal_depth) * 1e3, fixed
        )
        x = r["fixed, limit-aware shield"]
        lines.append(
            f"| fixed, limit-aware shield (success {x['success_rate']:.3f}) | {x['plans']} | {x['all_reachable_share']:.3f} | | |"
        )
    print("\n".join(lines))
    write_results(args.out, "clearance", lines, data)


if __name__ == "__main__":
    main()
