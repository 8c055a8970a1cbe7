"""``python -m regrasp_mjx.sweep``: a grid of training runs over the GPUs of a Ray cluster, resumable, one table.

Each grid point is one ``python -m regrasp_mjx.train`` run in ``OUT/<point>``, its Table I settings
(``--exploration a,b,c``) and seeds (``--seeds N``) trained side by side as one vmapped program
(learners in one program share a GPU far better than processes do; experiments/RESULTS.md). The
points are Ray tasks (:mod:`regrasp_mjx.core.jobs`), one per GPU at a time, or one per node at a time
without GPUs: on this machine's GPUs (Ray started here), or over a cluster's nodes with ``--address``
(or ``RAY_ADDRESS``; the sweep folder on a filesystem every node sees). A point whose node dies runs
again on another from its last checkpoint. A
point whose folder holds ``final_eval.json`` is done and skipped; one with a checkpoint resumes from
it; so a killed sweep started again with the same arguments goes on where it stopped (a different
grid in the same folder is refused). At the end, or with ``--report``, it writes ``sweep.md``,
``sweep.json`` and ``sweep.png``: per point and setting, the bare test success at the last epoch,
over the last 10 epochs, at the best epoch and of the exported policy (best on validation; bare and
shielded), the collision rate and path length at the last epoch, mean ± std over seeds: with
``--exploration ddpg_bc,targeted,mixed``, the paper's Table I.

    # Table I (the paper's three settings x 3 seeds at the paper's scale), one command:
    python -m regrasp_mjx.sweep --out runs/table1 --preset paper --exploration ddpg_bc,targeted,mixed \\
        --seeds 3 --demos runs/demos
    # a grid: 2 x 2 points, each 3 seeds, over the GPUs this machine has:
    python -m regrasp_mjx.sweep --out runs/bc --preset fast --seeds 3 \\
        --grid "bc_decay_epochs=0|30" --grid "critic_layer_norm=False|True"
    # the same over a Ray cluster's GPUs (docs/training.md: a cluster on SLURM)
    python -m regrasp_mjx.sweep --out /shared/runs/bc --preset fast --seeds 3 --address head:6379 \\
        --grid "bc_decay_epochs=0|30" --grid "critic_layer_norm=False|True"
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import itertools
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from regrasp_mjx.agents.ddpg_bc.config import make_config
from regrasp_mjx.core.atomic import output_folder_problem, write_figure, write_json, write_text
from regrasp_mjx.core.cluster import Cluster, add_options, check_options, connect
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.config_text import parse_overrides
from regrasp_mjx.core.host_loop import FolderInUse, folder_lock, run_command
from regrasp_mjx.core.jobs import Job, run_jobs
from regrasp_mjx.workflows import analysis
from regrasp_mjx.workflows.preflight import before_the_work, restart_args
from regrasp_mjx.world.sampling import DEFAULT_TESTSET

FORMAT = "regrasp_mjx.sweep"


def parse_grid(items: list[str]) -> list[tuple[str, list[Any]]]:
    """``["k=v1|v2", ...]`` to ``[(k, [v1, v2]), ...]``; values as Python literals, else strings."""
    grid = []
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise ConfigError(f"--grid {item!r} is not accepted: KEY=V1|V2|... (e.g. bc_decay_epochs=0|100)")
        if key in (k for k, _ in grid):
            raise ConfigError(f"--grid {key} is given twice; list all its values in one --grid")
        parsed = []
        for v in values.split("|"):
            try:
                parsed.append(ast.literal_eval(v.strip()))
            except (ValueError, SyntaxError):
                parsed.append(v.strip())
        if len(set(map(repr, parsed))) != len(parsed):
            raise ConfigError(f"--grid {item!r} is not accepted: a value is listed twice")
        grid.append((key, parsed))
    return grid


def points(grid: list[tuple[str, list[Any]]]) -> list[dict[str, Any]]:
    """The grid's points in order (the last key varies fastest); one empty point for no grid."""
    keys = [k for k, _ in grid]
    return [dict(zip(keys, combo)) for combo in itertools.product(*(v for _, v in grid))]


def point_name(index: int, point: dict[str, Any]) -> str:
    slug = "_".join(f"{k}={v!r}" for k, v in point.items()) or "run"
    return f"{index:02d}_" + re.sub(r"[^A-Za-z0-9_.=+-]", "", slug.replace(" ", ""))[:80]


def train_args(args: argparse.Namespace, point: dict[str, Any], out: Path) -> list[str]:
    """The ``python -m regrasp_mjx.train`` arguments of one point (``--resume`` added by the caller)."""
    argv = ["--preset", args.preset, "--exploration", args.exploration, "--learner", args.learner]
    argv += ["--seeds", str(args.seeds), "--seed", str(args.seed), "--out", str(out), "--quiet"]
    if args.demos:
        argv += ["--demos", args.demos]
    if args.testset:
        argv += ["--testset", args.testset]
    for item in args.set:
        argv += ["--set", item]
    for key, value in point.items():
        argv += ["--set", f"{key}={value!r}"]
    return argv


def command(folder: Path, argv: list[str]) -> list[str]:
    """The process that trains one point: resuming from its checkpoint when it has one (a point that
    never reached a checkpoint starts anew, its partial outputs cleared)."""
    return [sys.executable, "-m", "regrasp_mjx.train", *argv, *restart_args(folder)]


def status(folder: Path) -> str:
    """``done`` (final evaluation written), ``resume`` (a checkpoint) or ``new``."""
    if (folder / "final_eval.json").is_file():
        return "done"
    if (folder / "checkpoint" / "meta.json").is_file():
        return "resume"
    return "new"


def check_manifest(out: Path, manifest: dict[str, Any]) -> None:
    path = out / "sweep.json"
    if path.is_file():
        saved = json.loads(path.read_text()).get("manifest")
        if saved != manifest:
            raise ConfigError(
                f"{out} holds a sweep with other arguments ({path}); start it again with the same "
                "arguments to resume, or use another --out"
            )


def run_all(out: Path, names: list[str], argvs: list[list[str]], cluster: Cluster, log) -> dict[str, dict]:
    """Runs the points not done yet, one per GPU at a time; returns each started point's record
    (:func:`regrasp_mjx.core.jobs.run_jobs`: exit code, wall time, node)."""
    jobs = [
        Job(
            name,
            "points",
            lambda folder=out / name, argv=argv: command(folder, argv)[1:],
            out / name / "final_eval.json",
            out / name / "sweep_stdout.txt",
        )
        for name, argv in zip(names, argvs)
    ]
    return run_jobs(jobs, cluster, log)


def report(out: Path, names: list[str], grid_points: list[dict[str, Any]]) -> tuple[list[str], list[dict]]:
    """``sweep.md`` lines (and the figure) from the points' logs; points without a log are listed as such."""

    rows, curves = [], []
    for name, point in zip(names, grid_points):
        folder = out / name
        if not (folder / "log.jsonl").is_file():
            rows.append({"point": name, "overrides": point, "setting": None, "missing": True})
            continue
        finals = []
        if (folder / "final_eval.json").is_file():
            finals = json.loads((folder / "final_eval.json").read_text()).get("seeds", [])
        for setting in analysis.settings_in_log(folder / "log.jsonl") or [None]:
            log = analysis.read_log(folder / "log.jsonl", setting)
            summary = analysis.summarize_setting(log, [m for m in finals if m.get("setting") == setting])
            rows.append({"point": name, "overrides": point, "setting": setting, **summary})
            curves.append((f"{name}{' ' + setting if setting else ''}", *analysis.seed_band(log, "test.success_rate")))
    ms = analysis.mean_std
    lines = [
        "Bare policy (no shield) on the run's test set; mean ± std over seeds.",
        "",
        "| point | overrides | setting | epochs | last epoch | mean of last 10 | best epoch "
        "| exported (best on validation) | exported, shielded | collision, last | path (mm), last |",
        "| --- | --- | --- | ---: | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        over = ", ".join(f"{k}={v!r}" for k, v in r["overrides"].items()) or "-"
        if r.get("missing"):
            lines.append(f"| {r['point']} | {over} | - | - | not run yet | | | | | | |")
            continue
        lines.append(
            f"| {r['point']} | {over} | {r['setting'] or '-'} | {r['epochs']} | {ms(r['last'])} | {ms(r['last10'])} | "
            f"{ms(r['best'])} | {ms(r['exported'])} | {ms(r['exported_shielded'])} | {ms(r['collision_last'])} | "
            f"{ms(r['path_last'])} |"
        )
    if curves:
        import matplotlib.pyplot as plt  # optional (the analysis extra): only where a sweep has curves to draw

        fig, ax = plt.subplots(figsize=(8, 4.5))
        for label, epochs, succ in curves:
            (line,) = ax.plot(epochs, succ.mean(0), label=label, lw=1.2)
            ax.fill_between(epochs, succ.min(0), succ.max(0), color=line.get_color(), alpha=0.2, lw=0)
        ax.set_xlabel("epoch")
        ax.set_ylabel("test success rate (bare), mean and range over seeds")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        write_figure(out / "sweep.png", fig, dpi=120)
        plt.close(fig)
    write_text(out / "sweep.md", "\n".join(lines) + "\n")
    return lines, rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m regrasp_mjx.sweep",
        description=__doc__.splitlines()[0],
        epilog="Every other option is passed to each run (python -m regrasp_mjx.train --help).",
    )
    p.add_argument("--out", required=True, help="sweep folder: one run folder per point, sweep.md/json/png")
    p.add_argument("--preset", default="paper", help="training preset of every point (default paper)")
    p.add_argument("--exploration", default="mixed", help="Table I setting(s), comma-separated, one program")
    p.add_argument("--learner", default="ours", choices=("ours", "paper"))
    p.add_argument("--seeds", type=int, default=3, help="seeds per setting and point (one program)")
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1|V2",
        help="a config field and its values (repeatable: the points are the product)",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a field fixed for every point")
    p.add_argument(
        "--demos", default=None, help="a demonstration folder every point shares (default: each builds its own)"
    )
    p.add_argument("--testset", default=None, help="test set .npz (default paper300)")
    add_options(p, "points")
    p.add_argument("--report", action="store_true", help="only write the table and figure from what has run")
    p.add_argument("--dry-run", action="store_true", help="print each point's command and status, run nothing")
    args = p.parse_args(argv)
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    if problem := output_folder_problem(args.out):
        p.error(problem)
    out = Path(args.out)
    try:
        if args.seeds < 1:
            raise ConfigError(f"--seeds {args.seeds} is not accepted: at least 1")
        if check_options(args.address, args.gpus):  # before anything runs
            # on a cluster the points run on other nodes, from other folders: paths that name the same files
            out = out.resolve()
            args.demos, args.testset = (
                str(Path(x).resolve()) if x and Path(x).exists() else x for x in (args.demos, args.testset)
            )
        grid = parse_grid(args.grid)
        grid_points = points(grid)
        fixed = parse_overrides(args.set)
        for point in grid_points:  # every point's config, test set and demonstrations checked before anything runs
            cfg = make_config(args.preset, args.exploration, args.learner, **{**fixed, **point})
            if problem := before_the_work(cfg, args.testset or str(DEFAULT_TESTSET), args.demos):
                raise ConfigError(problem)
        names = [point_name(i, pt) for i, pt in enumerate(grid_points)]
        argvs = [train_args(args, pt, out / n) for n, pt in zip(names, grid_points)]
        manifest = {
            "preset": args.preset,
            "exploration": args.exploration,
            "learner": args.learner,
            "seeds": args.seeds,
            "seed": args.seed,
            "grid": [[k, [repr(v) for v in vs]] for k, vs in grid],
            "set": args.set,
            "demos": args.demos,
            "testset": args.testset,
        }
        check_manifest(out, manifest)
        if args.report and not any((out / name / "log.jsonl").is_file() for name in names):
            raise ConfigError(
                f"--report: no point of this sweep in {out} has a log yet, the report would be empty; accepted: "
                "the --out and arguments of a sweep that has run"
            )
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.dry_run:
        for name, a in zip(names, argvs):
            print(f"[{status(out / name)}] python {' '.join(command(out / name, a)[1:])}")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    record = {"format": FORMAT, "manifest": manifest, "points": dict(zip(names, grid_points))}
    runs = {}
    # --report reads what has run, also while a sweep runs; a sweep holds the folder until its table is written
    lock = contextlib.nullcontext() if args.report else folder_lock(out)
    try:
        with lock:  # a second sweep into this folder is refused while this one lives
            write_json(out / "sweep.json", record, indent=2)
            if not args.report:
                with connect(args.address, args.gpus) as cluster:
                    runs = run_all(out, names, argvs, cluster, log)
            codes = {name: r["exit"] for name, r in runs.items()}
            lines, rows = report(out, names, grid_points)
            record["results"] = rows
            record["exit_codes"] = codes
            record["nodes"] = {name: r["node"] for name, r in runs.items()}  # where each point ran (Ray's node id)
            write_json(out / "sweep.json", json.loads(json.dumps(record, default=_jsonable)), indent=2)
    except (ConfigError, FolderInUse) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    log("\n".join(lines))
    failed = [n for n, c in codes.items() if c != 0]
    if failed:
        print(f"error: {len(failed)} point(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return repr(x)


if __name__ == "__main__":
    sys.exit(run_command(main, "run the same command again to resume: finished points are kept"))
