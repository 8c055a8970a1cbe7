"""The robot's errors (regrasp_mjx.robot.robot_errors): the e_g-frame model against the lab's own frames
(camera, camera-to-base transforms, joint readings) worked by hand in float64, joint offsets through
the dVRK's kinematics, the calibration cancelling in the camera view, and the checks of bad values."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx import load_policy
from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs.estimates import NeedleNoise, camera_view, frame_estimate
from regrasp_mjx.evaluate import main as evaluate_main
from regrasp_mjx.robot import dvrk
from regrasp_mjx.robot.robot_errors import (
    NEUTRAL,
    Arms,
    RobotErrors,
    average,
    draw_arms,
    executed,
    kinematic_view,
    propagate,
    readings,
)
from regrasp_mjx.world.sampling import episode_poses


def _m(v):
    return dvrk.pose_matrix(np.asarray(v, np.float64))


def _vec(m):
    w, x, y, z = _quat(m[:3, :3])
    return np.r_[m[:3, 3], w, x, y, z]


def _quat(r):
    w = np.sqrt(max(1.0 + r[0, 0] + r[1, 1] + r[2, 2], 1e-300)) / 2.0
    return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])


def _ego(grasp, regrasp, needle):
    """The ego-centric state from three poses in one frame (SPEC "Deployment"), 4x4 each."""
    with jax.enable_x64(True):
        pose = lambda m: (jnp.asarray(m[:3, 3]), jnp.asarray(_quat(m[:3, :3])))  # noqa: E731
        return np.asarray(geometry.ego_observation(pose(grasp), pose(regrasp), pose(needle)))


@pytest.fixture(scope="module")
def rows(paper_testset):
    episodes, _ = paper_testset
    return tuple(np.asarray(x[:6], np.float64) for x in episode_poses(episodes))


def test_a_calibration_shift_cancels_in_the_camera_and_not_in_the_kinematics(rows):
    """A pure camera-to-base shift of 5 mm per arm, worked in the lab's frames: a camera, each arm's
    true and believed camera-to-base transform, the joint readings. The state built from the camera's
    three poses is the true one to 1e-9; built from the readings through the believed transforms it
    is what kinematic_view says, and the needle seen from the regrasping jaws is off by exactly 5 mm."""
    needle, start, _ = rows
    with jax.enable_x64(True):
        arms = draw_arms(jax.random.PRNGKey(3), jnp.asarray(start), 5.0, 0.0, 0.0)
        seen_needle, seen_ee = (
            np.asarray(x) for x in kinematic_view(arms, jnp.asarray(needle), jnp.asarray(start), None)
        )
    camera = _m([0.02, -0.05, 0.08, 0.9, 0.1, -0.3, 0.2])  # the camera in e_g
    cam_inv = np.linalg.inv(camera)
    fk_neutral = dvrk.forward_kinematics(NEUTRAL)
    for i in range(len(start)):
        base_r, believed_r = _m(np.asarray(arms.base[i])), _m(np.asarray(arms.believed_base[i]))
        base_g = np.linalg.inv(fk_neutral)  # the grasping tool (e_g itself) at the neutral joints
        believed_g = _m(np.asarray(arms.grasping_view[i])) @ np.linalg.inv(fk_neutral)
        for base, believed in ((base_r, believed_r), (base_g, believed_g)):
            error = np.linalg.inv(base) @ believed  # the calibration error in the base frame
            np.testing.assert_allclose(error[:3, :3], np.eye(3), atol=1e-12)
            assert abs(np.linalg.norm(error[:3, 3]) - 5e-3) < 1e-12
        true_eg, true_er, true_n = cam_inv, cam_inv @ _m(start[i]), cam_inv @ _m(needle[i])
        truth = _ego(np.eye(4), _m(start[i]), _m(needle[i]))
        np.testing.assert_allclose(_ego(true_eg, true_er, true_n), truth, atol=1e-9)  # camera only
        # the lab's kinematic view: readings q with FK(q) = base^-1 tool, through the believed transforms
        kin_g = cam_inv @ believed_g @ np.linalg.inv(base_g)
        kin_r = cam_inv @ believed_r @ np.linalg.inv(base_r) @ _m(start[i])
        kinematic = _ego(kin_g, kin_r, true_n)
        np.testing.assert_allclose(kinematic, _ego(np.eye(4), _m(seen_ee[i]), _m(seen_needle[i])), atol=1e-9)
        # the needle in the regrasping frame (the state's last 7 numbers): off by the shift exactly
        assert abs(np.linalg.norm(kinematic[14:17] - truth[14:17]) - 5e-3) < 1e-9


def test_the_camera_view_is_relative_to_the_seen_grasping_tool(rows):
    """Tracking noise of the grasping tool moves the whole view and nothing in it: the needle seen
    from the seen regrasping tool depends on the regrasping tool's and the needle's noise alone."""
    needle, start, _ = rows
    with jax.enable_x64(True):
        n, e = jnp.asarray(needle), jnp.asarray(start)
        seen_n, seen_e = camera_view(jax.random.PRNGKey(0), n, e, 0.5)
        k_g, k_r = jax.random.split(jax.random.PRNGKey(0))
        alone = geometry.relative(*[(x[:, :3], x[:, 3:]) for x in (frame_estimate(k_r, e, 0.5), n)])
        both = geometry.relative((seen_e[:, :3], seen_e[:, 3:]), (seen_n[:, :3], seen_n[:, 3:]))
        np.testing.assert_allclose(np.asarray(both[0]), np.asarray(alone[0]), atol=1e-12)
        assert float(jnp.max(jnp.abs(seen_e[:, :3] - e[:, :3]))) > 1e-4  # the view itself did move
        same_n, same_e = camera_view(jax.random.PRNGKey(0), n, e, 0.0)
        assert (np.asarray(same_n) == needle).all() and (np.asarray(same_e) == start).all()


def test_joint_offsets_move_the_reached_pose_by_what_fk_says(rows):
    """An arm whose joints read off by o: asked for the tool-frame motion D it goes to
    FK(IK(FK(q) D) + o), worked here with the float64 dVRK kinematics."""
    _, start, _ = rows
    offsets = np.radians([0.5, -0.4, 0.0, 0.3, -0.5, 0.2]) + np.array([0, 0, 0.5e-3, 0, 0, 0])
    base = dvrk.base_behind(start[0])
    q = NEUTRAL - offsets  # the reading where the tool is at the start
    tool = base @ dvrk.forward_kinematics(q + offsets)
    np.testing.assert_allclose(tool, _m(start[0]), atol=1e-12)
    action = np.array([0.8, -0.5, 0.3, -0.6, 0.9, 0.2])
    max_dp, max_drot = 0.5e-3, np.radians(3.0)
    with jax.enable_x64(True):
        arms = Arms(*(jnp.asarray(x)[None] for x in (np.zeros(7), _vec(base), _vec(base), offsets, False)))
        ee = jnp.asarray(_vec(tool))[None]
        np.testing.assert_allclose(np.asarray(readings(arms, ee, jnp.asarray(q)[None]))[0], q, atol=1e-9)
        moved = np.asarray(executed(arms, ee, ee, jnp.asarray(action)[None], max_dp, max_drot, jnp.asarray(q)[None]))[0]
        plain = np.asarray(executed(arms, ee, ee, jnp.asarray(action)[None], max_dp, max_drot))[0]
    np.testing.assert_allclose(plain, action, atol=1e-12)  # no offsets, a true view: the action itself
    target = np.eye(4)
    target[:3, :3] = _m(np.r_[0, 0, 0, geometry_quat(action[3:] * max_drot)])[:3, :3] @ tool[:3, :3]
    target[:3, 3] = tool[:3, 3] + action[:3] * max_dp
    motion = np.linalg.inv(tool) @ target  # D in the tool frame
    q_next = dvrk.inverse_kinematics(dvrk.forward_kinematics(q) @ motion, q_ref=q).q
    reached = base @ dvrk.forward_kinematics(q_next + offsets)
    np.testing.assert_allclose(tool[:3, 3] + moved[:3] * max_dp, reached[:3, 3], atol=1e-9)
    turned = _m(np.r_[0, 0, 0, geometry_quat(moved[3:] * max_drot)])[:3, :3] @ tool[:3, :3]
    np.testing.assert_allclose(turned, reached[:3, :3], atol=1e-9)
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) > 1e-7  # the offsets did move it off the target


def geometry_quat(rotvec):
    angle = np.linalg.norm(rotvec)
    axis = rotvec / angle if angle > 0 else np.zeros(3)
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]


def test_the_fused_tool_view_is_a_running_mean_moved_by_the_kinematics():
    a = jnp.array([[1e-3, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    b = jnp.array([[3e-3, 2e-3, 0.0, 1.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(average(a, jnp.float32(1.0), b))[0, :3], [2e-3, 1e-3, 0.0], atol=1e-9)
    np.testing.assert_allclose(np.asarray(average(a, jnp.float32(3.0), b))[0, :3], [1.5e-3, 0.5e-3, 0.0], atol=1e-9)
    # a view equal to the kinematics' pose before the motion is their pose after it
    after = jnp.array([[2e-3, -1e-3, 4e-3, 0.0, 1.0, 0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(propagate(a, a, after)), np.asarray(after), atol=1e-7)


@pytest.mark.parametrize(
    "bad, match",
    [
        (dict(calibration_mm=-1.0), "calibration_mm"),
        (dict(calibration_mm=float("nan")), "calibration_mm"),
        (dict(calibration_mm=51.0), r"\[0, 50\]"),
        (dict(calibration_deg=31.0), r"\[0, 30\]"),
        (dict(joint_offset=float("inf")), "joint_offset"),
        (dict(tool_noise_mm=-0.1), "tool_noise_mm"),
        (dict(tool_noise_mm="1"), "tool_noise_mm"),
    ],
)
def test_bad_robot_errors_are_refused(bad, match):
    with pytest.raises(ConfigError, match=match):
        RobotErrors(**bad)


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--calibration-mm", "-1"], "--calibration-mm -1.0 is not accepted"),
        (["--calibration-mm", "nan"], "--calibration-mm nan is not accepted"),
        (["--calibration-mm", "60"], r"in \[0, 50\]"),
        (["--calibration-deg", "31"], r"--calibration-deg 31.0 is not accepted: .* in \[0, 30\]"),
        (["--joint-offset", "-0.5"], "--joint-offset -0.5 is not accepted"),
        (["--tool-noise-mm", "inf"], "--tool-noise-mm inf is not accepted"),
        (["--observe", "eyes"], "invalid choice: 'eyes'"),
        (["--robustness", "--calibration-mm", "1"], "not accepted with"),
        (["--agreement", "--tool-noise-mm", "1"], "not accepted with"),
    ],
)
def test_bad_robot_error_options_exit_2_with_one_line(argv, match, capsys):
    with pytest.raises(SystemExit) as exit_:
        evaluate_main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if "error:" in line]  # argparse's usage, then one error line
    assert len(errors) == 1 and errors[0] == err[-1] and re.search(match, err[-1]), err


@pytest.fixture(scope="module")
def policy():
    return load_policy()


@pytest.mark.slow
def test_no_robot_error_is_the_needle_only_loop_and_the_camera_ignores_calibration(policy, rows):
    """Without robot errors both views are exactly the needle-only closed loop; with the camera
    seeing exact tools, a calibration error of 10 mm / 5 deg per arm changes nothing at all; seen
    through the kinematics, 3 mm / 2 deg moves the tool elsewhere."""
    needle, start, goal = rows
    noise = NeedleNoise(0.25)
    base = policy.execute(needle, start, goal, noise, seed=1)
    for robot, observe in ((RobotErrors(), "kinematic"), (RobotErrors(10.0, 5.0), "camera")):
        again = policy.execute(needle, start, goal, noise, seed=1, robot=robot, observe=observe)
        for k in base:
            np.testing.assert_array_equal(again[k], base[k], err_msg=f"{k} with {robot}, {observe}")
    off = policy.execute(needle, start, goal, noise, seed=1, robot=RobotErrors(3.0, 2.0), observe="kinematic")
    assert np.abs(off["poses"][:, 1:] - base["poses"][:, 1:]).max() > 1e-4
    with pytest.raises(ConfigError, match="observe='eyes' is not accepted"):
        policy.execute(needle, start, goal, noise, observe="eyes")
    with pytest.raises(ConfigError, match="robot=.* is not accepted: a RobotErrors"):
        policy.execute(needle, start, goal, noise, robot=(1.0, 1.0))


def _camera_frames(camera, needle, ee):
    """Camera-frame 7-vectors of the grasping tool (e_g itself), the regrasping tool and the needle."""
    cam_inv = np.linalg.inv(camera)
    return [_vec(cam_inv @ m) for m in (np.eye(4), _m(ee), _m(needle))]


def test_the_camera_loop_plans_as_the_policy_wherever_the_camera_is(policy, rows):
    """Exact camera frames, the arm moving by each commanded tool-frame motion: the loop takes the
    policy's own plan step by step, and moving the camera (a common error of all three poses) or
    telling it the motion its kinematics measured changes no command."""
    needle, start, goal = rows
    plan = policy.plan(needle, start, goal, check_grasp=False)
    cameras = [np.eye(4), _m([0.03, -0.02, 0.1, 0.3, 0.8, -0.1, 0.5])]
    for i in range(3):
        runs = []
        for camera, report in ((cameras[0], False), (cameras[1], False), (cameras[1], True)):
            goal_in_needle = _vec(np.linalg.inv(_m(needle[i])) @ _m(goal[i]))
            loop = policy.camera_loop(goal_in_needle=goal_in_needle, warmup_frames=1, stop_tolerance=1.0)
            ee, motions = _m(start[i]), []
            for _ in range(policy.env_config.horizon):
                command = loop.update(
                    *_camera_frames(camera, needle[i], _vec(ee)), moved=motions[-1] if report and motions else None
                )
                if command.at_goal:
                    break
                motions.append(command.motion)
                ee = ee @ command.motion
            runs.append((len(motions), _vec(ee)))
        steps = int(plan.steps[i])
        assert runs[0][0] == steps, (i, runs[0][0], steps)
        np.testing.assert_allclose(runs[0][1][:3], plan.poses[i, steps, :3], atol=2e-6)
        for n_steps, pose in runs[1:]:
            assert n_steps == steps
            np.testing.assert_allclose(pose, runs[0][1], atol=1e-6)


def test_the_camera_loop_refuses_bad_frames(policy):
    loop = policy.camera_loop()
    good = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="needle"):
        loop.update(good, good, [0.0, 0.0, float("nan"), 1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="one frame"):
        loop.update(np.tile(good, (2, 1)), np.tile(good, (2, 1)), np.tile(good, (2, 1)))
    with pytest.raises(ValueError, match="warmup_frames=0 is not accepted"):
        policy.camera_loop(warmup_frames=0)
