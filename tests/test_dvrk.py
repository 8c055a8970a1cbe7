"""dVRK PSM kinematics: FK against hand-worked poses, IK round trips, limits reported, and the
tool-tip frame being this project's end-effector frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from regrasp_mjx import dvrk


def test_forward_kinematics_by_hand():
    # Outer joints and wrist at zero, insertion 0.15 m: the shaft points along the base's -z, the
    # pitch axis sits 0.15 - 0.4318 + 0.4162 = 0.1344 m down it, the tip 9.1 mm further.
    q = np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    tip = dvrk.forward_kinematics(q)
    np.testing.assert_allclose(tip[:3, 3], [0.0, 0.0, -0.1435], atol=1e-12)
    np.testing.assert_allclose(tip[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)  # jaws along the shaft, outwards
    np.testing.assert_allclose(dvrk.forward_kinematics(q, upto=5)[:3, 3], [0.0, 0.0, -0.1344], atol=1e-12)
    # Outer yaw +90 degrees swings the shaft to +x (z3 = (sin q1 cos q2, -sin q2, -cos q1 cos q2)).
    tip = dvrk.forward_kinematics(np.array([math.pi / 2, 0.0, 0.15, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(tip[:3, 3], [0.1435, 0.0, 0.0], atol=1e-12)


def test_tool_tip_frame_is_our_end_effector_frame():
    """x on the yaw (jaw hinge) axis, z along the jaws, the pitch axis 9.1 mm behind the pivot on
    the jaws' line when the wrist is straight (models/mjcf/regrasp_scene.xml's e frame)."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.uniform(dvrk.Q_MIN, dvrk.Q_MAX)
        tip, pitch = dvrk.forward_kinematics(q), dvrk.forward_kinematics(q, upto=5)
        yaw_axis = tip[:3, :3] @ dvrk.TOOLTIP_OFFSET[:3, :3].T @ [0, 0, 1]  # joint 6's z in the base
        assert abs(abs(tip[:3, 0] @ yaw_axis) - 1.0) < 1e-12
        assert abs(np.linalg.det(tip[:3, :3]) - 1.0) < 1e-12
        link = tip[:3, 3] - pitch[:3, 3]
        assert abs(np.linalg.norm(link) - 0.0091) < 1e-12 and abs(link @ tip[:3, 0]) < 1e-12
    straight = np.array([0.2, -0.3, 0.12, 0.7, 0.0, 0.0])
    tip, pitch = dvrk.forward_kinematics(straight), dvrk.forward_kinematics(straight, upto=5)
    np.testing.assert_allclose(tip[:3, 3] - pitch[:3, 3], 0.0091 * tip[:3, 2], atol=1e-12)


def test_ik_round_trip_on_random_reachable_poses():
    rng = np.random.default_rng(0)
    for _ in range(500):
        q = rng.uniform(dvrk.Q_MIN, dvrk.Q_MAX)
        q[2] = rng.uniform(0.03, 0.24)  # the pitch axis beyond the RCM
        pose = dvrk.forward_kinematics(q)
        r = dvrk.inverse_kinematics(pose, q_ref=q)
        assert r.reachable and r.violations == ()
        back = dvrk.forward_kinematics(r.q)
        assert np.linalg.norm(back[:3, 3] - pose[:3, 3]) < 1e-6
        assert r.position_error < 1e-6 and r.rotation_error < 1e-5
        np.testing.assert_allclose(r.q, q, atol=1e-6)


def test_ik_reports_limits_instead_of_clipping():
    q = np.array([0.3, 0.2, 0.1, 0.4, 1.5, -0.2])  # wrist pitch 86 degrees: beyond the LND's 80
    r = dvrk.inverse_kinematics(dvrk.forward_kinematics(q))
    assert not r.reachable and r.violations == ("outer_wrist_pitch",)
    np.testing.assert_allclose(r.q, q, atol=1e-9)  # reported as it is, not clipped
    assert r.position_error < 1e-9
    q = np.array([0.0, 0.0, 0.30, 0.0, 0.0, 0.0])  # inserted 300 mm: beyond the 240 mm stroke
    assert dvrk.inverse_kinematics(dvrk.forward_kinematics(q)).violations == ("outer_insertion",)
    with pytest.raises(ValueError, match="unit quaternion"):
        dvrk.inverse_kinematics([0, 0, 0.1, 2, 0, 0, 0])


def test_roll_follows_the_reference_and_trajectories_stay_continuous():
    q = np.array([0.1, 0.1, 0.12, 3.5, 0.2, 0.1])  # roll 200 degrees, inside the +-260 range
    pose = dvrk.forward_kinematics(q)
    assert abs(dvrk.inverse_kinematics(pose, q_ref=q).q[3] - 3.5) < 1e-9
    assert abs(dvrk.inverse_kinematics(pose).q[3] - (3.5 - 2 * math.pi)) < 1e-9  # nearest zero
    base = dvrk.base_behind(np.r_[0.01, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    poses = np.array([[0.01, 0.0, 0.001 * k, 1.0, 0.0, 0.0, 0.0] for k in range(5)])
    traj = dvrk.joint_trajectory(base, poses)
    assert traj.all_reachable
    np.testing.assert_allclose(traj.q[0], [0, 0, 0.12 - dvrk.PITCH_FROM_RCM, 0, 0, 0], atol=1e-9)  # neutral
    assert np.all(np.abs(np.diff(traj.q, axis=0)).max(0) < 0.02)
