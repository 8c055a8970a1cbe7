"""What a new user still tripped on (issue 70's table): each refused before any work with one line
(exit 2, no traceback, nothing on disk), Ctrl-C as one line and exit 130 in every command, one run
per folder also for a run's own distillation, and the API's refusals naming the argument."""

from __future__ import annotations

import os
import re
import runpy
import signal
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from regrasp_mjx import compare, demos, distill, export_onnx, grasps, recipe, sweep, testset, train
from regrasp_mjx.core import cluster, distributed
from regrasp_mjx.core.atomic import output_file_problem, output_folder_problem
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.host_loop import FolderInUse, folder_lock, run_command

# a path no one can write, root included (os.access says yes to root here)
UNWRITABLE = "/proc/regrasp_mjx_x"


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _refused(main, argv, match, capsys, folder: Path) -> None:
    """``main(argv)`` exits 2 with one error line matching ``match``, no traceback, ``folder`` unchanged."""
    before = _files(folder)
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 2, (argv, code, err)
    lines = [line for line in err.splitlines() if "error" in line]
    assert len(lines) == 1 and re.search(match, lines[0]) and "Traceback" not in err, err
    assert _files(folder) == before, argv


# ---- 1: an unwritable --out, refused before any work, in every command that writes ----------------


def test_an_unwritable_folder_is_found_by_writing_not_by_permission_bits(tmp_path):
    assert "is not a writable folder" in output_folder_problem(f"{UNWRITABLE}/run")
    assert "is not a writable folder" in output_file_problem(f"{UNWRITABLE}/t.npz", ".npz")
    assert output_folder_problem(tmp_path / "new" / "run") is None
    assert output_file_problem(tmp_path / "t.npz", ".npz") is None
    assert _files(tmp_path) == []  # the try leaves nothing behind


@pytest.mark.parametrize(
    "main, argv",
    [
        (train.main, ["--out", UNWRITABLE]),
        (distill.main, ["--teacher", "default", "--out", UNWRITABLE]),
        (demos.main, ["--n", "2", "--out", UNWRITABLE]),
        (recipe.main, ["smoke", "--out", UNWRITABLE]),
        (compare.main, ["--out", UNWRITABLE]),
        (testset.main, ["--n", "2", "--out", UNWRITABLE + ".npz"]),
        (grasps.main, ["--n", "2", "--out", UNWRITABLE + ".npz"]),
        (export_onnx.main, ["--out", UNWRITABLE + ".onnx"]),
        (sweep.main, ["--out", UNWRITABLE, "--preset", "smoke", "--dry-run"]),
    ],
)
def test_an_unwritable_out_is_refused_before_any_work(main, argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _refused(main, argv, r"is not a writable folder", capsys, tmp_path)


# ---- 2: --gpus ------------------------------------------------------------------------------------


@pytest.mark.parametrize("gpus", [",", "abc", "0,,1", "0,x", ""])
def test_gpus_that_name_no_gpu_are_refused(gpus, capsys, tmp_path):
    with pytest.raises(ConfigError, match=r"--gpus .* is not accepted: GPU indices, comma-separated"):
        cluster.local_gpus(gpus)
    _refused(recipe.main, ["smoke", "--out", str(tmp_path / "r"), "--gpus", gpus], r"--gpus", capsys, tmp_path)
    argv = ["--out", str(tmp_path / "s"), "--preset", "smoke", "--gpus", gpus, "--dry-run"]
    _refused(sweep.main, argv, r"--gpus", capsys, tmp_path)
    assert cluster.local_gpus("0, 2") == ["0", "2"]


# ---- 3: the multi-process options ----------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--coordinator", "badaddr"], r"--coordinator badaddr is not accepted: HOST:PORT"),
        (["--coordinator", "host:99999", "--num-processes", "2", "--process-id", "0"], r"HOST:PORT"),
        (["--process-id", "5", "--num-processes", "2"], r"not accepted without --coordinator"),
        (["--coordinator", "h:1234", "--process-id", "5", "--num-processes", "2"], r"an index in \[0, 2\)"),
        (["--coordinator", "h:1234", "--process-id", "-1", "--num-processes", "2"], r"an index in \[0, 2\)"),
        (["--distributed", "--num-processes", "0", "--process-id", "0"], r"a count >= 1"),
        (["--coordinator", "h:1234", "--process-id", "1"], r"accepted only together"),
    ],
)
def test_train_refuses_multi_process_options_that_cannot_work(argv, match, capsys, tmp_path):
    _refused(train.main, ["--out", str(tmp_path / "r"), *argv], match, capsys, tmp_path)


def test_distributed_with_nothing_to_join_is_one_line(tmp_path):
    """--distributed where JAX detects no cluster: JAX's ValueError as one line (a child: JAX joins a
    run only before its first computation)."""
    import subprocess

    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COORDINATOR", "SLURM_", "OMPI_"))}
    argv = [sys.executable, "-m", "regrasp_mjx.train", "--out", str(tmp_path / "r"), "--distributed"]
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=120)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1, proc.stderr
    assert err[0].startswith("error: --distributed: JAX could not join a run") and "--coordinator HOST:PORT" in err[0]
    assert _files(tmp_path) == []


def test_the_documented_multi_process_options_are_accepted():
    assert distributed.options_problem(False, "node0:12345", 2, 1) is None
    assert distributed.options_problem(True, None, None, None) is None  # detected: SLURM, Open MPI, env
    assert distributed.options_problem(True, None, 4, 3) is None
    assert distributed.options_problem(False, "[::1]:1234", 1, 0) is None
    assert distributed.options_problem(False, None, None, None) is None  # a single-process run


# ---- 4, 5, 7: numbers and inputs checked before anything is made -----------------------------------


def test_testset_refuses_more_problems_than_its_bound(capsys, tmp_path):
    argv = ["--n", "10000000000", "--out", str(tmp_path / "t.npz")]
    _refused(
        testset.main, argv, r"--n 10000000000 is not accepted: an integer >= 1 and at most 1000000", capsys, tmp_path
    )


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--replay-batch", "0"], r"replay_batch=0 is not accepted: an integer >= 1"),
        (["--budget-s", "0"], r"budget_s=0.0 is not accepted"),
        (["--budget-s", "nan"], r"budget_s=nan is not accepted"),
        (["--budget-s", "inf"], r"budget_s=inf is not accepted"),
        (["--timeout-s", "-1"], r"timeout_s=-1.0 is not accepted"),
    ],
)
def test_demos_refuses_bad_numbers_before_making_its_folder(argv, match, capsys, tmp_path):
    _refused(demos.main, ["--n", "2", "--workers", "1", "--out", str(tmp_path / "d"), *argv], match, capsys, tmp_path)


def test_train_refuses_missing_demonstrations_before_making_its_folder(capsys, tmp_path):
    argv = ["--preset", "smoke", "--out", str(tmp_path / "r"), "--demos", str(tmp_path / "nonexistent")]
    _refused(train.main, argv, r"--demos .*nonexistent: demonstration set not found", capsys, tmp_path)


# ---- 6: compare's file names and policies --------------------------------------------------------


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--name", "../../x"], r"--name ../../x is not accepted: a file name without a folder"),
        (["--name", "sub/x"], r"--name sub/x is not accepted"),
        (["--name", ".."], r"--name .. is not accepted"),
        (["--policy", "=regrasp_mjx/policies/default"], r"--policy =regrasp_mjx/policies/default is not accepted"),
    ],
)
def test_compare_refuses_names_outside_out_and_blank_policy_names(argv, match, capsys, tmp_path):
    _refused(compare.main, ["--out", str(tmp_path / "c"), *argv], match, capsys, tmp_path)


# ---- 9, 10: one run per folder -------------------------------------------------------------------


def test_a_live_runs_folder_is_named_in_use_first(capsys, tmp_path):
    out = tmp_path / "r"
    out.mkdir()
    (out / "log.jsonl").write_text("{}\n")  # an earlier (here: the live) run's outputs
    with folder_lock(out):
        _refused(train.main, ["--out", str(out)], r"is in use by another run", capsys, tmp_path)
        _refused(train.main, ["--out", str(out), "--resume"], r"is in use by another run", capsys, tmp_path)
    assert "holds an earlier run" in train.check_out(out, resume=False, overwrite=False)  # free again


def test_a_runs_own_distillation_holds_the_students_folder(tmp_path, monkeypatch):
    """``train``'s distillation into ``RUN/student`` takes the lock the distill command takes."""
    import types

    from regrasp_mjx.agents.dagger import DistillConfig
    from regrasp_mjx.workflows import trainer

    held = []

    def fake_distill(teacher, folder, cfg, testset, name, quiet):
        with pytest.raises(FolderInUse):  # a distill command into it now is refused
            with folder_lock(folder):
                pass
        held.append(folder)
        return {"student": str(folder / "policy")}

    monkeypatch.setattr(trainer, "distill", fake_distill)
    monkeypatch.setattr(trainer, "load_policy", lambda path: None)
    run = types.SimpleNamespace(
        cfg=types.SimpleNamespace(distill=DistillConfig()),
        member_dir=lambda m: tmp_path,
        log=lambda msg: None,
        testset=None,
        quiet=True,
    )
    members = [{"seed": 0, "setting": None, "policy": str(tmp_path / "policy")}]
    students = trainer.Run.distill(run, members)
    assert held == [tmp_path / "student"] and students[0]["seed"] == 0
    with folder_lock(tmp_path / "student"):  # released after
        pass
    # and the distill command is refused while train's distillation runs
    with folder_lock(tmp_path / "student"):
        code = distill.main(["--teacher", "default", "--out", str(tmp_path / "student"), "--quiet"])
    assert code == 2


# ---- 11: sweep's report and dry run ---------------------------------------------------------------


def test_sweep_refuses_an_empty_report_and_a_dry_run_that_would_fail(capsys, tmp_path):
    argv = ["--out", str(tmp_path / "new"), "--preset", "smoke", "--report"]
    _refused(sweep.main, argv, r"report would be empty", capsys, tmp_path)
    (tmp_path / "garbage.npz").write_text("not a test set")
    argv = ["--out", str(tmp_path / "s"), "--preset", "smoke", "--dry-run", "--testset", str(tmp_path / "garbage.npz")]
    _refused(sweep.main, argv, r"--testset .*garbage.npz: .* is not an .npz test-set file", capsys, tmp_path)
    argv = ["--out", str(tmp_path / "s"), "--preset", "smoke", "--dry-run", "--demos", str(tmp_path / "none")]
    _refused(sweep.main, argv, r"--demos .*none: demonstration set not found", capsys, tmp_path)


# ---- 8: Ctrl-C ------------------------------------------------------------------------------------


def _raise_interrupt(*args, **kwargs):
    raise KeyboardInterrupt


@pytest.mark.filterwarnings("ignore:.*found in sys.modules:RuntimeWarning")  # runpy: run as python -m does
@pytest.mark.parametrize(
    "module, argv, target",
    [
        ("train", ["--out", "{t}/r"], "regrasp_mjx.agents.ddpg_bc.config.make_config"),
        ("demos", ["--n", "2", "--out", "{t}/d"], "regrasp_mjx.core.config_text.parse_overrides"),
        ("distill", ["--teacher", "default", "--out", "{t}/s"], "regrasp_mjx.inference.policy.load_policy"),
        ("compare", ["--no-testset", "--heldout", "2:0"], "regrasp_mjx.inference.policy.load_policy"),
        ("recipe", ["smoke", "--out", "{t}/rc"], "regrasp_mjx.core.cluster.connect"),
        ("sweep", ["--out", "{t}/sw", "--preset", "smoke"], "regrasp_mjx.agents.ddpg_bc.config.make_config"),
        ("testset", ["--n", "2", "--out", "{t}/t.npz"], "regrasp_mjx.world.testsets.make_testset"),
        ("grasps", ["--n", "2", "--out", "{t}/g.npz"], "regrasp_mjx.inference.grasps.GraspLibrary.make"),
        ("export_onnx", ["--out", "{t}/p.onnx"], "regrasp_mjx.inference.policy.load_policy"),
    ],
)
def test_ctrl_c_in_every_command_is_one_line_and_exit_130(module, argv, target, tmp_path, monkeypatch, capsys):
    """Run as ``python -m`` runs them (their ``__main__`` block), interrupted inside their work."""
    owner, _, name = target.rpartition(".")
    try:
        holder = sys.modules[owner] if owner in sys.modules else __import__(owner, fromlist=["x"])
    except ImportError:  # a class attribute
        mod, _, cls = owner.rpartition(".")
        holder = getattr(__import__(mod, fromlist=["x"]), cls)
    monkeypatch.setattr(holder, name, _raise_interrupt)
    monkeypatch.setattr(sys, "argv", [module, *(a.format(t=tmp_path) for a in argv)])
    cache = jax.config.jax_compilation_cache_dir
    try:
        with pytest.raises(SystemExit) as exit_:
            runpy.run_module(f"regrasp_mjx.{module}", run_name="__main__")
    except KeyboardInterrupt:  # not caught: a traceback (and here it would stop the whole test run)
        pytest.fail(f"python -m regrasp_mjx.{module}: Ctrl-C escaped as a KeyboardInterrupt traceback")
    finally:
        jax.config.update("jax_compilation_cache_dir", cache)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 130 and len(err) == 1 and err[0].startswith("interrupted; "), err


class _DropsInterrupts:
    """Sends this process a Ctrl-C while Python runs its ``__del__``, where a KeyboardInterrupt is
    dropped ("Exception ignored"), as it is in XLA's gc callback."""

    def __del__(self):
        _interrupt_here()


def _interrupt_here() -> None:
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(1000):  # the handler runs between these bytecodes, inside the caller
        pass


@pytest.mark.parametrize("where", ["__del__", "gc callback"])
def test_a_ctrl_c_that_python_would_drop_still_stops_the_command(where, capsys):
    import gc

    armed = []

    def callback(phase, info):  # as jax's _xla_gc_callback is called
        if phase == "start" and armed:
            armed.clear()
            _interrupt_here()

    def main():
        if where == "__del__":
            _DropsInterrupts()  # dropped at once: its __del__ runs here
        else:
            armed.append(True)
            gc.collect()
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 10.0:  # the command's work, which a dropped interrupt let go on
            time.sleep(0.01)
        return 0

    gc.callbacks.append(callback)
    t0 = time.perf_counter()
    try:
        assert run_command(main, "again") == 130
    finally:
        gc.callbacks.remove(callback)
    assert time.perf_counter() - t0 < 5.0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["interrupted; again"], err  # no "Exception ignored" traceback


def test_planner_workers_ignore_ctrl_c_and_the_parent_reports_it():
    """Ctrl-C reaches every process of the terminal's group: a worker neither dies nor prints, from
    its start (the signal sent while it still imports) to its work."""
    from regrasp_mjx.planning.pool import PlannerPool
    from tests.pool_faults import faulty_plan

    with PlannerPool(1, plan_fn=faulty_plan, timeout_s=60.0, queue_size=4) as pool:
        worker = pool._workers[0].process
        os.kill(worker.pid, signal.SIGINT)  # while it starts up
        pool.submit({"kind": "ok", "value": 1})
        first = pool.wait(60.0)
        os.kill(worker.pid, signal.SIGINT)  # while it waits for work
        time.sleep(0.5)
        pool.submit({"kind": "ok", "value": 2})
        second = pool.wait(60.0)
    assert [r.ok for r in first + second] == [True, True], first + second
    assert first[0].result["pid"] == second[0].result["pid"] == worker.pid and pool.replaced == 0


# ---- 13: 4x4 poses and the camera loop's frames ----------------------------------------------------

_EG = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
_NEEDLE = np.array([0.0, -0.0054, 0.0, 1.0, 0.0, 0.0, 0.0])
_EE = np.array([0.0, 0.0, 0.013, 1.0, 0.0, 0.0, 0.0])


def test_a_4x4_pose_is_refused_for_what_is_wrong_with_it():
    from regrasp_mjx.robot import dvrk

    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match=r"base \(a 4x4 matrix\) holds NaN or inf; accepted: finite values"):
        dvrk.as_matrix(nan, "base")
    with pytest.raises(ValueError, match=r"pose \(a 4x4 matrix\) is not a rigid transform .* determinant 1.331"):
        dvrk.as_matrix(np.diag([1.1, 1.1, 1.1, 1.0]))
    with pytest.raises(ValueError, match=r"pose has shape \(3, 3\); accepted: a 4x4"):
        dvrk.as_matrix(np.eye(3))
    turn = dvrk.as_matrix(np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    assert np.array_equal(dvrk.as_matrix(turn.astype(np.float32)), turn.astype(np.float32))  # float32 rigid


def test_a_psm_base_with_nan_is_named_before_planning():
    from regrasp_mjx import load_policy
    from regrasp_mjx.inference.queries import PoseError

    nan = np.eye(4)
    nan[2, 2] = np.nan
    policy = load_policy()
    with pytest.raises(PoseError, match=r"psm\['regrasping_base'\] \(a 4x4 matrix\) holds NaN or inf"):
        policy.plan_from_camera(_EG, _EE, _NEEDLE, psm={"regrasping_base": nan})
    with pytest.raises(PoseError, match=r"psm\['grasping_base'\] \(a 4x4 matrix\) is not a rigid transform"):
        policy.plan_from_camera(_EG, _EE, _NEEDLE, psm={"regrasping_base": np.eye(4), "grasping_base": 2 * np.eye(4)})


def test_the_camera_loop_refuses_nan_or_non_rigid_motions_and_a_needle_that_jumps():
    from regrasp_mjx import load_policy
    from regrasp_mjx.inference.camera_loop import MAX_NEEDLE_JUMP_M
    from regrasp_mjx.inference.queries import PoseError

    loop = load_policy().camera_loop(warmup_frames=5)
    assert not loop.update(_EG, _EE, _NEEDLE).ready
    bad = np.eye(4)
    bad[1, 1] = np.nan
    with pytest.raises(PoseError, match=r"moved \(a 4x4 matrix\) holds NaN or inf"):
        loop.update(_EG, _EE, _NEEDLE, moved=bad)
    shear = np.eye(4)
    shear[0, 1] = 0.3
    with pytest.raises(PoseError, match=r"moved \(a 4x4 matrix\) is not a rigid transform"):
        loop.update(_EG, _EE, _NEEDLE, moved=shear)
    jumped = _NEEDLE + np.r_[0.5, 0.0, 0.0, 0, 0, 0, 0]
    with pytest.raises(PoseError, match=r"needle moved 500.0 mm .* accepted: at most 50 mm between frames"):
        loop.update(_EG, _EE, jumped)
    assert loop.frames == 1  # the refused frames were left out
    assert MAX_NEEDLE_JUMP_M == 0.05
    small = _NEEDLE + np.r_[0.002, 0.0, 0.0, 0, 0, 0, 0]  # a 2 mm noisy view is fused
    assert not loop.update(_EG, _EE, small, moved=np.eye(4)).ready and loop.frames == 2


# ---- 14: the API names the argument -----------------------------------------------------------------


def test_the_api_names_the_bad_argument_and_what_is_accepted():
    from regrasp_mjx import load_policy
    from regrasp_mjx.inference.queries import PoseError
    from regrasp_mjx.interfaces import registry

    policy = load_policy()
    with pytest.raises(PoseError, match=r"needle='needle' is not accepted: numbers, \(7,\) or \(B, 7\)"):
        policy.plan("needle", _EE)
    with pytest.raises(PoseError, match=r"start=\[\[1, 2\], \[3\]\] is not accepted"):
        policy.plan(_NEEDLE, [[1, 2], [3]])
    with pytest.raises(ConfigError, match=r"config='x' is not accepted: None, a dict or an ml_collections"):
        registry.load("NeedleRegrasp", config="x")
    with pytest.raises(ConfigError, match=r"config_overrides=3 is not accepted: None or a dict"):
        registry.load("NeedleRegrasp", config_overrides=3)


def test_gym_reset_names_a_bad_episode_option():
    import gymnasium

    import regrasp_mjx.interfaces.gym_envs  # noqa: F401  (registers the ids)

    env = gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")
    for bad in (-1, None, "paper300"):
        with pytest.raises(ConfigError, match=r"options\['episode'\]=.* is not accepted: an Episode of 1 rows"):
            env.reset(options={"episode": bad})


def test_one_closed_loop_step_refuses_a_bad_stop_tolerance_step_or_margin():
    """Issue 70 defect 12: closed_loop_step's stop tolerance, step index and margin are checked."""
    from regrasp_mjx import load_policy
    from regrasp_mjx.core.config import ConfigError

    policy = load_policy()
    needle = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    ee = np.array([0.005, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    for kw, match in (
        ({"stop_tolerance": 5.0}, r"stop_tolerance=5.0 is not accepted: a fraction in \(0, 1\]"),
        ({"stop_tolerance": -1.0}, "stop_tolerance=-1.0 is not accepted"),
        ({"stop_tolerance": float("nan")}, "stop_tolerance=nan is not accepted"),
        ({"t": -1}, "t=-1 is not accepted: the step index, an integer >= 0"),
        ({"t": 1e9}, "t=1000000000.0 is not accepted"),
        ({"t": True}, "t=True is not accepted"),
        ({"clearance_mm": float("inf")}, "clearance_mm=inf is not accepted"),
    ):
        with pytest.raises(ConfigError, match=match):
            policy.closed_loop_step(needle, ee, **kw)
    # a numpy step index is an integer too (the default's jaws open on the way: it takes and returns the opening)
    action, *_ = policy.closed_loop_step(needle, ee, t=np.int64(3), jaw_deg=20.0)
    assert action.shape == (6,)
