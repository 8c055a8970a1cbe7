"""Bad input to the training CLI: one line naming the value and what is accepted, exit code 2, no
traceback, nothing on disk changed; a finished run is never mixed with a new one."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from regrasp_mjx import train
from regrasp_mjx.workflows.preflight import run_outputs


def _tree(folder: Path) -> dict[str, float]:
    return {str(p.relative_to(folder)): p.stat().st_mtime for p in sorted(folder.rglob("*"))}


@pytest.fixture()
def workdir(tmp_path):
    (tmp_path / "afile").write_text("not a folder\n")
    run = tmp_path / "done"
    (run / "seed0").mkdir(parents=True)
    (run / "log.jsonl").write_text(json.dumps({"epoch": 1}) + "\n")
    return tmp_path


CASES = [
    (["--out", "{w}/afile"], "is a file; accepted: a folder"),
    (["--out", "{w}/afile/sub"], "is not a writable folder"),
    (["--out", "{w}/new", "--resume"], "holds no run to continue; accepted: an earlier run's folder"),
    (["--out", "{w}/done"], "holds an earlier run (log.jsonl, seed0); accepted: --resume to continue it, --overwrite"),
    (["--out", "{w}/x", "--resume", "--overwrite"], "--resume and --overwrite are not accepted together"),
    (["--out", "{w}/x", "--preset", "huge"], "argument --preset: invalid choice: 'huge'"),
    (["--out", "{w}/x", "--set", "num_envs=0"], "num_envs=0 is not accepted: an integer >= 1"),
    (["--out", "{w}/x", "--set", "obs_noise_mm=-1"], "obs_noise_mm=-1 is not accepted"),
    (["--out", "{w}/x", "--set", "distill.goal_tolerance=2"], "distill.goal_tolerance=2 is not accepted"),
    (["--out", "{w}/x", "--testset", "paper3000"], "test-set file not found: paper3000; accepted: a shipped name"),
]


@pytest.mark.parametrize("argv, fragment", CASES)
def test_train_refuses_bad_input_and_changes_nothing(workdir, argv, fragment, capsys):
    before = _tree(workdir)
    with pytest.raises(SystemExit) as exit_:
        code = train.main([a.format(w=workdir) for a in argv])
        raise SystemExit(code)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err, err
    after = _tree(workdir)
    assert after == before or set(after) - set(before) <= {"x"}, set(after) ^ set(before)  # at most the empty folder


# The data-writing CLIs check --out (and their numbers) before any work.
OTHER_CASES = [
    ("testset", ["--out", "{w}/afile/t.npz"], "is not a writable folder"),
    ("testset", ["--out", "{w}/done"], "is not accepted: a file path ending in .npz"),
    ("testset", ["--out", "{w}/t.npz", "--n", "0"], "--n 0 is not accepted: an integer >= 1"),
    ("testset", ["--out", "{w}/t.npz", "--task", "huge"], "argument --task: invalid choice: 'huge'"),
    ("export_onnx", ["--out", "{w}/afile/p.onnx"], "is not a writable folder"),
    ("export_onnx", ["--out", "{w}/p.npz"], "is not accepted: a file path ending in .onnx"),
    ("export_onnx", ["--out", "{w}/p.onnx", "--policy", "genral"], "no shipped policy is named 'genral'"),
    ("compare", ["--out", "{w}/afile/c"], "is not a writable folder"),
    ("compare", ["--heldout", "3"], "--heldout 3 is not accepted: N:SEED"),
    ("compare", ["--heldout", "0:1"], "--heldout 0:1 is not accepted: N:SEED, N >= 1"),
    ("compare", ["--no-testset"], "--no-testset is not accepted without --heldout"),
    ("compare", ["--merge", "{w}/afile"], "--merge is not accepted without --robustness"),
    ("compare", ["--robustness", "--merge", "{w}/afile"], "accepted: table files this command wrote"),
    ("compare", ["--robustness", "--modes", "open,shut"], "--modes open,shut is not accepted"),
    ("compare", ["--robustness", "--conditions", "exact,sigma 9 mm"], "--conditions exact,sigma 9 mm is not accepted"),
    ("compare", ["--policy", "genral", "--no-testset", "--heldout", "2:0"], "no shipped policy is named 'genral'"),
    (
        "compare",
        ["--policy", "default", "--testset", "general1000"],
        "needle_radius_mm=9.32168 (query 0) is not accepted",
    ),
    ("evaluate", ["--testset", "general1000", "--repeats", "0"], "--testset general1000: needle_radius_mm=9.32168"),
    ("evaluate", ["--testset", "general1000", "--agreement"], "--testset general1000: needle_radius_mm=9.32168"),
    ("evaluate", ["--jaw-deg", "40"], "--jaw-deg and --jaw-sigmas are not accepted without --closed-loop"),
    ("grasps", ["--out", "{w}/afile/g.npz"], "is not a writable folder"),
    ("grasps", ["--out", "{w}/g.npz", "--n", "0"], "--n 0 is not accepted: an integer >= 1"),
]


@pytest.mark.parametrize("module, argv, fragment", OTHER_CASES)
def test_data_writing_clis_refuse_bad_input_and_change_nothing(workdir, module, argv, fragment, capsys):
    import importlib

    main = importlib.import_module(f"regrasp_mjx.{module}").main
    before = _tree(workdir)
    with pytest.raises(SystemExit) as exit_:
        raise SystemExit(main([a.format(w=workdir) for a in argv]))
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err, err
    assert _tree(workdir) == before


def test_run_outputs_are_what_a_run_wrote(tmp_path):
    (tmp_path / "sweep_stdout.txt").write_text("")
    assert run_outputs(tmp_path) == []  # another tool's file is no run
    (tmp_path / "mixed" / "seed0").mkdir(parents=True)
    (tmp_path / "events.out.tfevents.1").write_text("")
    assert [p.name for p in run_outputs(tmp_path)] == ["events.out.tfevents.1", "mixed"]


def test_the_grasp_library_command_needs_an_out():
    """Without --out it writes nothing (the package's copy untouched); the documented command's
    output is compared with the shipped library in tests/test_docs_commands.py."""
    from regrasp_mjx import grasps

    with pytest.raises(SystemExit) as exit_:
        grasps.main(["--n", "10"])
    assert exit_.value.code == 2
