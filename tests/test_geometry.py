"""grasp_pose against hand-worked values, and the ego-centric invariance of the observation."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.core import geometry as g

R = 0.0054


def test_goal_grasp_pose_by_hand():
    # alpha* = 4pi/3, theta* = 0, phi* = pi, d = 7 mm (SPEC goal). By hand:
    # p(alpha) = (0, R cos 240deg, R sin 240deg) = (0, -2.7, -4.67654) mm; offset (d cos pi, 0, 0).
    # z_e points from the end-effector at the grasping point: +x_n. Tangent (0, -sin a, cos a) =
    # (0, sqrt3/2, -1/2) is already normal to z_e, so x_e = it and y_e = z_e x x_e = (0, 1/2, sqrt3/2).
    pos, quat = g.grasp_pose(4 * math.pi / 3, 0.007, 0.0, math.pi)
    np.testing.assert_allclose(np.asarray(pos) * 1e3, [-7.0, -2.7, -4.676537], atol=1e-5)
    rot = np.asarray(g.rotation_matrix(quat))
    s3 = math.sqrt(3) / 2
    np.testing.assert_allclose(rot[:, 0], [0, s3, -0.5], atol=1e-6)
    np.testing.assert_allclose(rot[:, 1], [0, 0.5, s3], atol=1e-6)
    np.testing.assert_allclose(rot[:, 2], [1, 0, 0], atol=1e-6)
    # Its quaternion: the rotation by the matrix above, w >= 0. Worked by Shepperd's method:
    # trace = 0 + 0.5 + 0 = 0.5, w = sqrt(1 + 0.5) / 2 = 0.612372.
    assert float(quat[0]) == pytest.approx(math.sqrt(1.5) / 2, abs=1e-6)


def test_side_grasp_by_hand():
    # alpha = pi: p = (0, -R, 0); theta = 0, phi = pi/2: offset (0, d, 0), so the end-effector sits at
    # (0, d - R, 0) and z_e = (0, -1, 0). The tangent (0, 0, -1) is normal to z_e: x_e = (0, 0, -1),
    # y_e = z_e x x_e = (1, 0, 0).
    pos, quat = g.grasp_pose(math.pi, 0.007, 0.0, math.pi / 2)
    np.testing.assert_allclose(np.asarray(pos), [0.0, 0.007 - R, 0.0], atol=1e-8)
    rot = np.asarray(g.rotation_matrix(quat))
    np.testing.assert_allclose(rot, [[0, 1, 0], [0, 0, -1], [-1, 0, 0]], atol=1e-6)


def test_grasp_pose_points_at_grasping_point_and_hinge_along_wire():
    key = jax.random.PRNGKey(0)
    k = jax.random.split(key, 4)
    n = 500
    alpha = jax.random.uniform(k[0], (n,), minval=math.pi / 2, maxval=3 * math.pi / 2)
    depth = jax.random.uniform(k[1], (n,), minval=0.0065, maxval=0.008)
    theta = jax.random.uniform(k[2], (n,), maxval=2 * math.pi)
    phi = jax.random.uniform(k[3], (n,), maxval=0.4 * math.pi)
    pos, quat = g.grasp_pose(alpha, depth, theta, phi)
    assert pos.shape == (n, 3) and quat.shape == (n, 4)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-5)
    assert np.all(np.asarray(quat)[:, 0] >= 0)
    rot = np.asarray(g.rotation_matrix(quat))
    to_point = np.asarray(g.needle_point(alpha)) - np.asarray(pos)
    np.testing.assert_allclose(np.linalg.norm(to_point, axis=-1), depth, rtol=1e-5)
    np.testing.assert_allclose(rot[:, :, 2], to_point / np.linalg.norm(to_point, axis=-1, keepdims=True), atol=1e-5)
    # x_e is the tangent projected normal to z_e: it has no component along y_e.
    tangent = np.asarray(g.needle_tangent(alpha))
    np.testing.assert_allclose(np.einsum("ni,ni->n", tangent, rot[:, :, 1]), 0.0, atol=1e-5)
    assert np.all(np.einsum("ni,ni->n", tangent, rot[:, :, 0]) > 0)


def test_grasp_pose_degenerate_roll_falls_back_to_needle_normal():
    # Jaws along the wire: alpha = pi, phi = pi/2, theta = pi/2 gives offset (0, 0, d) and z_e = -z_n,
    # parallel to the tangent (0, 0, -1). x_e must then be the needle normal x_n.
    _, quat = g.grasp_pose(math.pi, 0.007, math.pi / 2, math.pi / 2)
    rot = np.asarray(g.rotation_matrix(quat))
    np.testing.assert_allclose(rot[:, 0], [1, 0, 0], atol=1e-5)
    assert np.all(np.isfinite(rot))


def _random_pose(key):
    k1, k2 = jax.random.split(key)
    q = jax.random.normal(k1, (4,))
    return jax.random.normal(k2, (3,)) * 0.05, q / jnp.linalg.norm(q)


def test_ego_observation_invariant_to_a_rigid_transform_of_the_world():
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    eg, er, n, world = (_random_pose(k) for k in keys)
    obs = g.ego_observation(eg, er, n)
    moved = g.ego_observation(g.compose(world, eg), g.compose(world, er), g.compose(world, n))
    assert obs.shape == (21,)
    np.testing.assert_allclose(np.asarray(moved), np.asarray(obs), atol=1e-5)
    # ...and a transform of one object alone does change it (the test could fail).
    other = g.ego_observation(eg, g.compose(world, er), n)
    assert np.max(np.abs(np.asarray(other) - np.asarray(obs))) > 1e-3
    # With e_g as the world the shortcut used by the environment gives the same numbers.
    identity = (jnp.zeros(3), jnp.array([1.0, 0, 0, 0]))
    eg_n, eg_er = g.relative(eg, n), g.relative(eg, er)
    np.testing.assert_allclose(
        np.asarray(g.ego_observation_eg(eg_n, eg_er)), np.asarray(g.ego_observation(identity, eg_er, eg_n)), atol=1e-6
    )


def test_quat_angle_ignores_sign_and_measures_the_rotation():
    q = g.quat_from_rotvec(jnp.array([0.0, 0.0, math.radians(30)]))
    ident = jnp.array([1.0, 0.0, 0.0, 0.0])
    assert math.degrees(float(g.quat_angle(q, ident))) == pytest.approx(30.0, abs=1e-4)
    assert math.degrees(float(g.quat_angle(-q, ident))) == pytest.approx(30.0, abs=1e-4)
    assert float(g.quat_angle(q, q)) == pytest.approx(0.0, abs=1e-3)
