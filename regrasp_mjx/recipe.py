"""``python -m regrasp_mjx.recipe NAME --out DIR``: a shipped policy's whole recipe, one command.

    python -m regrasp_mjx.recipe default --out runs/default                 # the shipped default
    python -m regrasp_mjx.recipe default --out runs/r4 --set env.scene.needle_radius_mm=4.0
    python -m regrasp_mjx.recipe general --out runs/general --gpus 0,1
    python -m regrasp_mjx.recipe default --out /shared/runs/default --address head:6379  # a Ray cluster
    python -m regrasp_mjx.recipe --list                                      # the recipes, as data

Every stage of the recipe (:mod:`regrasp_mjx.workflows.recipes`: demonstrations, teachers, students, the
choice on validation problems of their own seed, the closed loop's settings, the exported policy's
robustness table) is a job, a command of this package run as its own process, submitted as a Ray
task (:mod:`regrasp_mjx.core.jobs`): over every local GPU with Ray started here (side by side on one
where their memory shares fit), one at a time without a GPU, or over a cluster's nodes with
``--address`` (or ``RAY_ADDRESS``; the folder on a filesystem every node sees). A finished job is skipped and an unfinished one resumes (a teacher run from
its checkpoint, the demonstrations from the plans made so far, a student or a table anew), so a
killed recipe started again with the same arguments goes on; other arguments in the same folder are
refused. Writes ``DIR/policy`` (the chosen network, its closed-loop settings, and the recipe, its
``--set`` overrides and the commit in ``policy.json``), ``DIR/selection.md``/``.json``,
``DIR/robustness.md``/``.json`` (on GPUs joined from parts run side by side in ``DIR/report/``),
``DIR/recipe.json`` (the arguments and each job's wall time) and each job's output in ``DIR/logs/``.

With GPUs, precompile jobs run beside the teachers: each later stage's programs once on untrained
networks of the right shapes (``DIR/precompile/``: one distillation iteration per student variant,
one selection candidate, each report part), so the students, candidates and report parts load their
programs from the compilation cache instead of compiling them after the teachers (on one H100 those
compiles were about 5 of the recipe's 18 minutes). They save time only: one that fails fails nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from regrasp_mjx.core.atomic import dumps, output_folder_problem, write_json, write_results
from regrasp_mjx.core.cluster import add_options, check_options, connect, local_gpus
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.host_loop import FolderInUse, folder_lock, run_command
from regrasp_mjx.core.jobs import run_jobs
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.selection import closed_loop_markdown, closed_loop_settings, parse_noises, score
from regrasp_mjx.workflows import recipes
from regrasp_mjx.workflows.recipe_jobs import Plan
from regrasp_mjx.workflows.recipes import RECIPES
from regrasp_mjx.world.testsets import make_testset

FORMAT = "regrasp_mjx.recipe"
STAGES = ("demos", "precompile", "teachers", "students", "selection", "choose", "report")  # the jobs' stages, in order


def choose(plan: Plan, log) -> None:
    """Scores the candidates, tunes the winner's closed loop, exports ``out/policy``."""
    sel = plan.recipe.selection
    scores = {}
    for name in plan.candidates():
        table = json.loads((plan.out / "select" / f"{name}.json").read_text())["tables"][0]
        scores[name] = score(table["rows"], sel.rule)
    winner = max(scores, key=scores.get)  # the first of equals, in the recipe's order
    folder = plan.candidates()[winner][0]
    log(f"candidates: {', '.join(f'{n} {v:.4f}' for n, v in scores.items())}; chosen: {winner}")
    policy = load_policy(folder)
    noises = parse_noises(sel.loop_noises)
    episodes = make_testset(sel.loop_n, sel.loop_seed, policy.env_config)
    rows, best = closed_loop_settings(
        policy,
        episodes,
        noises,
        sel.loop_warmups,
        sel.loop_stops,
        log=lambda row: log(dumps(row)),
        looks=sel.loop_looks,
    )
    chosen_on = (
        f"fused closed loop at noise {sel.loop_noises} on {sel.loop_n} validation problems (seed {sel.loop_seed}), "
        f"recipe {plan.recipe.name}"
    )
    provenance = {
        "name": plan.recipe.name,
        "overrides": plan.items,
        "commit": commit(),
        "recipe": dataclasses.asdict(plan.recipe),
        "candidate": winner,
        "scores": scores,
        "score_rule": [list(x) for x in sel.rule],
    }
    export(folder, plan.out / "policy", best, chosen_on, provenance)
    lines = [
        f"Recipe {plan.recipe.name}, overrides {plan.items or 'none'}; candidates on {sel.n} validation problems "
        f"(seed {sel.seed}), score = mean success over {', '.join(f'{m} {c}' for m, c in sel.rule)}.",
        "",
        "| candidate | score |",
        "| --- | ---: |",
        *(f"| {'**' + n + '**' if n == winner else n} | {v:.4f} |" for n, v in scores.items()),
        "",
        f"Closed loop of {winner} on {sel.loop_n} other validation problems (seed {sel.loop_seed}):",
        "",
        *closed_loop_markdown(rows, best, noises),
    ]
    write_results(plan.out, "selection", lines, {"scores": scores, "chosen": winner, "closed_loop": rows, "best": best})
    log("\n".join(lines))


def export(source: Path, dest: Path, loop: dict[str, Any], chosen_on: str, provenance: dict[str, Any]) -> None:
    """Copies the policy in ``source`` to ``dest`` (whole or not at all) with its closed-loop
    settings and the recipe's provenance in ``policy.json``."""
    contract = json.loads((source / "policy.json").read_text())
    contract["closed_loop"] = {
        "stop_tolerance": loop["stop_tolerance"],
        "warmup_frames": loop["warmup_frames"],
        "look_frames": loop.get("look_frames", 0),
        "chosen_on": chosen_on,
    }
    contract.setdefault("training", {})["recipe"] = provenance
    partial = dest.with_name(dest.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    shutil.copy2(source / "policy.npz", partial / "policy.npz")
    write_json(partial / "policy.json", contract)
    shutil.rmtree(dest, ignore_errors=True)
    os.replace(partial, dest)


def commit() -> dict[str, Any]:
    """The package's git commit and whether its tree had changes (nulls outside a checkout)."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=30)
        if head.returncode != 0:
            return {"commit": None, "dirty": None}
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=30,
        )
        return {"commit": head.stdout.strip(), "dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def check_manifest(out: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    """The folder's record (new, or the earlier one of the same recipe and overrides)."""
    path = out / "recipe.json"
    if not path.is_file():
        return {"format": FORMAT, **manifest, "runs": []}
    record = json.loads(path.read_text())
    if {k: record.get(k) for k in manifest} != manifest:
        raise ConfigError(
            f"{out} holds recipe {record.get('recipe')} with overrides {record.get('set')}; accepted: the same "
            "recipe and --set to resume it, or another --out"
        )
    return record


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.recipe", description=__doc__.splitlines()[0])
    p.add_argument("name", nargs="?", help=f"the recipe: one of {', '.join(RECIPES)}")
    p.add_argument("--out", help="recipe folder (resumed when it holds this recipe)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a setting for every stage with it")
    add_options(p, "jobs")
    p.add_argument(
        "--workers", type=int, default=max(1, (os.cpu_count() or 2) - 1), help="planner processes for demonstrations"
    )
    p.add_argument(
        "--until", choices=STAGES, default=None, help="run the stages up to this one (default: all); later calls go on"
    )
    p.add_argument("--list", action="store_true", help="print every recipe's stages and exit")
    p.add_argument("--dry-run", action="store_true", help="print each job's command and whether it has finished")
    p.add_argument("--step", choices=("choose",), help=argparse.SUPPRESS)  # the job that chooses and exports
    args = p.parse_args(argv)
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    if args.list:
        log("\n".join(recipes.render_docs()))
        return 0
    if args.name not in RECIPES:
        p.error(f"recipe {args.name!r} is not accepted: one of {', '.join(RECIPES)}")
    if not args.out:
        p.error("--out is required: the recipe's folder")
    if args.workers < 1:
        p.error(f"--workers {args.workers} is not accepted: at least 1")
    out = Path(args.out)
    if problem := output_folder_problem(out):
        p.error(problem)
    try:
        address = check_options(args.address, args.gpus)
        if address:  # on a cluster the jobs run on other nodes, from other folders: a path that names the same files
            out = out.resolve()
        if args.step == "choose":
            choose(Plan(RECIPES[args.name], out, args.set, args.workers), log)
            return 0
        if args.dry_run:  # on this machine: its GPUs as nvidia-smi lists them (Ray not started)
            if address:
                with connect(address) as cluster:
                    gpus = cluster.gpus > 0
            else:
                gpus = bool(local_gpus(args.gpus))
            for j in jobs_until(Plan(RECIPES[args.name], out, args.set, args.workers, gpus=gpus), args.until):
                log(f"[{'finished' if j.done() else 'to run'}] {j.name}: python {shlex.join(j.argv())}")
            return 0
        Plan(RECIPES[args.name], out, args.set, args.workers)  # the recipe and --set checked before Ray starts
        with folder_lock(out), contextlib.ExitStack() as stack:
            record = check_manifest(out, {"recipe": args.name, "set": args.set})  # other arguments: before Ray
            cluster = stack.enter_context(connect(address, args.gpus))
            plan = Plan(RECIPES[args.name], out, args.set, args.workers, gpus=cluster.gpus > 0)
            jobs = jobs_until(plan, args.until)
            run = {"started": time.strftime("%Y-%m-%dT%H:%M:%S"), "cluster": cluster.describe(), "jobs": {}}
            record["runs"].append(run)
            write_json(out / "recipe.json", record)
            plan.prepare()
            t0 = time.perf_counter()

            def keep(jobs_so_far: dict[str, dict]) -> None:  # after every job: a killed recipe keeps its times
                run["jobs"], run["wall_s"] = dict(jobs_so_far), time.perf_counter() - t0
                write_json(out / "recipe.json", record)

            keep(run_jobs(jobs, cluster, log, on_end=keep))
    except (ConfigError, FolderInUse) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    code = summary(out, run, log)
    if code == 0 and args.until and args.until != STAGES[-1]:
        log(f"the stages up to {args.until} have finished; the same command without --until goes on from there")
    return code


def jobs_until(plan: Plan, until: str | None) -> list:
    """The plan's jobs up to the stage ``until`` (all for None); a precompile job whose jobs are
    cut runs for the next call."""
    jobs = plan.jobs()
    if until:
        jobs = [j for j in jobs if STAGES.index(j.stage) <= STAGES.index(until)]
        kept = {j.name for j in jobs}
        jobs = [dataclasses.replace(j, helps=tuple(h for h in j.helps if h in kept)) for j in jobs]
    return jobs


def summary(out: Path, run: dict[str, Any], log) -> int:
    """Per stage: the jobs this call ran and their wall time; the exported policy; exit status."""
    stages: dict[str, list[float]] = {}
    for r in run["jobs"].values():
        stages.setdefault(r["stage"], []).append(r["wall_s"])
    log(
        f"recipe wall {run['wall_s']:.0f} s; "
        + "; ".join(f"{s} {len(w)} job(s), longest {max(w):.0f} s" for s, w in stages.items())
    )
    failed = [n for n, r in run["jobs"].items() if r["exit"] != 0 and r["stage"] != "precompile"]
    missed = [n for n, r in run["jobs"].items() if r["exit"] not in (0, "stopped") and r["stage"] == "precompile"]
    if missed:
        log(
            f"{len(missed)} precompile job(s) did not finish ({', '.join(missed)}): "
            "the jobs they help compiled their own"
        )
    if failed:
        print(
            f"error: {len(failed)} job(s) did not finish: {', '.join(failed)}; their output is in {out / 'logs'}; "
            "run the same command again to resume",
            file=sys.stderr,
        )
        return 1
    if (out / "selection.json").is_file() and (out / "robustness.json").is_file():
        log(
            f"exported {out / 'policy'}; its robustness table: {out / 'robustness.md'}; "
            f"the choice: {out / 'selection.md'}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "run the same command again to resume: finished jobs are kept"))
