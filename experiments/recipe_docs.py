"""docs/training.md's recipe block, generated from the recipes as data (``regrasp_mjx.workflows.recipes``).

python experiments/recipe_docs.py            # rewrite the block
python experiments/recipe_docs.py --check    # exit 1 when the block differs (tests/test_recipe.py checks too)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from regrasp_mjx.core.atomic import write_text
from regrasp_mjx.workflows.recipes import render_docs

PAGE = Path(__file__).resolve().parents[1] / "docs" / "training.md"
BEGIN, END = "<!-- recipes:begin -->", "<!-- recipes:end -->"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="only compare")
    args = p.parse_args(argv)
    text = PAGE.read_text()
    head, rest = text.split(BEGIN + "\n", 1)
    _, tail = rest.split(END, 1)
    new = head + BEGIN + "\n" + "\n".join(render_docs()) + "\n" + END + tail
    if args.check:
        print("up to date" if new == text else f"{PAGE} differs: python experiments/recipe_docs.py")
        return 0 if new == text else 1
    write_text(PAGE, new)
    print(f"rewrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
