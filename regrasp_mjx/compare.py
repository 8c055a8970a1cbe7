"""``python -m regrasp_mjx.compare``: several policies side by side, bare and shielded, or as robustness tables.

    python -m regrasp_mjx.compare --policy default --policy student=runs/x/policy --heldout 3000:2022 --out OUT
    python -m regrasp_mjx.compare --policy general --policy default --out OUT --name general
    python -m regrasp_mjx.compare --robustness --out experiments/results/robustness     # every shipped policy
    python -m regrasp_mjx.compare --robustness --merge OUT/part0.json OUT/part1.json --out OUT

A policy is ``NAME=FOLDER`` (an empty FOLDER: the shipped default) or a shipped name alone; the
default is every shipped policy. Each is planned through ``Policy.plan``, as deployed, on its own
test sets (paper300 for a paper-task policy; general1000, then paper300, for a general one; the
robustness table: the first only) unless ``--testset`` names them, and on problems drawn here from
``--heldout N:SEED`` with the policy's task: validation problems of their own seed. With
``--no-testset`` only those: a policy is chosen without touching a test set. ``--env KEY=VALUE``
plans every policy in a changed environment (``Policy.with_env``); with a clearance margin the
problems whose start or goal already lies within it are left out (``robustness.clear_problems``).

Without ``--robustness``: success, collision and time-out rates, path length and steps, bare (the
network alone) and shielded; for a general policy on general1000 also its bare success by needle
radius and by goal angle alpha*, and in the JSON each problem's bare outcome (the heat map of
``notebooks/04_policy.ipynb``). With it: the robustness table of each policy
(``regrasp_mjx.inference.robustness``), its hash recorded, written after each policy so a cut run keeps them;
``--merge`` joins such tables from runs made side by side. Writes ``OUT/NAME.md`` and ``NAME.json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from regrasp_mjx.core.atomic import dumps, machine, output_folder_problem, write_results
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.config_text import parse_overrides
from regrasp_mjx.core.host_loop import release_programs, run_command
from regrasp_mjx.envs.rollout import summarize
from regrasp_mjx.inference import robustness, robustness_report
from regrasp_mjx.inference.policy import PolicyError, load_policy, shipped_policies
from regrasp_mjx.inference.queries import PoseError
from regrasp_mjx.inference.testset_plans import plan_testset
from regrasp_mjx.workflows.analysis import markdown_table
from regrasp_mjx.world.sampling import TestsetError, load_testset
from regrasp_mjx.world.testsets import make_testset

R_BINS_MM = (4.0, 6.0, 8.0, 10.0, 12.0)
ALPHA_BINS_RAD = tuple(10 * math.pi / 9 + k * (math.pi / 3) / 4 for k in range(5))  # [10pi/9, 13pi/9] in 4
OUTCOME_COLUMNS = [
    ("policy", "policy", ""),
    ("network", "network", ""),
    ("testset", "problems", ""),
    ("rollout", "rollout", ""),
    ("success_rate", "success", ".3f"),
    ("collision_rate", "collision", ".3f"),
    ("time_out_rate", "time-out", ".3f"),
    ("path_length_mm", "path (mm)", ".2f"),
    ("steps", "steps", ".2f"),
]


def problem_sets(policy, testsets: list[str], heldout: list[tuple[int, int]]) -> Iterator[tuple[str, Any]]:
    """The named problem sets one policy plans, each made when it is reached: ``testsets`` (None:
    its own), then the drawn ones, each without the problems that already break the policy's
    clearance margin."""
    if testsets is None:
        testsets = ["general1000", "paper300"] if policy.general else ["paper300"]
    for name in testsets:
        yield name, _keeping_margin(policy, load_testset(name)[0])
    for n, seed in heldout:
        yield f"held-out {n} (seed {seed})", _keeping_margin(policy, _drawn(n, seed, policy.env_config))


def _keeping_margin(policy, episodes):
    """The problems whose start and goal keep the policy's clearance margin (all without one)."""
    if policy.env_config.clearance_mm > 0:
        return episodes.row(robustness.clear_problems(policy.env_config, episodes))
    return episodes


@functools.lru_cache(maxsize=8)
def _drawn(n: int, seed: int, env_config) -> Any:
    """Held-out problems, drawn once for every policy of the same task and scene."""
    return make_testset(n, seed, env_config)


def binned(success: np.ndarray, values: np.ndarray, edges) -> list[float]:
    idx = np.clip(np.digitize(values, edges) - 1, 0, len(edges) - 2)
    return [float(success[idx == b].mean()) if np.any(idx == b) else float("nan") for b in range(len(edges) - 1)]


def breakdown(episodes, per_problem: dict[str, np.ndarray]) -> tuple[dict, list[str]]:
    """Bare success on general1000 by needle radius and by goal angle, mean over the general policies."""
    radius_mm, alpha = np.asarray(episodes.needle_radius) * 1e3, np.asarray(episodes.goal_grasp)[:, 0]
    success = np.mean(list(per_problem.values()), axis=0)
    data, lines = {}, []
    for key, values, edges, label, unit in (
        ("by_radius_mm", radius_mm, R_BINS_MM, "needle radius", lambda x: f"{x:g}"),
        ("by_alpha_rad", alpha, ALPHA_BINS_RAD, "goal angle alpha* (degrees)", lambda x: f"{math.degrees(x):.0f}"),
    ):
        rates, counts = binned(success, values, edges), np.histogram(values, edges)[0].tolist()
        data[key] = [edges, rates, counts]
        bins = [f"{unit(a)}-{unit(b)}" for a, b in zip(edges[:-1], edges[1:])]
        lines += ["", f"Bare success on general1000 by {label}, mean over {', '.join(per_problem)}:", ""]
        lines += ["| bin | " + " | ".join(bins) + " |", "| --- |" + " ---: |" * len(bins)]
        lines += ["| success | " + " | ".join(f"{v:.3f}" for v in rates) + " |"]
        lines += ["| problems | " + " | ".join(map(str, counts)) + " |"]
    bare = {k: v.astype(int).tolist() for k, v in per_problem.items()}
    per = {"needle_radius_mm": radius_mm.tolist(), "goal_alpha_rad": alpha.tolist(), "bare_success": bare}
    return {"breakdown": data, "per_problem": per}, lines


def outcomes(policies: dict, args: argparse.Namespace, changes: dict) -> tuple[list[str], dict]:
    """Every policy bare and shielded on its problem sets: the table and the JSON's data."""
    rows, per_problem, general = [], {}, None
    for name, (folder, policy) in policies.items():
        network = (f"{policy.members} x " if policy.members > 1 else "") + "x".join(map(str, policy.hidden))
        for sname, episodes in problem_sets(policy, args.testset, args.heldout):
            for shield in (False, True):
                plan = plan_testset(policy, episodes, shield)
                row = {"policy": name, "folder": folder, "network": network, "testset": sname, "env": changes}
                rows.append({**row, **summarize(plan, "shielded" if shield else "bare")})
                print(dumps(rows[-1]), flush=True)
                if sname == "general1000" and policy.general and not shield:
                    per_problem[name], general = np.asarray(plan.success, bool), episodes
        release_programs()  # policies of other shapes compile programs of their own
    where = machine()
    lines = [f"Machine: {where}; planned through Policy.plan" + (f"; environment {changes}" if changes else ""), ""]
    lines.append(markdown_table(rows, OUTCOME_COLUMNS))
    data, more = breakdown(general, per_problem) if per_problem else ({}, [])
    return lines + more, {"machine": where, "rows": rows, **data}


def tables(policies: dict, args: argparse.Namespace) -> None:
    """Each policy's robustness table on its first problem set, the files rewritten after each."""
    modes = tuple(args.modes.split(","))
    wanted = args.conditions.split(",") if args.conditions else None
    everything = robustness.ALL_CONDITIONS if wanted is None else robustness.NAMED_CONDITIONS
    conditions = tuple(c for c in everything if wanted is None or c.name in wanted)
    meta = {"machine": machine(), "seed": args.seed, "modes": modes}
    found, lines = [], [f"Machine: {meta['machine']}; shielded; seed {args.seed}.", ""]
    for name, (folder, policy) in policies.items():
        problems, episodes = next(problem_sets(policy, args.testset, args.heldout))  # the first only
        print(f"{name} ({folder}) on {problems}", flush=True)
        t0 = time.perf_counter()
        rows = robustness.table(policy, episodes, modes, args.seed, conditions, log=print)
        who = {"policy": name, "folder": folder, "policy_hash": robustness.policy_hash(folder), "hidden": policy.hidden}
        run = {"problems": problems, "wall_s": time.perf_counter() - t0, "machine": meta["machine"], "seed": args.seed}
        found.append({**who, **run, "rows": rows})
        lines += robustness_report.title(found[-1]) + robustness_report.markdown(rows, modes) + [""]
        write_results(args.out, args.name, lines, {**meta, "tables": found})
        release_programs()
    print("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.compare", description=__doc__.splitlines()[0])
    p.add_argument("--policy", action="append", metavar="NAME=FOLDER", help="repeatable; default: every shipped one")
    p.add_argument("--testset", action="append", help="a shipped name or .npz (repeatable; default: each policy's own)")
    p.add_argument("--heldout", action="append", default=[], metavar="N:SEED", help="problems drawn here (repeatable)")
    p.add_argument("--no-testset", action="store_true", help="only the --heldout problems (to choose a policy)")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE", help="e.g. clearance_mm=0.1")
    p.add_argument("--robustness", action="store_true", help="each policy's robustness table instead")
    p.add_argument("--modes", default=",".join(robustness.MODES), help="with --robustness: comma-separated modes")
    p.add_argument(
        "--conditions",
        default=None,
        help="with --robustness: comma-separated condition names (default: all but the fitted camera's, "
        "'camera: rendered', which is asked for by name)",
    )
    p.add_argument("--seed", type=int, default=0, help="with --robustness: seed of the needle-estimate noise")
    p.add_argument("--merge", nargs="+", metavar="JSON", help="with --robustness: only join earlier runs' tables")
    p.add_argument("--out", default=None, help="folder for NAME.md and NAME.json (default: print only)")
    p.add_argument("--name", default=None, help="file name (default: compare, or robustness)")
    args = p.parse_args(argv)
    args.name = args.name or ("robustness" if args.robustness else "compare")
    if Path(args.name).name != args.name or args.name in (".", ".."):  # OUT/NAME.md stays in --out
        p.error(f"--name {args.name} is not accepted: a file name without a folder (no '/'), e.g. general")
    for spec in args.policy or ():
        if spec.startswith("="):
            p.error(f"--policy {spec} is not accepted: NAME=FOLDER with a NAME, or a shipped name alone")
    if args.out is not None and (problem := output_folder_problem(args.out)):  # before any work: minutes
        p.error(problem)
    for item in args.heldout:
        n, _, seed = item.partition(":")
        if not (n.isdigit() and int(n) >= 1 and seed.lstrip("-").isdigit()):
            p.error(f"--heldout {item} is not accepted: N:SEED, N >= 1 problems drawn from the integer SEED")
    args.heldout = [tuple(int(x) for x in item.split(":")) for item in args.heldout]
    if args.no_testset:
        if not args.heldout:
            p.error("--no-testset is not accepted without --heldout: no problems would be left")
        args.testset = []
    if not args.robustness:
        chosen = {
            "--modes": args.modes != ",".join(robustness.MODES),
            "--conditions": args.conditions,
            "--merge": args.merge,
        }
        given = [option for option, value in chosen.items() if value]
        if given:
            p.error(f"{', '.join(given)} is not accepted without --robustness (it selects the robustness table's rows)")
    if set(args.modes.split(",")) - set(robustness.MODES):
        p.error(f"--modes {args.modes} is not accepted: comma-separated of {list(robustness.MODES)}")
    names = [c.name for c in robustness.NAMED_CONDITIONS]
    if args.conditions and set(args.conditions.split(",")) - set(names):
        p.error(f"--conditions {args.conditions} is not accepted: comma-separated of {names}")
    for c in robustness.NAMED_CONDITIONS:  # a fitted preset's file read now, not after minutes of other rows
        if args.conditions and c.name in args.conditions.split(","):
            try:
                c.resolved_camera()
            except ConfigError as err:
                p.error(f"--conditions {c.name!r}: {err}")
    if args.merge:
        if not args.robustness:
            p.error("--merge is not accepted without --robustness")
        try:
            tables_ = robustness_report.merge([json.loads(Path(path).read_text()) for path in args.merge])
        except (OSError, ValueError, KeyError) as err:  # missing, not JSON, no tables; ConfigError: mismatched
            why = f"{type(err).__name__}: {err}"
            print(
                f"error: --merge {' '.join(args.merge)}: {why}; accepted: table files this command wrote",
                file=sys.stderr,
            )
            return 2
        lines = [
            x
            for t in tables_
            for x in robustness_report.title(t, machine=True) + robustness_report.markdown(t["rows"]) + [""]
        ]
        print("\n".join(lines))
        write_results(args.out, args.name, lines, {"tables": tables_})
        return 0
    try:
        changes = parse_overrides(args.env)
        specs = [s.partition("=")[::2] if "=" in s else (s, s) for s in args.policy or shipped_policies()]
        policies = {}
        for name, folder in specs:
            policy = load_policy(folder or None)
            policies[name] = (folder or "default", policy.with_env(**changes) if changes else policy)
        if args.robustness:
            tables(policies, args)
            return 0
        lines, data = outcomes(policies, args, changes)
    # PoseError: a test set of needles or goal grasps the policy was not trained for
    except (PolicyError, TestsetError, ConfigError, PoseError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    write_results(args.out, args.name, lines, data)
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "the files in --out hold the policies finished so far: run the same command again"))
