"""Runs several training commands at once on one GPU, each with its share of GPU memory, until they
end or a deadline passes (then they are stopped and their logs kept).

One learner iteration is bound by the latency of its small sequential updates, not by the GPU's
arithmetic, so programs that share a GPU lose little to each other; this is how the settings of
Table I and the ablations run side by side. Each command's output goes to ``OUT/NAME.log``.

    python experiments/run_parallel.py --out runs/c1 --deadline-s 540 \\
        --run "v0=-m regrasp_mjx.train --preset fast --seeds 3 --out runs/c1/v0" \\
        --run "v3=-m regrasp_mjx.train --preset fast --seeds 3 --out runs/c1/v3 --set action_noise=0.2"
"""

from __future__ import annotations

import argparse
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="append", required=True, metavar="NAME=ARGS", help="python arguments of one run")
    p.add_argument("--out", required=True, help="folder for the runs' logs")
    p.add_argument("--deadline-s", type=float, default=None, help="stop every run still going after this long")
    p.add_argument("--memory", type=float, default=0.9, help="share of GPU memory split between the runs")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for item in args.run:
        name, sep, rest = item.partition("=")
        if not sep or not name.strip():
            sys.exit(f"error: --run {item!r} is not accepted: NAME=ARGS")
        runs.append((name.strip(), shlex.split(rest)))
    env = {
        **os.environ,
        "PYTHONUNBUFFERED": "1",
        # JAX takes 75% of the GPU by default; each run gets its share instead
        "XLA_PYTHON_CLIENT_MEM_FRACTION": f"{args.memory / len(runs):.3f}",
    }
    t0 = time.monotonic()
    procs = {}
    for name, cmd in runs:
        log = open(out / f"{name}.log", "w")  # noqa: SIM115  (closed below)
        procs[name] = (subprocess.Popen([sys.executable, *cmd], stdout=log, stderr=subprocess.STDOUT, env=env), log)
        print(f"started {name}: python {shlex.join(cmd)}", flush=True)
    codes = {}
    while len(codes) < len(procs):
        for name, (proc, _) in procs.items():
            if name not in codes and proc.poll() is not None:
                codes[name] = proc.returncode
                print(f"{name} ended with {proc.returncode} after {time.monotonic() - t0:.0f} s", flush=True)
        if args.deadline_s is not None and time.monotonic() - t0 > args.deadline_s:
            for name, (proc, _) in procs.items():
                if name not in codes:
                    proc.send_signal(signal.SIGTERM)
            time.sleep(5)
            for name, (proc, _) in procs.items():
                if name not in codes:
                    proc.kill()
                    codes[name] = "stopped at the deadline"
                    print(f"{name} stopped at the deadline ({args.deadline_s:.0f} s)", flush=True)
        time.sleep(1)
    for _, log in procs.values():
        log.close()
    return 0 if all(c == 0 for c in codes.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
