"""The manual's commands work: every ``python -m regrasp_mjx.*`` and ``python experiments/*.py``
line in README.md and docs/*.md (code blocks and inline code) parses with its program's own
arguments, and those that take under a minute on a CPU run for real, their outputs in a temporary
folder compared with the files they document."""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import json
import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from regrasp_mjx.world.sampling import load_testset
from tests.conftest import REGENERATION_ATOL, ROOT, needle_model_redraws

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# The manual's placeholders, by the option they stand after (``--policy P``, ``--noise-mm S``).
PLACEHOLDER = re.compile(r"^(?:[A-Z]|NAME|N|SEED|PATH|OUT)$")
PLACEHOLDER_VALUE = {
    "--policy": "default",
    "--testset": "paper300",
    "--queries": "3",
    "--batch-size": "2",
    "--repeats": "1",
    "--seed": "0",
    "--clearance-mm": "0.1",
    "--noise-mm": "0.1",
    "--bias-mm": "0.1",
    "--calibration-mm": "5",
    "--calibration-deg": "3",
    "--joint-offset": "0.5",
    "--tool-noise-mm": "0.25",
}


def documented_commands() -> list[tuple[str, str]]:
    """``(page, command)`` for each python command of the manual, in page order, once each."""
    found: dict[str, str] = {}
    for page in PAGES:
        text = page.read_text()
        blocks = re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
        lines = [ln for b in blocks for ln in b.replace("\\\n", " ").splitlines()]
        lines += re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
        for line in lines:
            m = re.search(r"\bpython (?:-m regrasp_mjx\.\w+|experiments/\w+\.py)\b.*", line)
            if m:
                found.setdefault(" ".join(m.group(0).split()), page.name)
    return [(page, cmd) for cmd, page in found.items()]


def program_and_argv(command: str) -> tuple[str, list[str]]:
    """The program (``regrasp_mjx.X`` or ``experiments/X.py``) and its arguments: comments and
    ``...`` dropped, optional ``[--x V]`` parts taken as given, placeholders replaced."""
    words = [w.strip("[]") for w in shlex.split(command, comments=True) if w not in ("...", "[...]")]
    words = [w for w in words if w]
    assert words[0] == "python", command
    program, rest = (words[2], words[3:]) if words[1] == "-m" else (words[1], words[2:])
    argv = []
    for i, w in enumerate(rest):
        if PLACEHOLDER.match(w) and i > 0 and rest[i - 1] in PLACEHOLDER_VALUE:
            w = PLACEHOLDER_VALUE[rest[i - 1]]
        argv.append(w)
    return program, argv


class _Parsed(Exception):
    """Raised once a program's parser accepted its arguments: nothing more of it runs."""


def parses(program: str, argv: list[str], monkeypatch) -> None:
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        ns = original(self, args, namespace)
        raise _Parsed(ns)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    with pytest.raises(_Parsed):
        if program.startswith("regrasp_mjx."):
            importlib.import_module(program).main(argv)
        else:
            monkeypatch.setattr(sys, "argv", [program, *argv])
            monkeypatch.syspath_prepend(str(ROOT / "experiments"))
            runpy.run_path(str(ROOT / program), run_name="__main__")


# The commands that run for real here (each under a minute on one CPU core): how to judge their
# output. ``--out`` goes to a temporary folder; the documented path is what the output must match.
def _same_testset(new: Path, shipped: Path) -> None:
    """The same problems, but for rows the earlier needle model redrew (``needle_model_redraws``)."""
    with np.load(new) as a, np.load(shipped) as b:
        meta_a, meta_b = json.loads(str(a["meta"])), json.loads(str(b["meta"]))
        assert meta_a["seed"] == meta_b["seed"] and meta_a["n"] == meta_b["n"]
    fresh, committed = load_testset(new)[0], load_testset(shipped)[0]
    needle_model_redraws(fresh, committed)


def _same_file_arrays(new: Path, shipped: Path) -> None:
    with np.load(new) as a, np.load(shipped) as b:
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            if a[key].dtype.kind in "US":  # the metadata: the same text
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
            else:
                np.testing.assert_allclose(a[key], b[key], rtol=0, atol=REGENERATION_ATOL, err_msg=key)


RUNS = {
    # the test sets are drawn beside the committed ones (never over the package's data) and compared with them
    "python -m regrasp_mjx.testset --n 300 --seed 2021 --out paper300.npz [--jaw-angle-deg 20]": (
        lambda new, _: _same_testset(new, ROOT / "regrasp_mjx" / "data" / "paper300.npz")
    ),
    "python -m regrasp_mjx.testset --task general --n 1000 --seed 2026 --out general1000.npz": (
        lambda new, _: _same_testset(new, ROOT / "regrasp_mjx" / "data" / "general1000.npz")
    ),
    "python -m regrasp_mjx.grasps --n 1000 --seed 7 --out regrasp_mjx/data/grasps1000.npz": _same_file_arrays,
    "python -m regrasp_mjx.export_onnx --out actor.onnx [--policy P] [--no-check]": None,
}
# The others take minutes (training, planners, test-set-wide timings) or a GPU: they are parsed
# only, here; the README's first command (the smoke run) is what tests/test_multihost.py runs.


@pytest.mark.parametrize("page, command", documented_commands())
def test_a_documented_command_parses(page, command, monkeypatch):
    program, argv = program_and_argv(command)
    if program.startswith("regrasp_mjx."):
        assert (ROOT / (program.replace(".", "/") + ".py")).is_file(), f"{page}: no module {program}"
    else:
        assert (ROOT / program).is_file(), f"{page}: no script {program}"
    if not argv or "..." in command:  # the program named (the README's table) or a partial command
        return
    try:
        parses(program, argv, monkeypatch)
    except SystemExit as err:  # argparse's refusal: the documented command no longer parses
        pytest.fail(f"{page}: `{command}` is refused by {program} (exit {err.code})")


def test_the_manual_has_the_commands_this_test_runs():
    documented = {cmd for _, cmd in documented_commands()}
    assert set(RUNS) <= documented, sorted(set(RUNS) - documented)
    assert len(documented) >= 25  # the extraction found the manual's commands, not a few of them


@pytest.mark.parametrize("command", sorted(RUNS))
def test_a_documented_command_runs_and_makes_what_it_says(command, tmp_path, monkeypatch, capsys):
    program, argv = program_and_argv(command)
    i = argv.index("--out")
    documented_out = ROOT / argv[i + 1]
    argv[i + 1] = str(tmp_path / Path(argv[i + 1]).name)
    monkeypatch.chdir(tmp_path)  # nothing lands in the checkout, even by a relative path
    before = {p: p.stat().st_mtime for p in (ROOT / "regrasp_mjx" / "data").iterdir()}
    assert importlib.import_module(program).main(argv) in (0, None)
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert Path(result["out"]) == Path(argv[i + 1]) and Path(argv[i + 1]).is_file()
    if RUNS[command] is not None:
        RUNS[command](Path(argv[i + 1]), documented_out)
    assert {p: p.stat().st_mtime for p in (ROOT / "regrasp_mjx" / "data").iterdir()} == before
    assert not any(p.suffix == ".onnx" for p in ROOT.iterdir()), "a command wrote into the checkout"
    assert os.listdir(tmp_path) == [Path(argv[i + 1]).name]


# the Minari dataset's snippet reads a dataset that an export made first: tests/test_minari.py runs it
LEARNER_SNIPPETS = [
    s
    for s in re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "learners.md").read_text(), re.S)
    if "import minari" not in s
]


@pytest.mark.parametrize(
    "snippet",
    # the Playground and vector-env snippets compile batches of rollouts: in the long tier (see tests/conftest.py)
    [pytest.param(s, marks=pytest.mark.slow) if i != 1 else s for i, s in enumerate(LEARNER_SNIPPETS)],
    ids=["playground", "gymnasium", "gymnasium-vector", "gymnasium-vector-jax"],
)
def test_the_learners_page_snippets_run(snippet, capsys):
    """docs/learners.md's four snippets (Playground style, gymnasium single and vector, the vector env
    with device arrays) run as written."""
    exec(compile(snippet, "docs/learners.md", "exec"), {"__name__": "__docs__"})
    assert capsys.readouterr().out.strip()  # each prints what it shows


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "experiments").glob("[!_]*.py")))
def test_every_experiment_script_answers_help(script, monkeypatch, capsys):
    """``python experiments/X.py --help`` prints its usage and exits 0 (nothing else runs)."""
    affinity = os.sched_getaffinity(0)  # bench_plan pins its process to one core as it starts
    monkeypatch.setattr(sys, "argv", [script, "--help"])
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    try:
        with pytest.raises(SystemExit) as done:
            runpy.run_path(str(ROOT / "experiments" / script), run_name="__main__")
    finally:
        os.sched_setaffinity(0, affinity)
    assert done.value.code in (0, None)
    assert "usage:" in capsys.readouterr().out


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "experiments").glob("*.sh")))
def test_every_experiment_shell_script_parses_and_what_it_calls_is_there(script):
    """``bash -n experiments/X.sh`` passes, every ``python -m MODULE`` it calls is importable, every
    ``python experiments/Y.py`` it calls exists and the imports of its ``python -c "..."`` lines run
    (nothing else runs: they are device calls)."""
    path = ROOT / "experiments" / script
    done = subprocess.run(["bash", "-n", str(path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    text = path.read_text()
    modules = re.findall(r"\bpython -m ([\w.]+)", text)
    scripts = re.findall(r"\bpython (experiments/\w+\.py)", text)
    assert modules or scripts, f"{script} calls no python program"
    for module in modules:
        assert importlib.util.find_spec(module) is not None, f"{script} calls {module}, which is not there"
    for called in scripts:
        assert (ROOT / called).is_file(), f"{script} calls {called}, which is not there"
    for code in re.findall(r"\bpython -c \"([^\"]*)\"", text):
        imports = [n for n in ast.parse(code).body if isinstance(n, (ast.Import, ast.ImportFrom))]
        exec(compile(ast.Module(imports, type_ignores=[]), script, "exec"), {})


def test_every_experiment_script_is_cited():
    """Each script in experiments/ is named by experiments/RESULTS.md, README.md or docs/ (issue 70)."""
    cited = " ".join(p.read_text() for p in (*PAGES, ROOT / "experiments" / "RESULTS.md"))
    scripts = [p.name for p in (ROOT / "experiments").iterdir() if p.suffix in (".py", ".sh")]
    assert scripts and not [s for s in scripts if f"experiments/{s}" not in cited]
