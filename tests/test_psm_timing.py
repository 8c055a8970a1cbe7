"""Timed joint trajectories at the dVRK's own limits: a hand-worked bang-bang move, every sample
within the limits and through every waypoint, a shipped plan timed and re-checked clear, the
grasping tool put in the executed motion's way caught, and the refusals."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.robot import dvrk, psm_timing
from regrasp_mjx.robot.executed_motion import (
    MotionRefused,
    check_motion,
    time_executed,
    time_plan,
    time_waypoints,
    tool_poses,
)
from regrasp_mjx.robot.psm_timing import A_MAX, HEADROOM, V_MAX, limit_ratio, sample_const_accel, time_joints
from regrasp_mjx.robot.topp import Spline
from regrasp_mjx.world.sampling import episode_poses
from tests.test_clearance import _as_pose


def test_one_insertion_move_is_the_hand_worked_bang_bang_profile():
    """0.05 m of insertion alone, at rest at both ends, a = 0.2 m/s^2 x HEADROOM: the distance is
    below v^2 / a (0.2 m), so the fastest move accelerates for half the way and brakes for the
    other half, T = 2 sqrt(d / a) = 1.0153 s, peak speed sqrt(d a) = 0.0985 m/s."""
    q0 = np.array([0.1, -0.2, 0.10, 0.3, 0.0, 0.0])
    q1 = q0 + [0, 0, 0.05, 0, 0, 0]
    timed = time_joints([q0, q1], gridpoints=200)  # the fine grid: within 1 % of the optimum
    assert time_joints([q0, q1]).duration_s == pytest.approx(timed.duration_s, rel=0.03)  # the default grid
    a = 0.2 * HEADROOM
    assert timed.duration_s == pytest.approx(2 * math.sqrt(0.05 / a), rel=0.01)
    assert np.abs(timed.qd[:, 2]).max() == pytest.approx(math.sqrt(0.05 * a), rel=0.01)
    np.testing.assert_allclose(timed.q[0], q0, atol=1e-12)
    np.testing.assert_allclose(timed.q[-1], q1, atol=1e-9)
    np.testing.assert_allclose(timed.qd[[0, -1]], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.diff(timed.t[:-1]), 1e-3, atol=1e-12)  # the controller's 1 kHz
    np.testing.assert_allclose(timed.q[:, [0, 1, 3, 4, 5]], np.tile(q0[[0, 1, 3, 4, 5]], (len(timed.t), 1)), atol=1e-9)


def test_every_sample_keeps_the_dvrk_limits_and_passes_every_waypoint():
    rng = np.random.default_rng(3)
    waypoints = dvrk.Q_MIN + (dvrk.Q_MAX - dvrk.Q_MIN) * (0.4 + 0.2 * rng.random((6, 6)))
    timed = time_joints(waypoints, rate_hz=500.0)
    assert np.all(np.abs(timed.qd) <= V_MAX * (1 + 1e-9)) and np.all(np.abs(timed.qdd) <= A_MAX * (1 + 1e-9))
    step = V_MAX / 500.0  # a sample period at full speed
    for w in waypoints:  # the path goes through each waypoint: some sample is within one period of it
        assert np.min(np.max(np.abs(timed.q - w) / step, axis=1)) <= 1.0
    # a repeated waypoint is no new segment; one waypoint is a trajectory of one sample
    again = time_joints(np.repeat(waypoints[:2], 2, axis=0), rate_hz=500.0)
    assert again.duration_s == pytest.approx(time_joints(waypoints[:2], rate_hz=500.0).duration_s)
    assert time_joints(waypoints[:1]).duration_s == 0.0
    for bad in (np.zeros((3, 5)), np.full((2, 6), np.nan)):
        with pytest.raises(ValueError, match=r"\[W, 6\] finite joint vectors"):
            time_joints(bad)
    with pytest.raises(ValueError, match="6 positive numbers"):
        time_joints(waypoints, v_max=np.zeros(6))
    with pytest.raises(ValueError, match="rate_hz"):
        time_joints(waypoints, rate_hz=0.0)
    with pytest.raises(ValueError, match="gridpoints=1 is not accepted"):
        time_joints(waypoints, gridpoints=1)
    fine = time_joints(waypoints, rate_hz=500.0, gridpoints=240)
    coarse = time_joints(waypoints, rate_hz=500.0, gridpoints=50)  # a coarser grid: never faster motion
    assert coarse.duration_s >= fine.duration_s * (1 - 1e-6)


def test_the_default_grid_is_the_knots_and_chebyshev_points_between_them():
    """``knot_grid``: every knot and, inside each segment, ``(1 - cos(pi k / (n + 1))) / 2`` of its
    length (hand-worked for n = 3: 0.1464, 0.5, 0.8536); on a curved path of eight waypoints the
    default timing on it (64 points) is within 6 % of a fine even grid's (315 points) and shorter than
    an even grid's of as many points (measured: +3.8 % and +10.3 %)."""
    grid = psm_timing.knot_grid(np.array([0.0, 0.25, 1.0]), 3)
    c = (1 - math.cos(math.pi / 4)) / 2
    expected = [0.0, 0.25 * c, 0.125, 0.25 * (1 - c), 0.25, 0.25 + 0.75 * c, 0.625, 0.25 + 0.75 * (1 - c), 1.0]
    np.testing.assert_allclose(grid, expected, atol=1e-12)
    t = np.linspace(0.0, 1.0, 8)[:, None]
    waypoints = np.c_[0.3 * np.sin(3 * t), 0.2 * np.cos(2 * t), 0.1 + 0.02 * t, np.sin(5 * t), t, -t] * 0.5
    default = time_joints(waypoints)
    fine = time_joints(waypoints, gridpoints=7 * 9 * 5)
    assert fine.duration_s <= default.duration_s <= 1.06 * fine.duration_s
    assert time_joints(waypoints, gridpoints=7 * 9 + 1).duration_s > default.duration_s
    assert limit_ratio(default.qd, default.qdd) <= 1.0 + 1e-9


def test_a_coarse_grid_is_slowed_uniformly_until_every_sample_keeps_the_limits(monkeypatch):
    """TOPP-RA holds the limits at its grid points only: on 20 points the constant-acceleration motion
    between them passes the acceleration limit (by more than a tenth here, measured at 1 kHz); the
    trajectory returned is that motion slowed uniformly, every sample within the limits, its
    duration the raw one times the slow-down; 2 grid points (at rest at both ends: no motion) are
    refused, not timed forever."""
    rng = np.random.default_rng(11)
    steps = rng.normal(0, [0.02, 0.02, 1e-3, 0.1, 0.1, 0.1], (6, 6))
    q = np.cumsum(np.r_[[[0.1, -0.2, 0.15, 0.3, 0.1, -0.2]], steps], 0)
    timed = time_joints(q, gridpoints=20)
    assert limit_ratio(timed.qd, timed.qdd) <= 1.0
    raw = psm_timing.raw_timing(q, 20)
    t, _, qd, qdd = sample_const_accel(*raw, 1000.0)
    assert limit_ratio(qd, qdd) > 1.1
    slow = psm_timing.path_ratio(*raw, V_MAX, A_MAX)
    assert timed.duration_s == pytest.approx(t[-1] * slow, rel=1e-9)  # one slow-down, from path_ratio
    monkeypatch.setattr(psm_timing, "path_ratio", lambda *args, **kwargs: 1.0)  # without the slow-down
    monkeypatch.setattr(psm_timing, "MAX_RESCALES", 1)
    with pytest.raises(ValueError, match="no timing within the limits"):
        time_joints(q, gridpoints=20)
    with pytest.raises(ValueError, match="TOPP-RA found no trajectory"):
        time_joints(q, gridpoints=2)


def test_the_sampled_trajectory_is_toppra_s_own_constant_acceleration_one():
    """``sample_const_accel`` (compiled, on the compiled spline) gives what
    ``toppra.parametrizer.ParametrizeConstAccel`` (a loop over samples, on toppra's scipy spline)
    gives for the same TOPP-RA velocities, at every sample and order."""
    import toppra
    from toppra.parametrizer import ParametrizeConstAccel

    rng = np.random.default_rng(5)
    q = dvrk.Q_MIN + (dvrk.Q_MAX - dvrk.Q_MIN) * (0.45 + 0.1 * rng.random((4, 6)))
    path = toppra.SplineInterpolator(np.linspace(0.0, 1.0, 4), q, bc_type="clamped")
    grid = np.linspace(0.0, 1.0, 60)
    sd = 0.5 + np.sin(np.linspace(0.0, 3.0, 60)) ** 2  # any positive path velocities
    t, position, velocity, acceleration = sample_const_accel(Spline(np.linspace(0.0, 1.0, 4), q), grid, sd, 1000.0)
    reference = ParametrizeConstAccel(path, grid, sd)
    assert t[0] == 0.0 and t[-1] == pytest.approx(reference.duration, abs=1e-12)
    assert np.all(np.diff(t[:-1]) == pytest.approx(1e-3))
    for order, mine in enumerate((position, velocity, acceleration)):
        np.testing.assert_allclose(mine, reference(t, order), rtol=0, atol=1e-9)


def _camera_plan(paper_testset, row: int):
    episodes, _ = paper_testset
    needle, start, _ = episode_poses(episodes)
    camera_eg = np.array([0.01, -0.02, 0.1, 0.9238795, 0.3826834, 0.0, 0.0])
    eg = dvrk.pose_matrix(camera_eg)
    cam = lambda pose: _as_pose(eg @ dvrk.pose_matrix(pose))  # noqa: E731
    psm = {"regrasping_base": eg @ dvrk.base_behind(start[row])}
    policy = load_policy("student_v3")  # its jaws stay (the default's opening: tests/test_psm_jaw.py)
    plan = policy.plan_from_camera(camera_eg, cam(start[row]), cam(needle[row]), psm=psm)
    return policy, plan, camera_eg, cam(needle[row]), psm, needle[row]


def test_a_shipped_plan_is_timed_and_clear_and_a_tool_in_its_way_is_caught(paper_testset):
    policy, plan, camera_eg, needle_cam, psm, needle_eg = _camera_plan(paper_testset, 0)
    assert plan.success and plan.joints.all_reachable
    timed = time_plan(policy, plan, camera_eg, needle_cam, psm)
    assert not timed.check.collides and timed.check.within_limits
    assert 0.2 < timed.trajectory.duration_s < 3.0
    assert 0.0 < timed.check.chord_margin_m < 1e-5  # the arc between 1-kHz samples: micrometres at most
    # the executed tool poses start and end where the plan does (in e_g)
    base = np.linalg.inv(dvrk.pose_matrix(camera_eg)) @ dvrk.as_matrix(psm["regrasping_base"])
    poses = tool_poses(base, timed.trajectory.q)
    np.testing.assert_allclose(poses[[0, -1], :3], plan.trajectory("eg")[[0, -1], :3], atol=1e-5)
    # the same motion with the arm's base moved so that the tool tip meets the grasping tool's tip
    # halfway: caught, at or before halfway
    middle = len(poses) // 2
    shifted = np.eye(4)
    shifted[:3, 3] = -poses[middle, :3]
    check = check_motion(timed.trajectory, shifted @ base, needle_eg, policy)
    assert check.collides and check.index <= middle and check.t_s == timed.trajectory.t[check.index]
    assert not check_motion(timed.trajectory, base, needle_eg, policy).collides
    # a closed loop's executed poses (e_g) go through time_executed: the plan's poses give the plan's motion
    again = time_executed(policy, plan.trajectory("eg"), needle_eg, base)
    assert again.trajectory.duration_s == pytest.approx(timed.trajectory.duration_s, rel=1e-6)
    np.testing.assert_allclose(again.trajectory.q, timed.trajectory.q, atol=1e-6)  # the frames differ by rounding
    with pytest.raises(MotionRefused, match="outside the PSM's joint limits"):
        far = plan.trajectory("eg").copy()
        far[:, 2] += 0.5  # half a metre past the arm's reach
        time_executed(policy, far, needle_eg, base)


def test_plans_that_cannot_be_timed_are_refused_with_the_reason(paper_testset):
    policy, plan, camera_eg, needle_cam, psm, _ = _camera_plan(paper_testset, 0)
    with pytest.raises(MotionRefused, match="has no joints"):
        time_plan(policy, dataclasses.replace(plan, joints=None), camera_eg, needle_cam, psm)
    with pytest.raises(MotionRefused, match="did not reach the goal"):
        time_plan(policy, dataclasses.replace(plan, success=np.array(False)), camera_eg, needle_cam, psm)
    out = dataclasses.replace(
        plan.joints,
        reachable=np.r_[plan.joints.reachable[:-1], False],
        violations=(*plan.joints.violations[:-1], ("outer_wrist_yaw",)),
    )
    with pytest.raises(MotionRefused, match=r"outside the PSM's joint limits \(outer_wrist_yaw\)"):
        time_plan(policy, dataclasses.replace(plan, joints=out), camera_eg, needle_cam, psm)


def test_a_spline_past_a_joint_limit_gets_waypoints_and_a_colliding_sweep_is_refused(paper_testset):
    """paper300 rows 175 and 229 from one fixed port (0.12 m behind the average start), planned with
    ``timed=True``: row 175's 13 waypoints are within the limits, the spline through them is not, and
    inserted Cartesian midpoints bring it back; row 229 has a pose past the wrist yaw's limit and its
    motion is refused with that reason. A yaw sweep of the tool tip through the grasping tool, whose
    Cartesian chord collides too, is refused."""
    episodes, _ = paper_testset
    needle, start, _ = episode_poses(episodes)
    rows = [175, 229]
    psm = {"regrasping_base": dvrk.base_behind(dvrk.average_pose(start))}
    identity = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (2, 1))
    policy = load_policy("student_v3")  # the default until 2026-11-29, whose plans of these rows leave the limits
    depth = np.asarray(episodes.goal_depth)[rows] * 1e3
    plan = policy.plan_from_camera(
        identity, start[rows], needle[rows], goal_depth_mm=depth, check_grasp=False, psm=psm, timed=True
    )
    assert plan.success.all() and plan.joints[0].all_reachable and not plan.joints[1].all_reachable
    base = dvrk.as_matrix(psm["regrasping_base"])
    first = check_motion(time_joints(plan.joints[0].q), base, needle[rows[0]], policy)
    assert not first.collides and not first.within_limits
    timed = plan.motion[0]
    assert timed.ok and timed.inserted >= 1 and timed.check.within_limits and not timed.check.collides
    assert len(timed.trajectory.waypoints) == len(plan.joints[0].q) + timed.inserted
    assert time_plan(policy, plan, identity, needle[rows], psm, query=0).trajectory.duration_s == pytest.approx(
        timed.trajectory.duration_s
    )
    assert not plan.motion[1].ok and plan.motion[1].trajectory is None
    assert "outside the PSM's joint limits (outer_wrist_yaw)" in plan.motion[1].refused
    with pytest.raises(ValueError, match="timed=True is not accepted without psm"):
        policy.plan_from_camera(identity[0], start[0], needle[0], timed=True)
    # the tool tip sweeping 0.6 rad of outer yaw through the grasping tool's tip: refused
    q0, q1 = np.array([-0.3, 0.0, 0.15, 0.0, 0.0, 0.0]), np.array([0.3, 0.0, 0.15, 0.0, 0.0, 0.0])
    through = np.linalg.inv(dvrk.forward_kinematics(np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.0])))
    far = np.r_[0.2, 0.2, 0.2, 1.0, 0.0, 0.0, 0.0]
    with pytest.raises(MotionRefused, match=r"collides at 0\.\d+ s after 8 inserted waypoints"):
        time_waypoints([q0, q1], through, far, policy)
