"""The docs' robustness blocks, rewritten from a robustness table file.

    python -m regrasp_mjx.compare --robustness --out experiments/results/robustness    # the table
    python experiments/robustness.py --docs experiments/results/robustness/robustness.json

``--docs`` rewrites the generated robustness blocks of docs/results.md, docs/inference.md and
experiments/RESULTS.md (``regrasp_mjx.inference.robustness_report.docs_blocks``: the default and ``exact``, each named
by its hash, and the robot-error rows: the default and ``exact`` in docs/, every policy in RESULTS) from
the table file; run it whenever the table is made again (tests/test_robustness.py
checks that they agree).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from regrasp_mjx.core.atomic import write_text
from regrasp_mjx.inference import robustness_report

ROOT = Path(__file__).resolve().parents[1]
DOC_PAGES = {  # page -> the blocks it holds
    ROOT / "docs" / "results.md": ("summary", "robot_summary"),
    ROOT / "docs" / "inference.md": ("robot_summary",),
    ROOT / "experiments" / "RESULTS.md": ("tables", "robot"),
}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--docs", metavar="JSON", required=True, help="the table file (its NAME.json)")
    args = p.parse_args(argv)
    blocks = robustness_report.docs_blocks(json.loads(Path(args.docs).read_text())["tables"])
    for page, kinds in DOC_PAGES.items():
        text = page.read_text()
        for kind in kinds:
            text = robustness_report.replace_block(text, kind, blocks[kind])
        write_text(page, text)
        print(f"rewrote {page.relative_to(ROOT)} ({', '.join(kinds)})")


if __name__ == "__main__":
    main()
