"""Writing an experiment's results: a markdown table for people, the rows as JSON for scripts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def write_results(out: str | Path | None, name: str, lines: list[str], data: Any) -> None:
    """``OUT/NAME.md`` (the table's lines) and ``OUT/NAME.json`` (``data``); nothing when ``out`` is None."""
    if out is None:
        return
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.md").write_text("\n".join(lines) + "\n")
    (folder / f"{name}.json").write_text(json.dumps(data, indent=2))
