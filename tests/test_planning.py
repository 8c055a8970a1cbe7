"""OMPL planning on the host, paths to episodes, the planner pool and the demonstration CLI."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from regrasp_mjx.envs.host import HostChecker, quat_conj, quat_from_rotvec, quat_mul, quat_to_rotvec
from regrasp_mjx.envs.lean_checker import LeanChecker
from regrasp_mjx.planning.episodes import DemosError, load_demos, make_replay, path_to_actions, replay_paths
from regrasp_mjx.planning.ompl_planner import OmplPlanner, PlannerConfig, straight_line
from regrasp_mjx.planning.pool import JobResult, PlannerPool, plan_with_ompl
from tests.fresh_planner import plan_fresh
from tests.pool_faults import faulty_plan

ROOT = Path(__file__).resolve().parent.parent


def _problem(episodes, i):
    return (
        np.r_[episodes.needle_pos[i], episodes.needle_quat[i]],
        np.r_[episodes.start_pos[i], episodes.start_quat[i]],
        np.r_[episodes.goal_pos[i], episodes.goal_quat[i]],
    )


def _dense_free(checker, needle, poses, step=0.05e-3, lever=0.0102):
    """Re-checks a path every 0.05 mm of tool-point motion (5x finer than the planner's checks)."""
    for a, b in zip(poses[:-1], poses[1:]):
        rotvec = quat_to_rotvec(quat_mul(b[3:], quat_conj(a[3:])))
        n = math.ceil((np.linalg.norm(b[:3] - a[:3]) + lever * np.linalg.norm(rotvec)) / step) + 1
        for s in np.linspace(0.0, 1.0, n):
            if checker.collides(
                needle[:3], needle[3:], a[:3] + s * (b[:3] - a[:3]), quat_mul(quat_from_rotvec(s * rotvec), a[3:])
            ):
                return False
    return True


@pytest.fixture(scope="module")
def bit_reverse_plans(paper_testset):
    episodes, _ = paper_testset
    planner = OmplPlanner(PlannerConfig(planner="BITstar", direction="reverse", budget_s=5.0), seed=1)
    return [(i, planner.plan(*_problem(episodes, i))) for i in range(4)]


def test_planned_paths_are_collision_free_when_rechecked_densely(paper_testset, bit_reverse_plans):
    """OMPL checks a motion every 0.25 mm of jaw motion: enough that no path passes through the wire,
    not that none grazes it. At margin 0 a densely re-checked path may touch by a few microns (7 of
    BIT*'s 300 paper300 paths, up to 1.6 um: experiments/RESULTS.md); with a clearance margin the
    same planner's paths never touch."""
    episodes, _ = paper_testset
    checker = HostChecker()
    for i, result in bit_reverse_plans:
        assert result.solved, result.error
        needle, start, goal = _problem(episodes, i)
        np.testing.assert_allclose(result.poses[0], start, atol=1e-9)  # reversed back: start first
        np.testing.assert_allclose(result.poses[-1], goal, atol=1e-9)
        assert _dense_free(checker, needle, result.poses) or checker.path_clearance(needle, result.poses) > -5e-6
    planner = OmplPlanner(
        PlannerConfig(planner="BITstar", direction="reverse", budget_s=5.0), HostChecker(clearance_mm=0.05), seed=1
    )
    for i, _ in bit_reverse_plans:
        needle, start, goal = _problem(episodes, i)
        result = planner.plan(needle, start, goal)
        assert result.solved and _dense_free(checker, needle, result.poses)
        assert checker.path_clearance(needle, result.poses) >= 0.0


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_rrt_connect_plans_start_to_goal_around_the_needle(paper_testset, direction):
    """The classical anchor of Table II (ours, not the paper's): its first path, shortcut or not,
    runs start to goal and keeps off the needle when re-checked densely (with a 50 um margin)."""
    episodes, _ = paper_testset
    checker = HostChecker()
    for simplify in (0.0, 0.2):
        cfg = PlannerConfig(planner="RRTConnect", direction=direction, budget_s=5.0, simplify_s=simplify)
        planner = OmplPlanner(cfg, HostChecker(clearance_mm=0.05), seed=2)
        for i in range(3):
            needle, start, goal = _problem(episodes, i)
            result = planner.plan(needle, start, goal)
            assert result.solved, result.error
            np.testing.assert_allclose(result.poses[0], start, atol=1e-9)
            np.testing.assert_allclose(result.poses[-1], goal, atol=1e-9)
            assert _dense_free(checker, needle, result.poses)
            assert result.path_length_mm >= np.linalg.norm(goal[:3] - start[:3]) * 1e3 - 1e-9


@pytest.mark.parametrize("margin_mm, radius_mm, wire_mm", [(0.0, None, None), (0.1, None, None), (0.0, 9.0, 0.3)])
def test_the_lean_checker_gives_the_host_checkers_verdicts(paper_testset, margin_mm, radius_mm, wire_mm):
    """LeanChecker (compiled capsule tests) against HostChecker (CPU MuJoCo) on poses between each
    problem's start and goal, shaken so that about half collide: the same verdict on every pose, at
    a margin too and for another needle (the scene's scaled against a scene built for that needle)."""
    episodes, _ = paper_testset
    size = (None if radius_mm is None else radius_mm * 1e-3, None if wire_mm is None else wire_mm * 1e-3)
    host = HostChecker(clearance_mm=margin_mm).for_needle(*size)
    lean = LeanChecker(clearance_mm=margin_mm).for_needle(*size)
    rng = np.random.default_rng(0)
    verdicts = []
    for i in range(40):
        needle, start, goal = _problem(episodes, i)
        for _ in range(12):
            s = rng.uniform(0.0, 1.2)
            pos = start[:3] + s * (goal[:3] - start[:3]) + rng.normal(0.0, 0.5e-3, 3)
            quat = start[3:] + s * (goal[3:] - start[3:]) + rng.normal(0.0, 0.05, 4)
            quat /= np.linalg.norm(quat)
            verdicts.append(
                (host.collides(needle[:3], needle[3:], pos, quat), lean.collides(needle[:3], needle[3:], pos, quat))
            )
    host_v, lean_v = np.array(verdicts).T
    assert 0.2 < host_v.mean() < 0.8  # both kinds of pose were tested
    np.testing.assert_array_equal(lean_v, host_v)


def test_the_lean_checker_checks_a_motion_as_ompl_interpolates_it(paper_testset):
    """``motion_collides`` tests the whole motion OMPL interpolates (positions linear, rotations
    slerped the shorter way): the host checker's continuous verdict, and colliding wherever one of
    OMPL's ``k / n`` states collides."""
    episodes, _ = paper_testset
    lean, host, seen = LeanChecker(), HostChecker(), set()
    for i in range(10):
        needle, start, goal = _problem(episodes, i)
        b = goal.copy()
        b[3:] = -b[3:] if i % 2 else b[3:]  # the same rotation with the other sign: the shorter way still
        placed = lean.place(needle)
        n = 25
        rotvec = quat_to_rotvec(quat_mul(goal[3:], quat_conj(start[3:])))
        poses = [
            np.r_[start[:3] + k / n * (goal[:3] - start[:3]), quat_mul(quat_from_rotvec(k / n * rotvec), start[3:])]
            for k in range(1, n + 1)
        ]
        sampled = any(lean.pose_collides(placed, *p) for p in poses)
        verdict = lean.motion_collides(placed, start, b)
        assert verdict == host.motion_collides_between(needle, start, b)
        assert verdict or not sampled  # a colliding state is never inside a motion called free
        seen.add(verdict)
    assert seen == {True, False}  # motions through the needle and clear of it
    assert not lean.motion_collides(placed, start, start)  # a start that is free stays free


@pytest.mark.parametrize("planner", ["RRTConnect", "BITstar"])
def test_a_planner_with_the_lean_checker_plans_the_same_paths(paper_testset, planner):
    """The same seed and the same verdicts: RRT-Connect (shortcut too) and BIT* return the very
    paths they return over CPU MuJoCo. OMPL's shortcutting runs until it converges or its time is up
    (`simplifySolution(seconds)`): given 2 s, both checkers converge (it stops early when nothing
    improves); at the default 0.2 s a loaded 2-core machine stopped the slower MuJoCo checks early
    once (7 waypoints against 8)."""
    episodes, _ = paper_testset
    problems = [_problem(episodes, i) for i in range(4)]
    assert isinstance(OmplPlanner(PlannerConfig(checker="lean")).checker, LeanChecker)
    for simplify in (0.0, 2.0) if planner == "RRTConnect" else (0.0,):
        paths = {}
        for checker in ("mujoco", "lean"):  # each in a fresh process: OMPL seeds once per process
            cfg = PlannerConfig(
                planner=planner, direction="forward", budget_s=5.0, simplify_s=simplify, checker=checker
            )
            paths[checker] = plan_fresh(cfg, 3, problems)
        for a, b in zip(paths["mujoco"], paths["lean"]):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)


def test_a_demonstration_replays_to_success_with_plus_one_last(env, paper_testset, bit_reverse_plans):
    episodes, _ = paper_testset
    rows = [i for i, _ in bit_reverse_plans]
    eps = jax.tree.map(lambda x: x[np.asarray(rows)], episodes)
    ok, demos = replay_paths(env, make_replay(env), eps, [r.poses for _, r in bit_reverse_plans], batch=4)
    assert ok.all()
    for d in demos:
        assert d["reward"][-1] == pytest.approx(1.0) and d["done"][-1] == 1.0
        np.testing.assert_allclose(d["reward"][:-1], -0.02, atol=1e-7)
        assert np.all(d["done"][:-1] == 0.0) and np.abs(d["action"]).max() <= 1.0
        np.testing.assert_allclose(d["obs"][1:], d["next_obs"][:-1], atol=1e-7)


def test_path_to_actions_by_hand():
    ident = np.array([1.0, 0, 0, 0])
    # 1.2 mm along x with 0.5 mm steps: ceil(2.4) = 3 steps of 0.4 mm, action 0.8.
    poses = np.array([np.r_[0, 0, 0, ident], np.r_[0.0012, 0, 0, ident]])
    np.testing.assert_allclose(path_to_actions(poses, 0.0005, math.radians(3)), [[0.8, 0, 0, 0, 0, 0]] * 3, atol=1e-6)
    # 10 deg about z with 3 deg steps: ceil(3.33) = 4 steps of 2.5 deg, action 2.5 / 3.
    q = quat_from_rotvec(np.array([0, 0, math.radians(10)]))
    poses = np.array([np.r_[0, 0, 0, ident], np.r_[0, 0, 0, q]])
    np.testing.assert_allclose(
        path_to_actions(poses, 0.0005, math.radians(3)), [[0, 0, 0, 0, 0, 2.5 / 3]] * 4, atol=1e-6
    )


def test_straight_line_baseline(paper_testset):
    episodes, _ = paper_testset
    checker = HostChecker()
    needle, _, goal = _problem(episodes, 0)
    assert straight_line(checker, needle, goal, goal).solved
    # From the goal pose shifted 3 mm along -y_e (past jaw a) back to the goal: jaw a crosses the wire.
    rot = np.zeros(9)
    import mujoco

    mujoco.mju_quat2Mat(rot, goal[3:])
    shifted = goal.copy()
    shifted[:3] -= 0.003 * rot.reshape(3, 3)[:, 1]
    result = straight_line(checker, needle, shifted, goal)
    assert not result.solved and "collision" in result.error


def test_bad_planner_inputs():
    from regrasp_mjx.core.config import ConfigError

    with pytest.raises(ConfigError, match="planner='RRT' is not accepted"):  # every config raises ConfigError
        PlannerConfig(planner="RRT")
    with pytest.raises(ValueError, match="budget_s=0 is not accepted"):
        PlannerConfig(budget_s=0)
    with pytest.raises(ConfigError, match="checker='fcl' is not accepted: one of"):
        PlannerConfig(checker="fcl")
    with pytest.raises(ValueError, match="clearance_mm=-1 is not accepted"):
        LeanChecker(clearance_mm=-1)
    planner = OmplPlanner(PlannerConfig(budget_s=0.1))
    good = np.r_[0, 0, 0, 1.0, 0, 0, 0]
    with pytest.raises(ValueError, match="start pose must be 7 finite numbers"):
        planner.plan(good, np.r_[np.nan, 0, 0, 1.0, 0, 0, 0], good)
    with pytest.raises(ValueError, match="goal pose: quaternion norm 2"):
        planner.plan(good, good, np.r_[0, 0, 0, 2.0, 0, 0, 0])


# ---- the pool ----------------------------------------------------------------------------------
def test_pool_survives_a_worker_that_raises_hangs_or_crashes():
    # 8 s: long enough for a fresh worker to import and start a job on a slow, busy 2-core machine
    with PlannerPool(2, plan_fn=faulty_plan, timeout_s=8.0, queue_size=8) as pool:
        jobs = {
            pool.submit({"kind": k, "value": v}, payload=k + str(v)): k
            for k, v in [("ok", 1), ("raise", 0), ("hang", 0), ("crash", 0), ("ok", 2), ("ok", 3)]
        }
        t0 = time.monotonic()
        results = pool.wait(30.0)
        assert time.monotonic() - t0 < 25.0
        by_kind = {jobs[r.job_id] + r.payload[-1]: r for r in results}
        assert len(results) == 6 and pool.in_flight == 0
        assert by_kind["ok1"].ok and by_kind["ok1"].result["value"] == 2
        assert by_kind["ok3"].ok and by_kind["ok3"].result["value"] == 6
        assert not by_kind["raise0"].ok and "planner exploded" in by_kind["raise0"].error
        assert not by_kind["hang0"].ok and "timed out" in by_kind["hang0"].error
        assert not by_kind["crash0"].ok and "worker died (exit code 3)" in by_kind["crash0"].error
        assert pool.replaced == 2
        # The pool still works after the replacements.
        pool.submit({"kind": "ok", "value": 5})
        assert [r.result["value"] for r in pool.wait(30.0)] == [10]
        pids = [w.process.pid for w in pool._workers]
    for pid in pids:  # no process outlives the pool
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text().lower()


def test_pool_submit_never_blocks_and_refuses_beyond_its_queue():
    with PlannerPool(1, plan_fn=faulty_plan, timeout_s=60.0, queue_size=2) as pool:
        t0 = time.monotonic()
        ids = [pool.submit({"kind": "hang", "value": 0}) for _ in range(6)]
        assert time.monotonic() - t0 < 1.0
        # One runs, two wait; the rest are refused.
        assert ids[:3] == [0, 1, 2] and ids[3:] == [None, None, None]
        assert pool.collect() == []


# ---- the demonstration CLI ----------------------------------------------------------------------
def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    """Whether the process runs (an exited one that nobody reaped yet, a zombie, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
def test_demos_cli_killed_and_restarted_ends_with_exactly_n_distinct(tmp_path):
    out = tmp_path / "demos"
    cmd = [
        sys.executable,
        "-m",
        "regrasp_mjx.demos",
        "--n",
        "24",
        "--workers",
        "1",
        "--planner",
        "PRMstar",
        "--budget-s",
        "5",
        "--out",
        str(out),
        "--quiet",
    ]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and len(list((out / "plans").glob("p*.npz"))) < 6:
        time.sleep(0.2)
    workers = _children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = {p.name: p.stat().st_mtime_ns for p in (out / "plans").glob("p*.npz")}
    assert len(before) >= 6 and not (out / "demos.npz").exists()
    # orphaned workers notice their parent is gone and exit once their plan in hand ends (within a
    # few seconds; 20 s for a loaded 2-core CI machine: one that never exits fails)
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.2)
    assert not [w for w in workers if _alive(w)], "a planner worker outlived its parent"

    # resumed over the lean checker: the same verdicts, so not other settings
    done = subprocess.run([*cmd, "--checker", "lean"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    demos = load_demos(out)
    assert demos.num_episodes == 24 and len(set(demos.problem_index.tolist())) == 24
    for name, mtime in before.items():  # finished plans were kept, not recomputed
        assert (out / "plans" / name).stat().st_mtime_ns == mtime
    assert demos.obs.shape == (int(demos.length.sum()), 21)
    ends = np.cumsum(demos.length) - 1
    np.testing.assert_allclose(demos.reward[ends], 1.0)
    assert demos.meta["settings"]["planner"]["planner"] == "PRMstar"
    # The same folder with other settings is refused, not mixed.
    other = subprocess.run(
        cmd[:-3] + ["--seed", "9", "--out", str(out), "--quiet"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert other.returncode == 2 and "other settings" in other.stderr


def test_load_demos_errors(tmp_path):
    with pytest.raises(DemosError, match="demonstration set not found"):
        load_demos(tmp_path)
    np.savez(tmp_path / "demos.npz", meta=np.array("{}"), obs=np.zeros((2, 21)))
    with pytest.raises(DemosError, match="lacks"):
        load_demos(tmp_path)


@pytest.mark.slow
def test_demos_cli_stops_with_the_error_when_every_plan_fails(tmp_path):
    """A machine without OMPL (or a broken planner) must not plan failures forever: the build stops
    after ALL_FAILED errors in a row and says what the error was."""
    fake = tmp_path / "site" / "ompl"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('no OMPL on this machine')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), os.environ.get("PYTHONPATH", "")])}
    argv = [
        sys.executable,
        "-m",
        "regrasp_mjx.demos",
        "--n",
        "4",
        "--workers",
        "2",
        "--out",
        str(tmp_path / "d"),
        "--quiet",
    ]
    r = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 2, r.stderr
    assert "the first 16 plans all failed with an error, the last: ImportError: no OMPL on this machine" in r.stderr


class _InstantPool:
    """A PlannerPool whose workers finish every plan the moment it is submitted (so nothing is ever
    in flight): the demonstration builder once refilled "while in flight < 4 workers" and never
    stopped submitting when its workers kept up (31 lean-checker workers on 32 cores)."""

    def __init__(self, workers, options, timeout_s):
        self.options, self.submitted, self._done = options, 0, []

    def submit(self, problem, payload=None):
        self.submitted += 1
        if self.submitted > 100:
            raise AssertionError("the builder kept submitting without collecting")
        self._done.append(JobResult(self.submitted, True, plan_with_ompl(problem, self.options), "", payload))
        return self.submitted

    def collect(self):
        out, self._done = self._done, []
        return out

    in_flight = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


@pytest.mark.slow  # 17 s on the 2-core VM (the replay's compile)
def test_demos_stop_submitting_when_the_workers_keep_up(tmp_path, monkeypatch):
    from regrasp_mjx.planning import demonstrations

    pools = []
    monkeypatch.setattr(demonstrations, "PlannerPool", lambda *a, **k: pools.append(_InstantPool(*a, **k)) or pools[-1])
    path = demonstrations.build(6, tmp_path / "d", workers=2, budget_s=2.0, checker="lean", quiet=True)
    assert load_demos(path).num_episodes == 6
    # one refill of 4 x workers, collected and verified: not a plan more
    assert pools[0].submitted == 8
