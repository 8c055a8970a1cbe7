"""Seeds over GPUs: the wall-clock of ``python -m regrasp_mjx.train --seeds N`` on one GPU against
two, with where each run's time went (its ``final_eval.json`` timing) and how busy each GPU was.

Each run is its own process, started the way a user starts it (compile, evaluation, final tests and
export included; demonstrations from ``--demos``, built once and shared). GPU utilisation is
``nvidia-smi``'s, sampled every 0.5 s. ``--runs`` picks which to make in this call (a pair of 32-seed
runs may not fit one device call), and the results file gathers them across calls.

    python experiments/multi_gpu_seeds.py --seeds 8 --demos runs/demos --out experiments/results/multi_gpu_seeds
    python experiments/multi_gpu_seeds.py --seeds 32 --runs 1 --demos runs/demos --out ... --set epochs=12
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from datetime import date
from pathlib import Path

import numpy as np

from regrasp_mjx.core.atomic import dumps, write_results


def gpu_sampler(stop: threading.Event, samples: list[list[float]]) -> None:
    """Appends every GPU's utilisation (%) every 0.5 s until ``stop``."""
    query = ["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"]
    while not stop.wait(0.5):
        try:
            samples.append([float(x) for x in subprocess.run(query, capture_output=True, text=True).stdout.split()])
        except (OSError, ValueError):
            return


def train(seeds: int, gpus: int, args: argparse.Namespace, extra: list[str]) -> dict:
    out = Path(args.work) / f"{gpus}gpu_{seeds}seeds"
    cmd = [sys.executable, "-m", "regrasp_mjx.train", "--preset", args.preset, "--seeds", str(seeds)]
    cmd += ["--devices", str(gpus), "--demos", args.demos, "--out", str(out), "--overwrite", "--quiet", *extra]
    # each run compiles from scratch, as a user's first run does (its own empty compilation cache)
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ",".join(map(str, range(gpus))), "REGRASP_JAX_CACHE": str(out / "jax")}
    stop, samples = threading.Event(), []
    sampler = threading.Thread(target=gpu_sampler, args=(stop, samples), daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    stop.set()
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    final = json.loads((out / "final_eval.json").read_text())
    rows = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    epoch_s = {r["epoch"]: r["epoch_s"] for r in rows if r["epoch"] > 1}  # the first holds the compiles
    busy = np.array([s[:gpus] for s in samples if len(s) >= gpus]) if samples else np.zeros((0, gpus))
    return {
        "gpus": gpus,
        "seeds": seeds,
        "wall_s": wall,
        "timing": final["timing"],
        "epoch_s_median": float(np.median(list(epoch_s.values()))),
        "gpu_utilisation_mean": busy.mean(axis=0).round(1).tolist() if len(busy) else None,
        "test_bare": [m["test"]["bare"]["success_rate"] for m in final["seeds"]],
        "test_shielded": [m["test"]["shielded"]["success_rate"] for m in final["seeds"]],
    }


PHASES = ("setup", "compile", "iterations", "exchange", "evaluate", "export", "checkpoint", "final_test")


def tables(data: dict) -> tuple[list[dict], list[str]]:
    """The 1-to-2-GPU pairs (same seeds, overrides and label) and the two tables: pairs, and where each
    run's time went."""
    key = lambda r: (r["seeds"], r["set"], r.get("label", ""))  # noqa: E731
    pairs = []
    lines = [
        "| code | seeds | overrides | 1 GPU (s) | 2 GPUs (s) | speedup | per epoch, 1 GPU / 2 GPUs (s) | "
        "epoch speedup | paper300 bare, 1 GPU | 2 GPUs |",
        "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r1 in (r for r in data["runs"] if r["gpus"] == 1):
        r2 = next((r for r in data["runs"] if r["gpus"] == 2 and key(r) == key(r1)), None)
        if r2 is None:
            continue
        speedup, epoch = r1["wall_s"] / r2["wall_s"], r1["epoch_s_median"] / r2["epoch_s_median"]
        same = {"seeds": r1["seeds"], "set": r1["set"], "label": r1.get("label", "")}
        times = {"time_1gpu_s": r1["wall_s"], "time_2gpu_s": r2["wall_s"], "speedup": speedup, "epoch_speedup": epoch}
        pairs.append({"gpus": 2, **same, **times, "machine": r2["machine"], "date": r2["date"]})
        lines.append(
            f"| {r1.get('label') or '-'} | {r1['seeds']} | {' '.join(r1['set']) or 'none'} | {r1['wall_s']:.0f} | "
            f"{r2['wall_s']:.0f} | **{speedup:.2f}x** | {r1['epoch_s_median']:.2f} / {r2['epoch_s_median']:.2f} | "
            f"{epoch:.2f}x | {np.mean(r1['test_bare']):.3f} | {np.mean(r2['test_bare']):.3f} |"
        )
    lines += ["", "Where each run's time went (seconds, the runs' own `timing`; epoch: median of epochs 2 on):", ""]
    lines += ["| code | GPUs | seeds | wall | " + " | ".join(PHASES) + " | epoch | GPU busy (%) |"]
    lines += ["| --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in PHASES) + " | ---: | ---: |"]
    for r in data["runs"]:
        cells = " | ".join(f"{r['timing'].get(k, 0.0):.1f}" for k in PHASES)
        busy = "/".join(f"{u:.0f}" for u in r["gpu_utilisation_mean"] or [])
        lines.append(
            f"| {r.get('label') or '-'} | {r['gpus']} | {r['seeds']} | {r['wall_s']:.0f} | {cells} | "
            f"{r['epoch_s_median']:.2f} | {busy or '-'} |"
        )
    return pairs, lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="8", help="seed counts, comma-separated")
    p.add_argument("--runs", default="1,2", help="GPU counts to run now, comma-separated (1 and/or 2)")
    p.add_argument("--preset", default="decay")
    p.add_argument("--demos", required=True, help="a demonstration folder (python -m regrasp_mjx.demos)")
    p.add_argument("--work", default="runs/multi_gpu_seeds", help="where the runs write")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed on to the runs")
    p.add_argument("--label", default="", help="names the code measured (e.g. a commit); pairs match on it")
    p.add_argument("--report", action="store_true", help="only remake the tables from OUT/multi_gpu_seeds.json")
    p.add_argument("--out", required=True)
    args = p.parse_args()
    extra = [x for kv in args.set for x in ("--set", kv)]
    path = Path(args.out) / "multi_gpu_seeds.json"
    data = json.loads(path.read_text()) if path.exists() else {"runs": []}
    try:
        machine = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True
        )
        machine = machine.stdout.strip().replace("\n", " + ")
    except OSError:  # no NVIDIA driver: a CPU run (the script's own check)
        machine = "no GPU"
    for seeds in map(int, args.seeds.split(",")) if not args.report else ():
        for gpus in map(int, args.runs.split(",")):
            run = train(seeds, gpus, args, extra)
            run.update(machine=machine, date=str(date.today()), preset=args.preset)
            run.update(set=args.set, label=args.label)
            same = (seeds, gpus, args.set, args.label)
            data["runs"] = [r for r in data["runs"] if (r["seeds"], r["gpus"], r["set"], r.get("label", "")) != same]
            data["runs"].append(run)
            print(dumps(run), flush=True)
    pairs, lines = tables(data)
    data["pairs"] = pairs
    write_results(args.out, "multi_gpu_seeds", lines, data)


if __name__ == "__main__":
    main()
