"""The jaw as a joint of the regrasping arm's trajectory (issue 67): a plan's jaw track, the opening
timed at the dVRK's jaw limits with the arm at rest, and the executed motion re-checked with the jaws
where they are at each moment, the opening sweep included; the default's motion unchanged."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from regrasp_mjx.core.config import EnvConfig, SceneConfig
from regrasp_mjx.envs.lean_checker import LeanChecker
from regrasp_mjx.inference import jaw_opening
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.robot import dvrk
from regrasp_mjx.robot.executed_motion import (
    MotionRefused,
    at_opening,
    check_motion,
    opening_room,
    time_executed,
    time_waypoints,
    tool_poses,
)
from regrasp_mjx.robot.psm_joints import JawTrack
from regrasp_mjx.robot.psm_timing import JAW_A_MAX, JAW_V_MAX, move_time_s, sample_move, time_joints, time_with_jaw
from regrasp_mjx.world.sampling import episode_poses
from regrasp_mjx.world.scene import load_scene

OPEN40 = Path(__file__).resolve().parents[1] / "experiments" / "results" / "jaw_on_the_way" / "policy_open40"
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # the camera at the grasping tool: poses in e_g


def test_a_jaw_track_keeps_the_scene_s_opening_opens_at_its_pose_and_keeps_the_opening():
    track = JawTrack(20.0, 40.0, opens_at=2, poses=5)
    np.testing.assert_array_equal(track.deg, [20.0, 20.0, 40.0, 40.0, 40.0])  # the opening each step leaves with
    q = np.arange(30.0).reshape(5, 6) / 100.0
    seven = track.waypoints(q)
    assert seven.shape == (6, 7)
    np.testing.assert_array_equal(seven[:, :6], q[[0, 1, 2, 2, 3, 4]])  # pose 2 twice: only the jaw moves there
    np.testing.assert_allclose(np.degrees(seven[:, 6]), [20, 20, 20, 40, 40, 40])
    never = JawTrack(20.0, 40.0, -1, 5)
    assert not never.opens
    np.testing.assert_array_equal(never.deg, 20.0)
    np.testing.assert_allclose(np.degrees(never.waypoints(q)[:, 6]), 20.0)
    assert JawTrack.of(EnvConfig(jaw_open_deg=40.0), 1, 4) == JawTrack(20.0, 40.0, 1, 4)
    assert JawTrack.of(EnvConfig(), -1, 4) == JawTrack(20.0, 20.0, -1, 4)  # jaws that stay
    with pytest.raises(ValueError, match=r"q of shape \(4, 6\) is not accepted: \[5, 6\]"):
        track.waypoints(q[:4])


@pytest.mark.parametrize(
    "args, match",
    [
        ((20.0, 85.0, 0, 3), r"to_deg=85.0 is not accepted: .* from 0 \(closed\) to the Large Needle Driver's 80"),
        ((-1.0, 40.0, 0, 3), r"from_deg=-1.0 is not accepted"),
        ((20.0, math.nan, 0, 3), r"to_deg=nan is not accepted"),
        ((20.0, 40.0, 2, 3), r"opens_at=2 is not accepted: -1 \(never\) or the pose a step leaves, 0 to 1 for 3"),
        ((20.0, 40.0, -2, 3), r"opens_at=-2 is not accepted"),
        ((20.0, 20.0, 0, 3), r"to_deg=20.0 is not accepted where the jaws open .* wider than from_deg=20.0"),
        ((20.0, 40.0, -1, 0), r"poses=0 is not accepted"),
    ],
)
def test_a_jaw_track_outside_the_jaw_s_limits_or_the_plan_is_refused_with_what_is_accepted(args, match):
    with pytest.raises(ValueError, match=match):
        JawTrack(*args)


def test_the_jaw_opens_20_degrees_in_a_third_of_a_second_at_the_dvrk_s_limits():
    """The jaw's limits, 1080 deg/s and 720 deg/s^2 (4 pi rad/s^2): 20 degrees (pi / 9 rad) lie far below
    v^2 / a (9 pi rad), so the fastest move accelerates half the way and brakes the other half:
    T = 2 sqrt(d / a) = 2 sqrt(1 / 36) = 1/3 s, peak speed a T / 2 = 2 pi / 3 rad/s (120 deg/s);
    40 degrees: 2 sqrt(1 / 18) = 0.4714 s. A move long enough to cruise: 3 rad at 1 rad/s and 1 rad/s^2,
    d / v + v / a = 4 s."""
    assert math.degrees(JAW_V_MAX) == pytest.approx(1080.0) and math.degrees(JAW_A_MAX) == pytest.approx(720.0)
    assert move_time_s(math.radians(20.0)) == pytest.approx(1.0 / 3.0, abs=1e-12)
    assert move_time_s(math.radians(-40.0)) == pytest.approx(2.0 * math.sqrt(1.0 / 18.0), abs=1e-12)
    assert move_time_s(3.0, v_max=1.0, a_max=1.0) == pytest.approx(4.0)
    lo, hi = math.radians(20.0), math.radians(40.0)
    t, s, v, a = sample_move(lo, hi, 1000.0)
    assert t[0] == 0.0 and t[-1] == pytest.approx(1.0 / 3.0, abs=1e-12) and len(t) == 335  # 0, 1 ms, ..., 333 ms, 1/3 s
    np.testing.assert_allclose(np.diff(t[:-1]), 1e-3, atol=1e-12)
    assert s[0] == lo and s[-1] == hi and v[0] == 0.0 and v[-1] == 0.0
    assert np.all(np.diff(s) > 0.0) and np.abs(v).max() == pytest.approx(2.0 * math.pi / 3.0, abs=JAW_A_MAX * 1e-3)
    assert np.all(np.abs(v) <= JAW_V_MAX) and np.all(np.abs(a) <= JAW_A_MAX)
    # accelerating to half time, braking after: a t^2 / 2 from the start, a (T - t)^2 / 2 short of the end
    assert s[100] == pytest.approx(lo + JAW_A_MAX * 0.1**2 / 2.0, abs=1e-12)
    assert s[300] == pytest.approx(hi - JAW_A_MAX * (1.0 / 3.0 - 0.3) ** 2 / 2.0, abs=1e-12)
    # the samples are one motion: the mean velocity over each interval is the position's change
    np.testing.assert_allclose(np.diff(s) / np.diff(t), (v[1:] + v[:-1]) / 2.0, atol=JAW_A_MAX * 1e-3)
    t, s, v, _ = sample_move(hi, 0.0, 1000.0)  # a closing (not modelled in a plan: the move it would take)
    assert t[-1] == pytest.approx(2.0 * math.sqrt(1.0 / 18.0)) and s[-1] == 0.0 and np.all(np.diff(s) < 0.0)


def test_an_opening_adds_a_third_of_a_second_with_the_arm_at_rest():
    """0.05 m of insertion alone (test_psm_timing's hand-worked move: 2 sqrt(d / a) = 1.0 s at 0.2 m/s^2)
    through a middle waypoint. Opened at the first pose: the arm's motion plus the jaw's 1/3 s. Opened at
    the middle one: the arm comes to rest there, so each half is a move from rest to rest,
    2 sqrt(0.025 / 0.2) = 0.7071 s each, and the whole 2 x 0.7071 + 1/3 = 1.748 s."""
    q0 = np.array([0.1, -0.2, 0.10, 0.3, 0.0, 0.0])
    q = np.stack([q0, q0 + [0, 0, 0.025, 0, 0, 0], q0 + [0, 0, 0.05, 0, 0, 0]])
    plain = time_joints(q)
    first = time_with_jaw(q, JawTrack(20.0, 40.0, 0, 3))
    assert first.duration_s == pytest.approx(plain.duration_s + 1.0 / 3.0, abs=1e-12)
    middle = time_with_jaw(q, JawTrack(20.0, 40.0, 1, 3))
    halves = time_joints(q[:2]).duration_s + time_joints(q[1:]).duration_s
    assert middle.duration_s == pytest.approx(halves + 1.0 / 3.0, abs=1e-12)
    assert middle.duration_s == pytest.approx(2 * 2 * math.sqrt(0.025 / 0.2) + 1.0 / 3.0, rel=0.03)  # the default grid
    turning = np.flatnonzero(np.diff(middle.jaw) != 0.0) + 1  # the samples the jaw moved to
    assert len(turning) == 334 and np.all(np.diff(turning) == 1)  # one run, 1/3 s at 1 kHz
    np.testing.assert_array_equal(middle.q[turning], middle.q[turning - 1])  # the arm at rest meanwhile
    np.testing.assert_array_equal(middle.qd[turning], 0.0)
    np.testing.assert_allclose(middle.q[turning[0]], q[1], atol=1e-12)  # at the middle waypoint
    np.testing.assert_allclose(np.degrees(middle.jaw[[0, turning[0] - 1, -1]]), [20.0, 20.0, 40.0])
    assert np.all(np.diff(middle.jaw) >= 0.0) and np.all(np.diff(middle.t) > 0.0)
    kept = time_with_jaw(q, JawTrack(20.0, 40.0, -1, 3))  # never opened: the arm's own timing, the jaw held
    np.testing.assert_array_equal(kept.q, plain.q)
    np.testing.assert_array_equal(kept.t, plain.t)
    np.testing.assert_array_equal(kept.jaw, math.radians(20.0))
    with pytest.raises(ValueError, match=r"one a pose of the jaw's track, 4"):
        time_with_jaw(q, JawTrack(20.0, 40.0, 0, 4))


def test_the_checker_with_the_jaws_turned_is_the_scene_built_at_that_opening(paper_testset):
    """The executed-motion check turns the scene's jaw capsules (``world.jaw.opened_ends``) instead of
    building a scene: the same capsules as the scene built at 40 degrees, and the same verdicts on poses
    near the needle (starts and goals moved by up to 1.5 mm, some of them into it)."""
    scene, built = load_scene(), load_scene(SceneConfig(jaw_angle_deg=40.0))
    opened = at_opening(scene, 40.0)
    assert at_opening(scene, 20.0) is scene
    np.testing.assert_allclose(opened.capsule_frames.tool_ends, built.capsule_frames.tool_ends, rtol=0, atol=2e-7)
    episodes, _ = paper_testset
    needle, start, goal = episode_poses(episodes)
    rng = np.random.default_rng(67)
    poses = np.concatenate([start, goal])
    poses[:, :3] += rng.uniform(-1.5e-3, 1.5e-3, (len(poses), 3))
    turned, own, at_20 = LeanChecker(opened), LeanChecker(built), LeanChecker(scene)
    mine, theirs, narrow = [], [], []
    for n, p in zip(np.concatenate([needle, needle]), poses):
        mine.append(turned.collides(n[:3], n[3:], p[:3], p[3:]))
        theirs.append(own.collides(n[:3], n[3:], p[:3], p[3:]))
        narrow.append(at_20.collides(n[:3], n[3:], p[:3], p[3:]))
    assert mine == theirs
    assert 20 < sum(mine) < len(mine) - 20 and mine != narrow  # both verdicts, and the opening matters


def _default_row0(paper_testset):
    episodes, _ = paper_testset
    needle, start, _ = episode_poses(episodes)
    policy = load_policy("student_v3")  # a policy that keeps its jaws (the default until 2026-11-29)
    psm = {"regrasping_base": dvrk.base_behind(start[0])}
    plan = policy.plan_from_camera(IDENTITY, start[0], needle[0], psm=psm, check_grasp=False)
    assert plan.success and plan.joints.all_reachable
    return policy, plan, needle[0], dvrk.as_matrix(psm["regrasping_base"])


def test_jaws_that_open_into_the_needle_are_caught_and_the_default_s_motion_is_unchanged(paper_testset):
    """paper300 row 0: at its start the needle lies where a jaw turns through as it opens from 20 to 40
    degrees (the environment's proof leaves it -0.31 mm), though the jaws at 40 are clear of it: only the
    sweep shows it. The shipped default's plan with its jaws opened there is refused; its motion with no
    jaw track, or one that never opens, is the same to the bit; opened later, where the tool has moved
    away, the same opening is clear."""
    policy, plan, needle, base = _default_row0(paper_testset)
    assert plan.joints.jaw is None  # the default keeps its jaws
    scene = load_scene(policy.env_config.scene)
    poses = tool_poses(base, plan.joints.q)
    room = opening_room(scene, needle, poses[0], 20.0, 40.0)
    assert room < -1e-4 and not LeanChecker(at_opening(scene, 40.0)).collides(
        needle[:3], needle[3:], *np.split(poses[0], [3])
    )
    n = len(plan.joints.q)
    into = JawTrack(20.0, 40.0, 0, n)
    with pytest.raises(
        MotionRefused, match=r"the jaws' opening at pose 0 \(20 to 40 deg, the arm at rest\) is not proved"
    ):
        time_waypoints(plan.joints.q, base, needle, policy, jaw=into)
    timed = time_with_jaw(plan.joints.q, into)  # the same motion checked whole: caught at the sweep's first piece
    check = check_motion(timed, base, needle, policy)
    sweep = np.flatnonzero(np.diff(timed.jaw) != 0.0) + 1
    assert check.collides and check.index == sweep[0] and check.opening_room_m == pytest.approx(room, abs=1e-9)
    plain = time_waypoints(plan.joints.q, base, needle, policy)
    assert plain.trajectory.jaw is None and plain.check.opening_room_m is None and not plain.check.collides
    kept = time_waypoints(plan.joints.q, base, needle, policy, jaw=JawTrack(20.0, 40.0, -1, n))
    for name in ("t", "q", "qd", "qdd", "waypoints"):
        np.testing.assert_array_equal(getattr(kept.trajectory, name), getattr(plain.trajectory, name))
    assert kept.check == plain.check and kept.inserted == plain.inserted
    # the first pose with the environment's room (0.5 mm) to open: opened there, the plan is clear
    later = next(k for k in range(1, n - 1) if opening_room(scene, needle, poses[k], 20.0, 40.0) >= 5e-4)
    opened = time_waypoints(plan.joints.q, base, needle, policy, jaw=JawTrack(20.0, 40.0, later, n))
    assert not opened.check.collides and opened.check.within_limits and opened.check.opening_room_m >= 5e-4 - 1e-6
    assert math.degrees(opened.trajectory.jaw[-1]) == pytest.approx(40.0)
    with pytest.raises(ValueError, match="the arm and the jaw both move"):  # a motion this check cannot prove
        both = timed.jaw.copy()
        both[-1] -= 1e-3
        check_motion(type(timed)(**{**vars(timed), "jaw": both}), base, needle, policy)
    with pytest.raises(ValueError, match=r"jaw.poses=3 is not accepted: the track of these \d+ waypoints"):
        time_waypoints(plan.joints.q, base, needle, policy, jaw=JawTrack(20.0, 40.0, 0, 3))
    with pytest.raises(ValueError, match=r"jaw.from_deg=30 is not accepted: the policy's scene's opening, 20 deg"):
        time_waypoints(plan.joints.q, base, needle, policy, jaw=JawTrack(30.0, 40.0, 0, n))


def test_a_jaw_opening_policy_s_plans_carry_the_jaw_track_and_its_time(paper_testset):
    """policy_open40 (trained with jaws that open on the way to 40 degrees) on paper300 rows 0 and 2: each
    plan's joints carry the jaw's track at the pose its environment opened at (``opening_steps``), and its
    timed motion is the arm's to that pose, the jaw's 1/3 s, the arm's from it; the sweep keeps the
    environment's 0.5 mm. A closed loop's executed poses need the track too."""
    episodes, _ = paper_testset
    needle, start, _ = episode_poses(episodes)
    rows = [0, 2]
    policy = load_policy(str(OPEN40))
    psm = {"regrasping_base": dvrk.base_behind(dvrk.average_pose(start))}
    base = dvrk.as_matrix(psm["regrasping_base"])
    depth = np.asarray(episodes.goal_depth)[rows] * 1e3
    cams = np.tile(IDENTITY, (2, 1))
    plan = policy.plan_from_camera(
        cams, start[rows], needle[rows], goal_depth_mm=depth, check_grasp=False, psm=psm, timed=True
    )
    opens = jaw_opening.opening_steps(policy, needle[rows], plan.poses, plan.steps)
    assert plan.success.all() and np.all(opens >= 0) and len(set(opens)) == 2  # two places to open
    for i, (joints, motion) in enumerate(zip(plan.joints, plan.motion)):
        assert joints.jaw == JawTrack(20.0, 40.0, int(opens[i]), int(plan.steps[i]) + 1)
        assert motion.ok and not motion.check.collides and motion.check.opening_room_m >= 5e-4 - 1e-5
        k = joints.jaw.opens_at
        arm = time_joints(joints.q[: k + 1]).duration_s + time_joints(joints.q[k:]).duration_s
        if motion.inserted == 0:
            assert motion.trajectory.duration_s == pytest.approx(arm + 1.0 / 3.0, abs=1e-9)
        np.testing.assert_allclose(np.degrees(motion.trajectory.jaw[[0, -1]]), [20.0, 40.0])
        again = time_executed(policy, plan.trajectory("eg", i), needle[rows[i]], base, jaw=joints.jaw)
        assert again.trajectory.duration_s == pytest.approx(motion.trajectory.duration_s, rel=1e-6)
    with pytest.raises(ValueError, match=r"jaw=None is not accepted for a policy whose jaws open on the way \(to 40"):
        time_executed(policy, plan.trajectory("eg", 0), needle[0], base)
