"""Every number of README.md, docs/results.md and docs/notebooks.md is checked against its file by a test (issue 46).

Each number is changed in its last digit, one at a time, and the page's tests (those of
tests/test_docs.py that read it, and the robustness blocks' test) are run on the changed page: one
of them must fail. Not checked, because they are not results: a command's arguments (inside
backticks or a code block), a link's target, identifiers (dates, issues, commits, seeds, test sets,
the needle models' chord counts, notebooks, the paper's venue, Python versions) and the settings,
targets and values of the paper listed in ``NOT_RESULTS`` with why. 2-3.5 minutes on the 2-core
machine, so in the long tier.
"""

from __future__ import annotations

import inspect
import pathlib
import re

import pytest

import tests.test_docs as docs_tests
import tests.test_robustness as robustness_tests
from tests.conftest import ROOT

NUMBER = re.compile(r"(?<![\w.])\d+(?:[.,]\d+)*(?![\w])")
# spans whose numbers are not results: code, link targets, comments and identifiers
NOT_NUMBERS = re.compile(
    r"```.*?```|`[^`]+`|\]\([^)\s]*\)|<!--.*?-->"  # code, commands (may wrap), link targets, markers
    r"|\d{4}-\d{2}-\d{2}"  # dates
    r"|\bissues? \d+(?:(?:,| and) \d+(?![\d-]))*"  # issues (not a date after one)
    r"|\bseeds? (?:S = )?\d{3,}(?::\d+)?|\bseed \d(?:, \d)* ?(?:'s|/)"  # named seeds
    r"|held-out:? \d+(?::\d+)?|\b\d+ held-out|\b\d+ problems of seed"  # the held-out test set's name
    r"|\b\d+-chord|\bnotebooks? \d+(?: and \d+)?|\b0\d and 0\d\b|ICRA \d{4}|Python \d\.\d+ or \d\.\d+"
    r"|\d+-core Xeon host|H100 80GB|\bx86-64",  # machines
    re.S,
)
# (phrase, why its numbers are not results): the phrase's numbers are settings, targets or the
# paper's; each phrase must still be on its page (its spaces match any whitespace, line breaks too)
NOT_RESULTS = {
    "README.md": (("65,530 (`vm.max_map_count`)", "Linux's default limit, a fact of the system"),),
    "docs/notebooks.md": (),
    "docs/results.md": (
        ("median of 100 single queries", "the benchmark's setting"),
        ("four runs of 100-200 queries", "the benchmark's setting"),
        ("(100 queries x 3;", "the benchmark's setting"),
        ("100-step rollouts", "the benchmark's setting"),
        ("needle radius 4-6 / 6-8 / 8-10 / 10-12 mm", "the breakdown's bins"),
        ("By needle radius (4-6 / 6-8 / 8-10 / 10-12 mm)", "the breakdown's bins"),
        ("the paper's 0.97 at 200 epochs. **Trained for the paper's full 500 epochs", "the paper's, and settings"),
        ("below the paper's 0.97", "the paper's"),
        ("paper's 0.97, and they tie", "the paper's"),
        ("paper's ordering (0.97 / 0.71 / 0.64)", "the paper's Table I"),
        ("Decaying BC to 0 by epoch 100", "a setting of the run"),
        ("32 environments (fresher data)", "a setting of the run"),
        ("the same 100,000 updates", "the sweep's setting"),
        ("chosen on 2000 validation problems", "the selection's setting"),
        ("On 2000 validation", "the selection's setting"),
        ("10 s budget", "the planner's setting"),
        ("15 worker processes", "the recipe's setting"),
        ("(target 0.98)", "issue 29's target"),
        ("targets, 0.97 at 10 mm /", "issue 45's target"),
        ("the generalist's 0.97 at 5 mm", "issue 45's target"),
        ("20 warm-up frames instead of 10", "the closed loop's settings compared"),
    ),
}


def _page_tests(page: str) -> list:
    """The doc tests that read ``page`` (no fixtures), and the robustness blocks' test."""
    name = pathlib.PurePath(page).name
    found = [
        f
        for n, f in inspect.getmembers(docs_tests, inspect.isfunction)
        if n.startswith("test_") and name in inspect.getsource(f) and not inspect.signature(f).parameters
    ]
    return found + [robustness_tests.test_the_docs_robustness_blocks_are_the_table_file_rendered]


def _caught(tests: list) -> bool:
    for test in tests:
        try:
            test()
        except Exception:  # an AssertionError, or a parse of the changed page that broke: caught
            return True
    return False


def _not_results(text: str, page: str) -> list[tuple[int, int]]:
    spans = [m.span() for m in NOT_NUMBERS.finditer(text)]
    for phrase, _why in NOT_RESULTS[page]:
        found = [m.span() for m in re.finditer(re.escape(phrase).replace(r"\ ", r"\s+"), text)]
        assert found, f"{page}: NOT_RESULTS phrase no longer on the page: {phrase!r}"
        spans += found
    return spans


def uncaught_numbers(page: str, monkeypatch) -> list[str]:
    """The numbers of ``page`` that no test notices when changed, each with its line."""
    path = ROOT / page
    text = path.read_text()
    tests = _page_tests(page)
    current = {"text": text}
    read = pathlib.Path.read_text

    def read_text(self, *args, **kwargs):
        return current["text"] if self == path else read(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "read_text", read_text)
    assert not _caught(tests), f"{page}'s tests fail on the page as it is"
    skip = _not_results(text, page)
    missed = []
    for m in NUMBER.finditer(text):
        token = m.group(0)
        if len(token.replace(",", "").replace(".", "")) < 2 and "." not in token:
            continue  # one-digit counts ("3 seeds", "two") are words more than results
        if any(a <= m.start() and m.end() <= b for a, b in skip):
            continue
        digit = "1" if token[-1] != "1" else "2"
        current["text"] = text[: m.end() - 1] + digit + text[m.end() :]
        if not _caught(tests):
            line = text.count("\n", 0, m.start()) + 1
            missed.append(f"{page}:{line}: {token} in {text.splitlines()[line - 1].strip()[:90]!r}")
    current["text"] = text
    return missed


@pytest.mark.slow
@pytest.mark.parametrize("page", sorted(NOT_RESULTS))
def test_every_number_of_the_page_is_checked_by_a_test(page, monkeypatch):
    missed = uncaught_numbers(page, monkeypatch)
    assert not missed, (
        f"{len(missed)} numbers of {page} change no test's verdict: test them against their result file "
        "(tests/test_docs.py), or, if a setting, target or the paper's, list them in NOT_RESULTS with why:\n"
        + "\n".join(missed)
    )
