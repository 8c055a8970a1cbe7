"""dVRK PSM kinematics: FK against hand-worked poses, IK round trips, limits reported, and the
tool-tip frame being this project's end-effector frame."""

from __future__ import annotations

import math
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest

from regrasp_mjx.robot import dvrk, psm_joints


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
    traj = psm_joints.joint_trajectory(base, poses)
    assert traj.all_reachable
    np.testing.assert_allclose(traj.q[0], [0, 0, 0.12 - dvrk.PITCH_FROM_RCM, 0, 0, 0], atol=1e-9)  # neutral
    assert np.all(np.abs(np.diff(traj.q, axis=0)).max(0) < 0.02)


def test_a_roll_walk_to_its_limit_never_jumps_a_turn():
    """Issue 48: a trajectory whose roll walks towards +-260 degrees keeps each roll nearest the
    previous one (never a 360-degree jump, which the arm cannot make between two poses); the first
    pose takes the turn that keeps the walk within the limits; a walk longer than the 520-degree
    range is reported out of limits where it leaves them, still continuous."""
    from scipy.spatial.transform import Rotation

    def poses(rolls):
        out = []
        for roll in rolls:
            t = dvrk.forward_kinematics(np.array([0.1, 0.1, 0.12, roll, 0.2, 0.1]))
            out.append(np.r_[t[:3, 3], Rotation.from_matrix(t[:3, :3]).as_quat()[[3, 0, 1, 2]]])
        return np.array(out)

    up = np.radians(np.arange(170.0, 300.0, 5.0))  # 170 -> 295 degrees: past +260 from the nearest-0 turn
    traj = psm_joints.joint_trajectory(np.eye(4), poses(up))
    assert np.abs(np.diff(traj.q[:, 3])).max() < np.radians(6.0)  # continuous: 5 degrees a pose
    assert traj.all_reachable  # walked as -190 -> -65 degrees
    np.testing.assert_allclose(traj.q[:, 3], up - 2 * math.pi, atol=1e-9)
    # the same walk from a reference at +170: it keeps that turn and leaves the limit at 265 degrees
    traj = psm_joints.joint_trajectory(np.eye(4), poses(up), q_ref=np.array([0, 0, 0, up[0], 0, 0]))
    assert np.abs(np.diff(traj.q[:, 3])).max() < np.radians(6.0)
    np.testing.assert_allclose(traj.q[:, 3], up, atol=1e-9)
    beyond = np.degrees(up) > 260.0 + 1e-6
    np.testing.assert_array_equal(traj.reachable, ~beyond)
    assert all(v == ("outer_roll",) for v, b in zip(traj.violations, beyond) if b)
    # a roll a rounding past its limit is put on it, not sent a turn away
    at_limit = dvrk.forward_kinematics(np.array([0.1, 0.1, 0.12, dvrk.Q_MAX[3], 0.2, 0.1]))
    r = dvrk.inverse_kinematics(at_limit, q_ref=np.array([0, 0, 0, dvrk.Q_MAX[3] + 1e-10, 0, 0]))
    assert r.reachable and abs(r.q[3] - dvrk.Q_MAX[3]) < 1e-9


def test_ik_is_exact_at_the_crossing():
    """Issue 48: with the insertion exactly at the pitch-point/RCM crossing (15.6 mm), and within a
    micrometre of it, every in-limit joint vector's pose is reachable (the straight wrist alone put
    the outer pitch out of its limits for about 30 % of them), its residual below the tolerance."""
    rng = np.random.default_rng(48)
    for offset in (0.0, 1e-9, 5e-7):
        for _ in range(200):
            q = rng.uniform(dvrk.Q_MIN, dvrk.Q_MAX)
            q[2] = -dvrk.PITCH_FROM_RCM + offset
            r = dvrk.inverse_kinematics(dvrk.forward_kinematics(q))
            assert r.reachable, (q, r)
            assert r.position_error < (1e-12 if offset == 0.0 else dvrk.IK_POSITION_TOLERANCE)


def _quat(m):
    """wxyz of a rotation matrix (for the JAX check's inputs)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(m).as_quat()[..., [3, 0, 1, 2]]


def _edge_joints():
    """The limits' edges: insertion at its minimum, 0.1 mm, the pitch axis at the RCM, its maximum;
    outer pitch, wrist pitch and wrist yaw at their limits; roll at +-260 degrees."""
    base = np.array([0.2, -0.1, 0.1, 0.3, 0.2, -0.3])
    edges = []
    for i, values in (
        (2, [dvrk.Q_MIN[2], 1e-4, -dvrk.PITCH_FROM_RCM, dvrk.Q_MAX[2]]),
        (1, [dvrk.Q_MIN[1], dvrk.Q_MAX[1]]),
        (4, [dvrk.Q_MIN[4], dvrk.Q_MAX[4]]),
        (5, [dvrk.Q_MIN[5], dvrk.Q_MAX[5]]),
        (3, [dvrk.Q_MIN[3], dvrk.Q_MAX[3]]),
    ):
        for v in values:
            for q3 in (0.0, 1e-4, 0.01, 0.12):  # every edge also at small insertions
                q = base.copy()
                q[2] = q3
                q[i] = v
                edges.append(q)
    return np.array(edges)


def test_ik_round_trip_over_the_whole_insertion_range_and_the_jax_verdict_agrees():
    """FK -> IK -> FK for 10,000 joint vectors drawn within the json's limits and the edges: every
    residual below 1e-6 m / 1e-5 rad, every verdict reachable, on both sides of the pitch axis
    crossing the RCM (insertion 15.6 mm); the jitted check used by the shield says the same."""
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(7)
    qs = np.concatenate([rng.uniform(dvrk.Q_MIN, dvrk.Q_MAX, size=(10_000, 6)), _edge_joints()])
    assert (qs[:, 2] < -dvrk.PITCH_FROM_RCM).sum() > 500  # the pitch axis behind the RCM is well covered
    poses = np.array([dvrk.forward_kinematics(q) for q in qs])
    for q, pose in zip(qs, poses):
        r = dvrk.inverse_kinematics(pose, q_ref=q)
        assert r.position_error < 1e-6 and r.rotation_error < 1e-5, (q, r)
        assert r.reachable and r.violations == (), q
        np.testing.assert_allclose(dvrk.forward_kinematics(r.q), pose, atol=1e-9)
    check = jax.jit(jax.vmap(dvrk.within_limits_jax, in_axes=(None, 0, 0)))
    verdict = np.asarray(
        check(jnp.eye(4), jnp.asarray(poses[:, :3, 3], jnp.float32), jnp.asarray(_quat(poses[:, :3, :3]), jnp.float32))
    )
    assert verdict.all()


def test_poses_out_of_reach_are_refused_by_both_checks():
    import jax
    import jax.numpy as jnp

    qs = np.array(
        [
            [0.3, 0.2, 0.1, 0.4, 1.5, -0.2],  # wrist pitch 86 degrees: beyond the LND's 80
            [0.0, 0.0, 0.30, 0.0, 0.0, 0.0],  # inserted 300 mm: beyond the 240 mm stroke
            [0.1, 0.0, 0.05, 0.0, 0.0, 1.45],  # wrist yaw beyond its limit
            [0.1, 1.0, 0.05, 0.0, 0.0, 0.0],  # outer pitch 57 degrees: beyond 53
        ]
    )
    poses = np.array([dvrk.forward_kinematics(q) for q in qs])
    for pose in poses:
        r = dvrk.inverse_kinematics(pose)
        assert not r.reachable and r.violations and r.position_error < 1e-9
    check = jax.vmap(dvrk.within_limits_jax, in_axes=(None, 0, 0))
    verdict = check(
        jnp.eye(4), jnp.asarray(poses[:, :3, 3], jnp.float32), jnp.asarray(_quat(poses[:, :3, :3]), jnp.float32)
    )
    assert not np.asarray(verdict).any()
    # a pose the arm cannot realise at all (the wrist link cannot span it): a residual, not reachable
    far = dvrk.forward_kinematics(np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]))
    far[:3, 3] += [0.0, 0.0, 0.001]  # the tip moved along the shaft but the wrist kept: no joints do this
    r = dvrk.inverse_kinematics(far @ np.diag([1.0, 1.0, 1.0, 1.0]))
    assert r.reachable == (r.position_error < dvrk.IK_POSITION_TOLERANCE)


def test_reachability_counts_the_successful_plans_and_the_joints_that_leave_their_limits():
    def as_pose(t):
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, t[:3, :3].flatten())
        return np.r_[t[:3, 3], quat]

    base = np.eye(4)
    near = dvrk.forward_kinematics(np.array([0.0, 0.0, 0.12, 0.0, 0.0, 0.0]))
    far = dvrk.forward_kinematics(np.array([0.0, 0.0, 0.12, 0.0, 1.5, 0.0]))  # wrist pitch 86 degrees
    poses = np.array([[as_pose(near), as_pose(near)], [as_pose(near), as_pose(far)], [as_pose(far)] * 2])
    plan = SimpleNamespace(success=np.array([True, True, False]), steps=np.array([1, 1, 1]), poses=poses)
    r = psm_joints.reachability(plan, base)
    assert r["plans"] == 2 and r["all_reachable_share"] == 0.5  # the failed plan is not counted
    assert r["out_of_limit_poses_by_joint"] == {"outer_wrist_pitch": 1}
    # median of |dq| per plan: 0 and 1.5 rad of wrist pitch
    assert r["joint_path_median"]["wrist_pitch_deg"] == pytest.approx(np.degrees(0.75), abs=1e-4)
    assert r["joint_path_median"]["insertion_mm"] == pytest.approx(0.0, abs=1e-6)
    assert psm_joints.reachability(plan, lambda i: base) == r  # a base per plan
