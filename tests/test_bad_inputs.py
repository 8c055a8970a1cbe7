"""What a new user trips on (issue 46), each refused before any work with one line that says what
was wrong and what is accepted (exit 2 for a command line, one exception type for the API), with
nothing written; one run per output folder; Ctrl-C as one line; strict JSON everywhere."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from regrasp_mjx import compare, demos, distill, evaluate, export_onnx, grasps, load_policy, testset, train
from regrasp_mjx.core.atomic import dumps
from regrasp_mjx.core.host_loop import FolderInUse, folder_lock, run_command
from regrasp_mjx.inference.policy_file import PolicyError
from regrasp_mjx.inference.queries import PoseError

ROOT = Path(__file__).resolve().parents[1]


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _refused(main, argv, match, capsys, folder: Path):
    """``main(argv)`` exits 2 with one error line matching ``match``, and ``folder`` is unchanged."""
    before = _files(folder)
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    assert code == 2, (argv, code)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    errors = [line for line in err if "error" in line]
    assert len(errors) == 1 and re.search(match, errors[0]), err
    assert _files(folder) == before, argv


def _cli_cases(tmp: Path):
    (tmp / "afile").write_text("x")
    (tmp / "student").mkdir()
    (tmp / "student" / "distill_log.jsonl").write_text("{}\n")
    (tmp / "empty").mkdir()
    return [
        (train.main, ["--preset", "smoke", "--out", ""], r"--out '' is not accepted"),
        (train.main, ["--preset", "smoke", "--out", str(tmp / "afile")], r"is a file; accepted: a folder"),
        (
            train.main,
            ["--preset", "smoke", "--out", str(tmp / "r"), "--testset", "general1000"],
            r"--testset general1000 holds problems of another task .* accepted: paper300",
        ),
        (
            train.main,
            ["--preset", "smoke", "--out", str(tmp / "r"), "--set", "batch_size=20000"],
            r"batch_size=20000 needs .* accepted: a smaller batch_size",
        ),
        (train.main, ["--preset", "smoke", "--out", str(tmp / "empty"), "--resume"], r"holds no run to continue"),
        (train.main, ["--preset", "smoke", "--out", str(tmp / "r"), "--testset", "missing.npz"], r"missing.npz"),
        (demos.main, ["--n", "2", "--out", str(tmp / "afile")], r"is a file; accepted: a folder"),
        (demos.main, ["--n", "2", "--out", ""], r"--out '' is not accepted"),
        (demos.main, ["--n", "0", "--out", str(tmp / "d")], r"--n and --workers must be >= 1"),
        (
            distill.main,
            ["--teacher", "default", "--out", str(tmp / "student")],
            r"holds an earlier distillation \(distill_log.jsonl\); accepted: another --out, or --overwrite",
        ),
        (distill.main, ["--teacher", "default", "--out", ""], r"--out '' is not accepted"),
        (distill.main, ["--teacher", "default", "--out", str(tmp / "afile")], r"is a file"),
        (compare.main, ["--modes", "open"], r"--modes is not accepted without --robustness"),
        (compare.main, ["--conditions", "exact"], r"--conditions is not accepted without --robustness"),
        (compare.main, ["--robustness", "--out", ""], r"--out '' is not accepted"),
        (
            train.main,
            ["--preset", "smoke", "--out", str(tmp / "r"), "--devices", "64"],
            r"devices=64 is not accepted: JAX sees \d+ cpu device\(s\)",
        ),
        (export_onnx.main, ["--out", str(tmp / "nowhere" / "a.onnx")], r"the folder .*nowhere does not exist"),
        (testset.main, ["--n", "2", "--out", str(tmp / "nowhere" / "t.npz")], r"the folder .*nowhere does not exist"),
        (grasps.main, ["--n", "2", "--out", str(tmp / "nowhere" / "g.npz")], r"the folder .*nowhere does not exist"),
    ]


def test_command_lines_refuse_bad_input_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a refusal that failed would write here, not into the checkout
    for main, argv, match in _cli_cases(tmp_path):
        _refused(main, argv, match, capsys, tmp_path)


@pytest.mark.parametrize(
    "call, error, match",
    [
        (lambda p: p.plan(np.zeros((2, 3, 7)), np.zeros((2, 3, 7))), PoseError, r"accepted: \(7,\) or \(B, 7\)"),
        (lambda p: p.plan(np.zeros((0, 7)), np.zeros((0, 7))), PoseError, r"an empty batch; accepted: at least one"),
        (lambda p: p.plan(np.zeros(6), np.zeros(6)), PoseError, r"shape \(6,\); accepted: \(7,\) or \(B, 7\)"),
        (lambda p: p.plan(_pose(), _pose(), shield="no"), ValueError, r"shield='no' is not accepted: True or False"),
        (lambda p: p.plan(_pose(), _pose(), check_grasp=1), ValueError, r"check_grasp=1 is not accepted"),
        (lambda p: load_policy(123), PolicyError, r"policy 123 is not accepted: a folder path"),
        (lambda p: _batch_plan(p).trajectory(), ValueError, r"holds 2 queries; trajectory\(query=i\) gives"),
        (lambda p: _batch_plan(p).trajectory(query=2), ValueError, r"query=2 is not accepted"),
        (lambda p: _batch_plan(p).trajectory("world", 0), ValueError, r"frame='world' is not accepted"),
        (lambda p: _batch_plan(p).trajectory("camera", 0), ValueError, r"no camera-frame poses"),
        (lambda p: p.closed_loop_step(np.zeros((0, 7)), np.zeros((0, 7))), PoseError, r"empty batch"),
        (lambda p: p.camera_loop().update(_pose(), _pose(), np.zeros(6)), PoseError, r"needle has shape \(6,\)"),
    ],
)
def test_the_api_refuses_bad_poses_and_flags_with_one_exception(call, error, match):
    with pytest.raises(error, match=match):
        call(load_policy())


def _batch_plan(policy):
    plan = policy.plan(np.tile(_NEEDLE, (2, 1)), np.tile(_pose(), (2, 1)), check_grasp=False)
    assert plan.trajectory(query=1).shape == (int(plan.steps[1]) + 1, 7)  # a batch's query is served
    return plan


_NEEDLE = np.array([0.0, -0.0054, 0.0, 1.0, 0.0, 0.0, 0.0])


def _pose():
    return np.array([0.0, 0.0, 0.013, 1.0, 0.0, 0.0, 0.0])


def test_a_second_run_into_a_held_folder_is_refused_and_a_killed_run_leaves_no_lock(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "r"
    with folder_lock(out):
        with pytest.raises(FolderInUse, match=r"is in use by another run \(pid \d+\)"):
            with folder_lock(out):
                pass
        _refused(train.main, ["--preset", "smoke", "--out", str(out)], r"is in use by another run", capsys, tmp_path)
        _refused(demos.main, ["--n", "2", "--out", str(out)], r"is in use by another run", capsys, tmp_path)
    # a process that holds the lock and is killed: the kernel drops it
    code = "import sys, time; from pathlib import Path; from regrasp_mjx.core.host_loop import folder_lock\n"
    code += "with folder_lock(Path(sys.argv[1])):\n    print('held', flush=True); time.sleep(60)\n"
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout.readline().strip() == "held"
    with pytest.raises(FolderInUse):
        with folder_lock(out):
            pass
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    with folder_lock(out):  # free again
        pass
    # shared holders (shards) hold it together; one that needs it alone is refused while any lives, and
    # they while it does
    with folder_lock(out, shared=True), folder_lock(out, shared=True):
        with pytest.raises(FolderInUse):
            with folder_lock(out):
                pass
    with folder_lock(out):
        with pytest.raises(FolderInUse):
            with folder_lock(out, shared=True):
                pass


def test_ctrl_c_is_one_line_and_exit_130(capsys):
    def interrupted():
        raise KeyboardInterrupt

    assert run_command(interrupted, "run the same command with --resume") == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["interrupted; run the same command with --resume"]


def test_a_run_stopped_before_its_first_checkpoint_resumes(tmp_path):
    """Interrupted while building its demonstrations: --resume is accepted (it starts at epoch 0
    and keeps the demonstrations built so far), and without it the folder is named as an earlier run."""
    out = tmp_path / "r"
    (out / "demos" / "plans").mkdir(parents=True)
    assert train.check_out(out, resume=True, overwrite=False) is None
    assert "--resume to continue it" in train.check_out(out, resume=False, overwrite=False)


def _strict(text: str):
    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_every_committed_json_file_is_strict():
    names = subprocess.run(
        ["git", "ls-files", "*.json", "*.jsonl", "*.ipynb"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    assert len(names) > 50
    for name in names:
        text = (ROOT / name).read_text()
        rows = [x for x in text.splitlines() if x.strip()] if name.endswith(".jsonl") else [text]
        for row in rows:
            try:
                _strict(row)
            except ValueError as err:
                raise AssertionError(f"{name}: {err}") from None


def test_json_written_or_printed_is_strict(capsys):
    assert dumps({"a": float("nan"), "b": [np.float32("inf"), 1.5], "c": np.arange(2)}) == (
        '{"a": null, "b": [null, 1.5], "c": [0, 1]}'
    )
    # no problem keeps a 1 mm margin: the rates have no value (null), not NaN
    args = ["--noise-mm", "0.1", "--clearance-mm", "1.0", "--json", "--testset", "paper300", "--policy", "student_v3"]
    assert evaluate.main(args) == 0  # student_v3: its 20-degree jaws leave no problem 1 mm
    r = _strict(capsys.readouterr().out)
    assert r["problems_valid"] == 0 and r["success_rate"] is None


def test_a_policy_with_nan_weights_is_refused(tmp_path):
    """A diverged or damaged network (NaN in its weights) no longer loads and plans silently."""
    from regrasp_mjx.inference.policy_file import resolve

    folder = tmp_path / "p"
    folder.mkdir()
    shipped = resolve("default")
    (folder / "policy.json").write_text((shipped / "policy.json").read_text())
    with np.load(shipped / "policy.npz") as f:
        arrays = {k: f[k] for k in f.files}
    name = next(k for k in arrays if k.startswith("actor/") and k.endswith("kernel"))
    arrays[name] = arrays[name].copy()
    arrays[name].flat[0] = np.nan
    np.savez(folder / "policy.npz", **arrays)
    with pytest.raises(PolicyError, match=r"hold NaN or inf; accepted: finite weights"):
        load_policy(folder)
    arrays[name].flat[0] = 0.0
    np.savez(folder / "policy.npz", **arrays)
    assert load_policy(folder).hidden == load_policy().hidden  # the same file with finite weights loads
