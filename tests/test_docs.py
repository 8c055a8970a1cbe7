"""The manual stays true: every option of every command line is documented in README.md or docs/."""

from __future__ import annotations

import contextlib
import importlib
import io
import re

import pytest

from tests.conftest import ROOT

CLIS = ("train", "evaluate", "compare", "distill", "demos", "sweep", "testset", "export_onnx", "grasps")


def _options(module: str) -> set[str]:
    """The long options ``python -m regrasp_mjx.MODULE --help`` lists."""
    main = importlib.import_module(f"regrasp_mjx.{module}").main
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        main(["--help"])
    return set(re.findall(r"(--[a-z][a-z0-9-]*)", out.getvalue())) - {"--help"}


@pytest.mark.parametrize("module", CLIS)
def test_every_option_is_documented(module):
    docs = (ROOT / "README.md").read_text() + "".join(p.read_text() for p in sorted((ROOT / "docs").glob("*.md")))
    options = _options(module)
    assert options, f"python -m regrasp_mjx.{module} --help lists no options"
    missing = sorted(o for o in options if not re.search(rf"(?<![\w-]){o}(?![\w-])", docs))
    assert not missing, f"python -m regrasp_mjx.{module}: options not in README.md or docs/*.md: {missing}"


def test_the_manual_links_resolve():
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#]+)\)", page.read_text()):
            if target.startswith("http"):
                continue
            assert (page.parent / target).exists(), f"{page.name} links to {target}, which does not exist"


def test_the_readme_command_table_lists_every_cli_and_exactly_its_options():
    """README.md's command table: one row per command line of the package (every module that runs as
    ``__main__``, but the mesh-building development script), and each row's options are exactly
    those its ``--help`` lists."""
    rows = {}
    for line in (ROOT / "README.md").read_text().splitlines():
        m = re.match(r"\| `python -m regrasp_mjx\.(\w+)` \|[^|]*\|(.*)\|[^|]*\|$", line)
        if m:
            rows[m.group(1)] = set(re.findall(r"`(--[a-z][a-z0-9-]*)", m.group(2)))
    mains = {p.stem for p in (ROOT / "regrasp_mjx").glob("*.py") if 'if __name__ == "__main__":' in p.read_text()}
    assert set(rows) == mains == set(CLIS), (sorted(rows), sorted(mains))
    for module, listed in rows.items():
        options = _options(module)
        assert listed == options, (
            f"{module}: README lists {sorted(listed - options)} too many, {sorted(options - listed)} missing"
        )
