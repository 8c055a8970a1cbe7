"""The paper's Table II for the sampling planners and the straight-line baseline.

Every planner and direction plans each problem of the committed test set once, in parallel worker
processes (one plan per process at a time, so each planning time is single-threaded). Planning
stops at the first exact solution or the budget; found paths are shortcut for ``simplify_s``
inside the timed budget. Reported per row: success rate, planning time (mean and median over
successes, and the mean over all problems with failures counted at their full time), path length
(mean over successes, mm). Written as markdown and CSV under ``--out``.

    python experiments/planners.py --budget-s 10 --workers 16 --out experiments/results
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

from regrasp_mjx.core.atomic import dumps, machine, write_csv, write_text
from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.planning.ompl_planner import CHECKERS, PLANNERS, PlannerConfig
from regrasp_mjx.planning.pool import plan_all, summarize_plans
from regrasp_mjx.world.sampling import load_testset
from regrasp_mjx.world.scene import load_scene

SHORT = {"PRMstar": "PRM*", "RRTstar": "RRT*", "BFMTstar": "BFMT*", "BITstar": "BIT*", "RRTConnect": "RRT-Connect"}


def run_rows(episodes, rows, jaw_angle: float, budget: float, workers: int, seed: int, **planner) -> list[dict]:
    """Plans every clear problem once per row; ``planner``: further :class:`PlannerConfig` fields."""
    scene = SceneConfig(jaw_angle_deg=jaw_angle)
    valid = HostChecker(load_scene(scene)).clear_episodes(episodes)
    scene_fields = dataclasses.asdict(scene)
    out = []
    for method, planner_name, direction in rows:
        cfg = PlannerConfig(planner=planner_name, direction=direction, budget_s=budget, **planner)
        options = {"method": method, "planner": dataclasses.asdict(cfg), "scene": scene_fields, "seed": seed}
        t0 = time.perf_counter()
        results = plan_all(episodes, valid, options, workers, budget)
        name = "straight line" if method == "straight_line" else f"{SHORT[planner_name]} ({direction[0].upper()})"
        ompl = method == "ompl"
        row = {
            "algorithm": name + (", no shortcutting" if ompl and cfg.simplify_s == 0 else ""),
            "jaw_angle_deg": jaw_angle,
            "budget_s": budget if ompl else None,
            "simplify_s": cfg.simplify_s if ompl else None,
            "range_mm": cfg.rrt_range_mm if ompl and planner_name in ("RRTstar", "RRTConnect") else None,
            "checker": cfg.checker,
            **summarize_plans(list(results.values()), budget),
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        print(dumps(row), flush=True)
        out.append(row)
    return out


def _fmt(v, spec):
    return "–" if v is None else format(v, spec)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--testset", default="paper300", help="a shipped name (paper300, general1000) or an .npz")
    p.add_argument("--budget-s", type=float, default=10.0)
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--limit", type=int, default=None, help="first N problems only (a quick look)")
    p.add_argument("--wide-jaw-deg", type=float, default=35.0)
    p.add_argument("--out", default="experiments/results")
    p.add_argument(
        "--rows",
        default=None,
        help="only these rows at 20° jaws, e.g. 'straight_line,BITstar:reverse' (default: the straight line and "
        "every planner both ways, then the straight line and BIT* (R) at --wide-jaw-deg)",
    )
    p.add_argument("--name", default="planners", help="output file names NAME.md and NAME.csv")
    p.add_argument(
        "--checker",
        choices=CHECKERS,
        default=PlannerConfig.checker,
        help="collision checker: CPU MuJoCo, or the compiled capsule test, one call per motion (default %(default)s)",
    )
    p.add_argument(
        "--range-mm",
        type=float,
        default=PlannerConfig.rrt_range_mm,
        help="RRT* and RRT-Connect's longest extension, mm (default %(default)s)",
    )
    p.add_argument(
        "--simplify-s",
        type=float,
        default=PlannerConfig.simplify_s,
        help="shortcutting of a found path, s, inside the timed budget; 0 turns it off (default %(default)s)",
    )
    args = p.parse_args()
    episodes, meta = load_testset(args.testset)
    episodes = episodes.row(slice(args.limit))
    planners = [("ompl", pl, d) for pl in PLANNERS for d in ("forward", "reverse")]
    chosen = [("straight_line", "BITstar", "forward"), *planners]
    if args.rows:
        wanted = [r.strip() for r in args.rows.split(",")]
        chosen = [r for r in chosen if (r[0] if r[0] == "straight_line" else f"{r[1]}:{r[2]}") in wanted]
    tuned = {"rrt_range_mm": args.range_mm, "simplify_s": args.simplify_s, "checker": args.checker}
    rows = run_rows(episodes, chosen, 20.0, args.budget_s, args.workers, args.seed, **tuned)
    if not args.rows:
        rows += run_rows(
            episodes,
            [("straight_line", "BITstar", "forward"), ("ompl", "BITstar", "reverse")],
            args.wide_jaw_deg,
            args.budget_s,
            args.workers,
            args.seed,
            **tuned,
        )
    where = f"{machine(devices=False)}, {args.workers} planner processes"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / f"{args.name}.csv", list(rows[0]), [[r[k] for k in rows[0]] for r in rows])
    lines = [
        f"Test set `{args.testset}` ({len(episodes.needle_pos)} problems, seed {meta.get('seed')}); "
        f"budget {args.budget_s:g} s per plan, first solution + {args.simplify_s:g} s shortcutting; RRT range "
        f"{args.range_mm:g} mm; collision checker {args.checker}; {where}.",
        "",
        "| algorithm | jaws | success rate | planning time mean (s) | median (s) | mean incl. failures (s) | path length (mm) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['algorithm']} | {r['jaw_angle_deg']:g}° | {r['success_rate']:.3f} | "
            f"{_fmt(r['plan_time_mean_s'], '.4f')} | {_fmt(r['plan_time_median_s'], '.4f')} | "
            f"{r['plan_time_mean_all_s']:.4f} | {_fmt(r['path_length_mm'], '.2f')} |"
        )
    write_text(out / f"{args.name}.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
