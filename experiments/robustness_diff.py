"""Two policies' robustness tables side by side: every row both measured (condition and mode), each
one's success and the difference, as a markdown table (a recipe's exported policy against the shipped
one it should rebuild, experiments/RESULTS.md, issue 47).

    python experiments/robustness_diff.py SHIPPED.json REBUILT.json [--names shipped,rebuilt]

Each file is a ``robustness.json`` (``python -m regrasp_mjx.compare --robustness`` or a recipe's
report); its first table is read.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def rows(path: str) -> dict[tuple[str, str], float]:
    """``(condition, mode) -> success_rate`` of the file's first table."""
    table = json.loads(Path(path).read_text())["tables"][0]
    return {(r["condition"], r["mode"]): r["success_rate"] for r in table["rows"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("first")
    p.add_argument("second")
    p.add_argument("--names", default="first,second", help="the two columns' names, comma-separated")
    args = p.parse_args(argv)
    a, b = rows(args.first), rows(args.second)
    names = args.names.split(",")
    print(f"| condition | mode | {names[0]} | {names[1]} | {names[1]} - {names[0]} |")
    print("| --- | --- | ---: | ---: | ---: |")
    shared = [k for k in a if k in b]
    for condition, mode in shared:
        x, y = a[condition, mode], b[condition, mode]
        print(f"| {condition} | {mode} | {x:.3f} | {y:.3f} | {y - x:+.3f} |")
    within = sum(abs(b[k] - a[k]) <= 0.01 + 1e-9 for k in shared)
    better = sum(b[k] - a[k] > 0.01 + 1e-9 for k in shared)
    print(
        f"\n{within} of {len(shared)} rows within 0.01, {better} better by more, {len(shared) - within - better} worse"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
