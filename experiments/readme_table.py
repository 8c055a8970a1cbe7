"""The README's results table, generated from the result files it cites (so a stale number fails CI).

    python experiments/readme_table.py            # rewrite the block in README.md
    python experiments/readme_table.py --check    # exit 1 when README.md's block differs

Sources: success rates from ``experiments/results/continuous/compare.json`` (``python -m
regrasp_mjx.compare --heldout 3000:2022``), the fused closed loop at sigma 0.25 mm from
``experiments/results/robustness/robustness.json`` (``python -m regrasp_mjx.compare --robustness``),
one-core planning time from ``experiments/results/jaws40_default/bench_plan/bench_plan.json``
(``python experiments/bench_plan.py --no-rrt --repeats 3 --out ...``) and BIT* (R) from ``experiments/results/planners.csv``
(``python experiments/planners.py``); the paper's numbers are its Tables I and II.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from regrasp_mjx.workflows.analysis import PAPER_TABLE2

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
# (policy, what it is): the rows of the shipped networks, in this order
POLICIES = (
    ("default", "**shipped default** (3x512, jaws open on the way)"),
    ("general", "`general`: any grasp and needle (general1000 {g})"),
    ("decay", "`decay`: one 3x512 network, exact poses"),
    ("exact", "`exact`: the default until 2026-11-24"),
)


def _success(rows, policy, testset):
    pick = {r["rollout"]: r["success_rate"] for r in rows if r["policy"] == policy and r["testset"].startswith(testset)}
    return f"{pick['bare']:.3f} / {pick['shielded']:.3f}"


def _fused(tables, policy, condition="sigma 0.25 mm"):
    table = next(t for t in tables if t["policy"] == policy)
    row = next(r for r in table["rows"] if r["condition"] == condition and r["mode"] == "fused")
    return f"{row['success_rate']:.3f}"


def table_lines() -> list[str]:
    """The block's lines: the table and the line under it naming where each number comes from."""
    compare = json.loads((RESULTS / "continuous" / "compare.json").read_text())["rows"]
    tables = json.loads((RESULTS / "robustness" / "robustness.json").read_text())["tables"]
    bench = json.loads((RESULTS / "jaws40_default" / "bench_plan" / "bench_plan.json").read_text())
    lean = next(r for r in bench["rows"] if r["method"].startswith("policy `default`, shielded, lean path"))
    with open(RESULTS / "planners.csv") as f:
        bit = next(r for r in csv.DictReader(f) if r["algorithm"] == "BIT* (R)" and float(r["jaw_angle_deg"]) == 20.0)
    paper = {  # the paper's Table II, as the project records it once
        key: next(r for r in PAPER_TABLE2 if r["method"] == f"paper: {name}")
        for key, name in (("mixed", "DDPG+BC (mixed)"), ("bit", "BIT* (R)"))
    }
    lines = [
        "| planner | paper300 bare / shielded | held-out 3000 bare / shielded | fused, 0.25 mm noise |",
        "| --- | --- | --- | ---: |",
    ]
    for policy, what in POLICIES:
        fused = _fused(tables, policy) + (" on general1000" if policy == "general" else "")
        what = what.format(g=_success(compare, "general", "general1000")) if "{g}" in what else what
        lines.append(
            f"| {what} | {_success(compare, policy, 'paper300')} | {_success(compare, policy, 'held-out')} | {fused} |"
        )
    lines += [
        f"| BIT* (R), 10 s budget | {float(bit['success_rate']):.3f} | | |",
        f"| paper: DDPG+BC (mixed) / BIT* (R) | {paper['mixed']['success']} / {paper['bit']['success']} | | |",
        "",
        f"One query, shielded: the default plans in {lean['median_ms']:.3f} ms (median, one core of the "
        f"{bench['machine']} development VM, `experiments/bench_plan.py`), BIT* (R) in "
        f"{float(bit['plan_time_median_s']) * 1e3:.1f} ms (H100 host, before the continuous test), the paper's policy "
        f"in {paper['mixed']['mean_ms']} ms and its BIT* (R) in {paper['bit']['mean_ms']:.0f} ms (means).",
    ]
    return lines


def replace(text: str, lines: list[str]) -> str:
    i, j = text.index(BEGIN), text.index(END)
    return text[: i + len(BEGIN)] + "\n" + "\n".join(lines) + "\n" + text[j:]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="only compare; exit 1 when README.md's block differs")
    args = p.parse_args(argv)
    readme = ROOT / "README.md"
    text = readme.read_text()
    new = replace(text, table_lines())
    if args.check:
        print("README.md's results table is up to date" if new == text else "README.md's results table is stale")
        return 0 if new == text else 1
    readme.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
