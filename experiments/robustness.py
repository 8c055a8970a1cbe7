"""The docs' robustness blocks, rewritten from a robustness table file.

    python -m regrasp_mjx.compare --robustness --out experiments/results/robustness    # the table
    python experiments/robustness.py --docs experiments/results/robustness/robustness.json
    python -m regrasp_mjx.compare --robustness --modes fused --conditions "camera: tools 0.5 mm,..." \
        --out experiments/results/robustness --name camera                             # a real camera's rows
    python experiments/robustness.py --camera experiments/results/robustness/camera.json \
        --real-camera experiments/results/real_camera/real_camera.md      # and experiments/real_camera.py's tables

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
CAMERA_PAGES = {  # page -> the blocks of a real camera's rows (their own table file) it holds
    ROOT / "docs" / "results.md": ("camera_summary",),
    ROOT / "docs" / "inference.md": ("camera_summary",),
    ROOT / "experiments" / "RESULTS.md": ("camera",),
}
REAL_CAMERA_PAGES = {ROOT / "docs" / "results.md": ("real_camera",)}  # experiments/real_camera.py's tables


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--docs", metavar="JSON", help="the table file (its NAME.json)")
    p.add_argument("--camera", metavar="JSON", help="the table file of a real camera's rows")
    p.add_argument("--real-camera", metavar="MD", help="experiments/real_camera.py's tables (its NAME.md)")
    args = p.parse_args(argv)
    if not (args.docs or args.camera or args.real_camera):
        p.error("nothing to do: give --docs, --camera or --real-camera")
    if args.docs:
        rewrite(robustness_report.docs_blocks(json.loads(Path(args.docs).read_text())["tables"]), DOC_PAGES)
    if args.camera:
        rewrite(robustness_report.camera_blocks(json.loads(Path(args.camera).read_text())["tables"]), CAMERA_PAGES)
    if args.real_camera:
        rewrite({"real_camera": Path(args.real_camera).read_text().rstrip("\n").split("\n")}, REAL_CAMERA_PAGES)


def rewrite(blocks: dict[str, list[str]], pages: dict[Path, tuple[str, ...]]) -> None:
    for page, kinds in pages.items():
        text = page.read_text()
        for kind in kinds:
            text = robustness_report.replace_block(text, kind, blocks[kind])
        write_text(page, text)
        print(f"rewrote {page.relative_to(ROOT)} ({', '.join(kinds)})")


if __name__ == "__main__":
    main()
