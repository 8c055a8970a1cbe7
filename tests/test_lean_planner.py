"""The lean one-query CPU path (numba) against the JAX planning program: the same verdict on every
problem, the same actions up to float32 rounding, the same trajectories; and Policy.plan's choice
of engine. The full agreement on a test set is ``python -m regrasp_mjx.evaluate --agreement``
(on paper300, held-out 3000 and general1000: experiments/results/bench_plan/agreement.md)."""

from __future__ import annotations

import dataclasses
import logging

import jax
import numpy as np
import pytest

from regrasp_mjx.envs import lean_collision, lean_geometry
from regrasp_mjx.envs.lean_geometry import nearest_grasp
from regrasp_mjx.inference import planner, plans
from regrasp_mjx.inference.grasps import GraspLibrary
from regrasp_mjx.inference.plans import default_goal
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.queries import TASK_FIELDS, PoseError
from regrasp_mjx.inference.testset_plans import engine_agreement
from regrasp_mjx.world.sampling import episode_poses, load_testset
from regrasp_mjx.world.testsets import make_testset

# The JAX path computes in float32 and this one its geometry in float64 (the network in float32 in
# both): the observations round differently, the network amplifies it and a plan carries it along.
# Seen (experiments/results/bench_plan/agreement.md): up to 2.4e-5 in an action of a plan that ends
# before the horizon on the default and the generalist, 1.8e-4 by the last step of a 100-step
# time-out; and on an AMD EPYC host (XLA compiles for the host's CPU, so the JAX side rounds
# differently there), 1.05e-4 by the end of ensemble3's 36-step plan of paper300 row 53 (1.4e-4
# with the lean code before 2026-11-25). The verdicts are the contract; the actions only to this.
ACTION_ATOL = 2e-4
ACTION_ATOL_TIME_OUT = 1e-3
# poses carry the actions' differences step after step (seen: 1.1e-5 on that 36-step plan)
POSE_ATOL, POSE_ATOL_TIME_OUT = 5e-5, 1e-4


def _agree(policy, episodes, shield=True):
    """Each problem planned one at a time by the lean path and all at once by the JAX path."""
    r = engine_agreement(policy, episodes, shield)
    assert r["differ"] == []  # the same verdicts, and trajectories of the plan's own length
    late = r["time_out"]
    assert r["action_diff"][~late].max() <= ACTION_ATOL and r["action_diff"].max() <= ACTION_ATOL_TIME_OUT
    assert r["pose_diff"][~late].max() <= POSE_ATOL and r["pose_diff"].max() <= POSE_ATOL_TIME_OUT
    # each step's translation within ACTION_ATOL x 0.5 mm (the largest step) of the JAX path's
    assert np.all(r["path_diff_mm"] <= np.maximum(1e-4, 0.5 * ACTION_ATOL * r["steps"]))
    return r["batch"]


def test_the_lean_path_gives_the_jax_paths_verdicts_on_paper300_shielded_and_bare():
    # student_v3 (the default until 2026-11-29), whose bare network collides on a few rows, so that the
    # shield is exercised; a policy whose jaws open on the way, as the default's, in tests/test_lean_jaw.py
    policy = load_policy("student_v3")
    episodes = load_testset("paper300")[0]
    shielded = _agree(policy, episodes)
    assert shielded.success.mean() == pytest.approx(1.0)
    bare = _agree(policy, episodes, shield=False)
    assert bare.collision.sum() >= 1  # the bare network collides on a few: the shield is exercised above


@pytest.mark.slow
def test_the_lean_path_on_held_out_problems_an_ensemble_and_a_general_policy():
    default = load_policy("default")
    _agree(default, make_testset(100, 2022, default.env_config))
    _agree(load_policy("ensemble3"), jax_rows(load_testset("paper300")[0], 60))
    _agree(load_policy("general"), jax_rows(load_testset("general1000")[0], 100))


def jax_rows(episodes, n):
    return jax.tree.map(lambda x: x[:n], episodes)


def test_policy_plan_takes_the_lean_path_for_one_query_on_the_cpu():
    policy = load_policy("exact")
    needle, start, goal = (x[0] for x in episode_poses(load_testset("paper300")[0]))
    auto = policy.plan(needle, start, goal)
    assert ("lean", True) in policy._programs and (False, True) not in policy._programs
    ref = policy.plan(needle, start, goal, engine="jax")
    assert auto.success == ref.success and auto.steps == ref.steps
    assert auto.poses.shape == ref.poses.shape == (ref.steps + 1, 7)
    for field in dataclasses.fields(plans.Plan):  # the lean Plan is built without __init__: every field, typed alike
        mine, theirs = getattr(auto, field.name), getattr(ref, field.name)
        assert type(mine) is type(theirs) and getattr(mine, "dtype", None) == getattr(theirs, "dtype", None), field
    batch = policy.plan(needle[None], start[None], goal[None])  # a batch of one: still lean, batch axis kept
    assert batch.success.shape == (1,) and batch.steps[0] == ref.steps
    with pytest.raises(ValueError, match="engine='fast' is not accepted; accepted: 'auto', 'jax', 'lean'"):
        policy.plan(needle, start, goal, engine="fast")
    with pytest.raises(ValueError, match="engine='lean' plans one query at a time; got 2"):
        policy.plan(np.stack([needle] * 2), np.stack([start] * 2), np.stack([goal] * 2), engine="lean")


def test_one_query_on_the_lean_path_has_the_same_shape_where_jax_runs_on_a_gpu(monkeypatch):
    """With JAX on a GPU, ``engine="lean"`` plans one query after the batch checks (there is no fast
    single-query entry): its Plan still holds numpy scalars and one trajectory, as on the CPU."""
    policy = load_policy("default")
    needle, start, goal = (x[3] for x in episode_poses(load_testset("paper300")[0]))
    cpu = policy.plan(needle, start, goal, engine="lean")
    monkeypatch.setattr(plans, "auto_engine", lambda queries, policy=None: "jax")  # what a GPU backend answers
    gpu = policy.plan(needle, start, goal, engine="lean")
    assert np.ndim(gpu.success) == 0 and np.ndim(gpu.steps) == 0 and gpu.poses.shape == (int(cpu.steps) + 1, 7)
    assert gpu.success == cpu.success and gpu.steps == cpu.steps
    np.testing.assert_array_equal(gpu.actions, cpu.actions)
    assert policy.plan(needle[None], start[None], goal[None], engine="lean").steps.shape == (1,)


def test_the_default_goal_on_the_lean_path_is_the_jax_one():
    """Policy.plan without a goal computes it from the goal grasp: in numba on the lean path."""
    policy = load_policy("general")
    lean = policy.lean(True)
    rng = np.random.default_rng(3)
    needle, _, _ = episode_poses(load_testset("general1000")[0])
    lo, hi = (np.array(x) for x in zip(*[policy.trained_ranges()[k] for k in TASK_FIELDS[:4]]))
    grasp = rng.uniform(lo, hi, (50, 4)) * np.array([1, 1e-3, 1, 1])
    radii = rng.uniform(0.004, 0.012, 50)
    ref = default_goal(needle[:50], grasp, np.stack([radii, radii], 1))
    for i in range(50):
        np.testing.assert_allclose(lean.goal(needle[i], grasp[i], radii[i]), ref[i], atol=2e-6)


def test_the_collision_test_gives_the_verdict_of_the_closest_pair():
    """lean_collision.collides (bounding spheres, chord groups, early exit) against the minimum over
    every counted pair, at thresholds just below and above each pose's own smallest distance: a
    bound that skipped the closest pair would miss the collision just above it."""
    policy = load_policy("general")  # varies needles: the chords and their bounds are scaled
    geo = policy.lean(True).geo
    needle, start, goal = episode_poses(load_testset("general1000")[0])
    rng = np.random.default_rng(5)
    tool, tool_mid = np.empty_like(geo.tool_local), np.empty((len(geo.tool_local), 3))
    checked = 0
    for i in range(40):
        radius, wire = rng.uniform(0.004, 0.012), rng.uniform(0.00015, 0.00035)
        n = needle[i] / np.r_[1, 1, 1, [np.linalg.norm(needle[i, 3:])] * 4]
        fixed = lean_collision.fixed_ends(geo, True, tuple(n[:3]), tuple(n[3:]), radius, wire)
        for ee in (start[i], goal[i], start[i] + np.r_[rng.normal(0, 2e-3, 3), 0, 0, 0, 0]):
            q = ee[3:] / np.linalg.norm(ee[3:])
            m = np.array(lean_geometry.matrix(tuple(q))).reshape(3, 3)
            placed = ee[:3] + geo.tool_local @ m.T  # [T, 2, 3]
            closest = min(
                lean_collision.segment_distance(placed, t, fixed.other, o) - fixed.sums[geo.pair_index[t, o]]
                for t in range(len(placed))
                for o in range(len(fixed.other))
            )
            for threshold, expected in ((closest - 1e-9, False), (closest + 1e-9, True)):
                got = lean_collision.collides(geo, fixed, tuple(ee[:3]), tuple(q), tool, tool_mid, threshold)
                assert got == expected, (i, threshold)
            checked += 1
    assert checked == 120


def test_the_nearest_grasp_is_the_librarys():
    """The compiled nearest-grasp search (a float32 bound, then exact distances) finds the distance
    GraspLibrary.nearest finds, on test-set needles and on needles moved off the library."""
    library = GraspLibrary.default()
    needle = episode_poses(load_testset("paper300")[0])[0]
    rng = np.random.default_rng(2)
    moved = needle + np.c_[rng.normal(0, 2e-3, (300, 3)), rng.normal(0, 0.2, (300, 4))]
    for poses in (needle, moved):
        poses = np.c_[poses[:, :3], poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)]
        got = np.array([nearest_grasp(*library.unit_arrays, p) for p in poses])
        np.testing.assert_allclose(got, library.nearest(poses)[1], atol=1e-9)


def test_a_single_query_names_its_bad_pose_as_a_batch_does():
    """The lean path checks poses inside its compiled call; what it refuses gets the checks' message."""
    policy = load_policy("default")
    needle, start, goal = (x[0] for x in episode_poses(load_testset("paper300")[0]))
    bad_goal = goal.copy()
    bad_goal[0] = np.nan  # a NaN where no goal is given would be read as "the default goal" if unchecked
    for args, message in (
        ((needle, start, bad_goal), "goal has NaN or inf"),
        ((np.r_[needle[:3], needle[3:] * 1.1], start, goal), "needle: quaternion norm"),
        ((needle, np.r_[start[:6], np.inf], goal), "start has NaN or inf"),
    ):
        with pytest.raises(PoseError, match=message):
            policy.plan(*args)
    far = start.copy()
    far[:3] *= 1000  # millimetres given as metres
    with pytest.warns(UserWarning, match="mm from its needle"):
        plan = policy.plan(needle, far, goal)
    assert plan.nearest_grasp_distance == pytest.approx(
        policy.plan(needle, start, goal, engine="jax").nearest_grasp_distance
    )


def test_a_motion_proved_clear_is_clear_all_along_it():
    """lean_collision.interval_collides: its verdict is that of the pairs' lower bounds over the
    interval (continuous.interval_low, float64), exact to 1e-9 m either side of the threshold, and
    where it proves an interval clear, every pose of the interval is (sampled far finer)."""
    from regrasp_mjx.world import continuous

    policy = load_policy("general")
    planner = policy.lean(True)
    geo, max_dp, max_drot = planner.geo, planner.consts[0], planner.consts[1]
    needle, start, _ = episode_poses(load_testset("general1000")[0])
    rng = np.random.default_rng(11)
    tool, tool_mid = np.empty_like(geo.tool_local), np.empty((len(geo.tool_local), 3))
    levers = continuous.levers(geo.tool_local)

    def place(p, q):
        return p + geo.tool_local @ np.array(lean_geometry.matrix(tuple(q))).reshape(3, 3).T

    def pairs(fixed, placed):  # [T, O, 3] closest-point vectors and [T, O] signed distances
        gap = np.array(
            [
                [lean_geometry.segment_gap(placed, t, fixed.other, o) for o in range(len(fixed.other))]
                for t in range(len(placed))
            ]
        )
        return gap, np.linalg.norm(gap, axis=-1) - fixed.sums[geo.pair_index]

    proved = directional = 0
    for i in range(30):
        radius, wire = rng.uniform(0.004, 0.012), rng.uniform(0.00015, 0.00035)
        n = needle[i] / np.r_[1, 1, 1, [np.linalg.norm(needle[i, 3:])] * 4]
        fixed = lean_collision.fixed_ends(geo, True, tuple(n[:3]), tuple(n[3:]), radius, wire)
        for _ in range(4):
            p0 = start[i, :3] + rng.normal(0, 1.5e-3, 3)
            q0 = start[i, 3:] / np.linalg.norm(start[i, 3:])
            dp, w = rng.uniform(-1, 1, 3) * max_dp, rng.uniform(-1, 1, 3) * max_drot
            h, s = 0.5 ** rng.integers(1, 4), 0.5
            at_q = lean_geometry.qmul(lean_geometry.qexp(*(s * w)), tuple(q0))
            placed = place(p0 + s * dp, at_q)
            gap, d = pairs(fixed, placed)
            low = continuous.interval_low(placed, p0 + s * dp, fixed.other, gap, d, h, dp, w, levers, xp=np)
            moved = d - h * (np.linalg.norm(dp) + np.linalg.norm(w) * levers)[:, None]
            directional += int(low.min() > moved.min() + 1e-12)  # the directional bound decided
            edge = float(low.min()) - continuous.SLACK
            threshold = edge - rng.uniform(0, 3e-3)  # near the margin: both verdicts occur
            args = (tuple(p0 + s * dp), at_q, tool, tool_mid)
            for bump, expected in ((-1e-9, False), (1e-9, True)):  # exact at the bounds' margin
                got = lean_collision.interval_collides(geo, fixed, *args, edge + bump, h, tuple(dp), tuple(w))
                assert got == expected, (i, bump)
            if lean_collision.interval_collides(geo, fixed, *args, threshold, h, tuple(dp), tuple(w)):
                continue
            proved += 1
            for u in np.linspace(s - h, s + h, 33):
                q = lean_geometry.qmul(lean_geometry.qexp(*(u * w)), tuple(q0))
                assert pairs(fixed, place(p0 + u * dp, q))[1].min() >= threshold, (i, u)
    assert proved >= 30 and directional >= 10


def test_a_querys_task_keywords_are_checked_once_and_kept():
    """TaskRanges.keywords_vector keeps the vector of keywords it has seen (each query of a test set
    passes its needle's radii): the same values give the same vector, other values their own, and
    values it refuses are refused again."""
    ranges = load_policy("general").task_ranges
    first = ranges.keywords_vector({"needle_radius_mm": np.float64(6.0), "wire_radius_mm": 0.2})
    again = ranges.keywords_vector({"needle_radius_mm": 6.0, "wire_radius_mm": np.float64(0.2)})
    other = ranges.keywords_vector({"needle_radius_mm": 7.0, "wire_radius_mm": 0.2})
    assert again is first and first[4] == pytest.approx(6e-3) and other[4] == pytest.approx(7e-3)
    for _ in range(2):  # out of range, not a scalar: None both times (the caller's checks name it)
        assert ranges.keywords_vector({"needle_radius_mm": 99.0}) is None
        assert ranges.keywords_vector({"needle_radius_mm": np.array([6.0, 7.0])}) is None


def test_the_first_lean_plan_in_a_process_says_it_prepares_the_planner_once(monkeypatch, capsys, caplog):
    """Issue 70, defect 16: the lean planner's numba compile (about 20 s on a 2-core CPU without numba's
    cache) is announced by one line before it, once per process: on stderr where logging is not set up,
    through the ``regrasp_mjx`` logger where it is, and not at all with that logger above INFO."""
    needle, start, goal = (x[0] for x in episode_poses(load_testset("paper300")[0]))

    def first_plans():
        monkeypatch.setattr(planner, "_said", False)  # as in a fresh process
        for policy in (load_policy("default"), load_policy("default")):  # the second builds its own planner
            policy.plan(needle, start, goal)
            policy.plan(needle, start, goal, shield=False)

    monkeypatch.setattr(planner.LOG, "hasHandlers", lambda: False)  # no logging set up (pytest sets it up)
    first_plans()
    out, err = capsys.readouterr()
    assert err.count(planner.LEAN_PREPARES) == 1 and planner.LEAN_PREPARES not in out
    package = logging.getLogger("regrasp_mjx")
    monkeypatch.setattr(package, "level", logging.WARNING)  # what setLevel(logging.WARNING) sets
    first_plans()
    assert planner.LEAN_PREPARES not in capsys.readouterr().err
    monkeypatch.undo()  # logging as pytest set it up: the line goes to the logger at INFO
    monkeypatch.setattr(planner, "_said", False)
    with caplog.at_level(logging.INFO, logger="regrasp_mjx"):
        load_policy("default").plan(needle, start, goal)
    assert [r.getMessage() for r in caplog.records if r.name == planner.LOG.name] == [planner.LEAN_PREPARES]
    assert planner.LEAN_PREPARES not in capsys.readouterr().err
