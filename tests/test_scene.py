"""The MJCF: needle geometry, collision filtering, the tunnelling bound, host vs MJX verdicts."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.core import geometry as g
from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.world.scene import load_scene


def test_needle_capsules_follow_the_arc():
    scene = load_scene()
    caps = scene.needle_capsules
    assert len(caps) == 56
    ends = np.array([p for c in caps for p in (c.p0, c.p1)])
    np.testing.assert_allclose(ends[:, 0], 0.0, atol=1e-9)  # needle in the y-z plane
    # ends moved out from the arc by k = 2 / (1 + cos h), h = 90/56 deg: 5.4 mm -> 5.401062 mm
    half = math.pi / 112
    np.testing.assert_allclose(np.linalg.norm(ends, axis=1), 0.0054 * 2 / (1 + math.cos(half)), atol=1e-10)
    alpha = np.mod(np.arctan2(ends[:, 2], ends[:, 1]), 2 * np.pi)
    alpha = np.unique(np.round(alpha, 6))
    np.testing.assert_allclose(alpha, np.linspace(np.pi / 2, 3 * np.pi / 2, 57), atol=1e-6)
    # the wire radius plus e = R tan^2(h/2) (conservative_needle) = 1.062 um
    assert all(c.radius == pytest.approx(0.00025 + 0.0054 * math.tan(half / 2) ** 2, abs=1e-10) for c in caps)
    for c0, c1 in zip(caps, caps[1:]):  # a chain without gaps, along the arc: neighbours share an end
        gaps = [np.linalg.norm(a - b) for a in (c0.p0, c0.p1) for b in (c1.p0, c1.p1)]
        assert min(gaps) < 1e-9
    frames = scene.capsule_frames  # the same chords, in order along the arc, for the JAX and lean paths
    np.testing.assert_allclose(frames.other_ends[frames.chords, 0], [c.p0 for c in caps], atol=1e-12)
    np.testing.assert_allclose(frames.other_ends[frames.chords, 1], [c.p1 for c in caps], atol=1e-12)


def test_scene_config_changes_the_geometry():
    scene = load_scene(SceneConfig(jaw_angle_deg=40.0, wire_radius_mm=0.3, needle_radius_mm=6.0))
    jaw = scene.regrasp_capsules[0]
    tip = jaw.p0 if np.linalg.norm(jaw.p0) > np.linalg.norm(jaw.p1) else jaw.p1
    assert math.degrees(math.atan2(abs(tip[1]), tip[2])) == pytest.approx(20.0, abs=1e-6)
    half = math.pi / 112
    assert scene.needle_capsules[0].radius == pytest.approx(0.0003 + 0.006 * math.tan(half / 2) ** 2, abs=1e-10)
    assert np.linalg.norm(scene.needle_capsules[3].p0) == pytest.approx(0.006 * 2 / (1 + math.cos(half)), abs=1e-10)


def test_only_the_counted_pairs_collide():
    scene = load_scene()
    m = scene.model
    regrasp = {c.geom_id for c in scene.regrasp_capsules}
    needle = {c.geom_id for c in scene.needle_capsules}
    grasp = {c.geom_id for c in scene.grasp_capsules}

    def can_collide(i, j):
        return bool((m.geom_contype[i] & m.geom_conaffinity[j]) or (m.geom_contype[j] & m.geom_conaffinity[i]))

    for i in range(m.ngeom):
        for j in range(i + 1, m.ngeom):
            counted = (i in regrasp) != (j in regrasp)
            assert can_collide(i, j) == counted, (m.geom(i).name, m.geom(j).name)
    assert len(scene.pairs) == len(regrasp) * (len(needle) + len(grasp))


def test_host_checker_agrees_with_mjx(distance_fn, paper_testset):
    """A few thousand random poses around the needle: the same collide/free verdict on both."""
    episodes, _ = paper_testset
    checker = HostChecker()
    n = 2000
    rng = np.random.default_rng(0)
    rows = rng.integers(0, len(episodes), n)
    needle_pos, needle_quat = episodes.needle_pos[rows], episodes.needle_quat[rows]
    # Poses between the start and the goal, shaken by up to 2 mm and 20 degrees: many near contacts.
    s = rng.uniform(0, 1, (n, 1))
    pos = episodes.start_pos[rows] * (1 - s) + episodes.goal_pos[rows] * s + rng.uniform(-2e-3, 2e-3, (n, 3))
    rotvec = rng.normal(size=(n, 3))
    rotvec *= np.radians(rng.uniform(0, 20, (n, 1))) / np.linalg.norm(rotvec, axis=1, keepdims=True)
    quat = np.asarray(g.quat_mul(g.quat_from_rotvec(jnp.asarray(rotvec)), jnp.asarray(episodes.goal_quat[rows])))
    mjx_dist = np.asarray(distance_fn(*(jnp.asarray(a, jnp.float32) for a in (needle_pos, needle_quat, pos, quat))))
    mjx_min = mjx_dist.min(axis=1)
    host = np.array([checker.collides(needle_pos[i], needle_quat[i], pos[i], quat[i]) for i in range(n)])
    mjx_collides = mjx_min < 0
    assert 0.2 < host.mean() < 0.8, "the poses should mix free and colliding ones"
    # float32 on the device vs float64 on the host: only poses within 1 micron of contact may differ.
    differ = host != mjx_collides
    assert np.all(np.abs(mjx_min[differ]) < 1e-6), mjx_min[differ]
    # Every pair's distance agrees with MuJoCo's exact mj_geomDistance, not only the verdicts.
    for i in rng.choice(n, 100, replace=False):
        host_d = checker.distances(needle_pos[i], needle_quat[i], pos[i], quat[i])
        np.testing.assert_allclose(mjx_dist[i], host_d, atol=1e-6)


def test_segment_distance_by_hand():
    # Crossing at right angles 1 apart; parallel and overlapping; collinear with a gap; end to middle.
    a0 = jnp.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    a1 = jnp.array([[2.0, 0, 0], [2, 0, 0], [1, 0, 0], [1, 0, 0]])
    b0 = jnp.array([[1.0, -1, 1], [1, 0.5, 0], [3, 0, 0], [2, -1, 3]])
    b1 = jnp.array([[1.0, 1, 1], [3, 0.5, 0], [4, 0, 0], [2, 1, 3]])
    expected = [1.0, 0.5, 2.0, math.sqrt(1 + 9)]
    np.testing.assert_allclose(np.asarray(g.segment_distance(a0, a1, b0, b1)), expected, atol=1e-6)


def test_missing_mjcf_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="scene MJCF not found"):
        load_scene(SceneConfig(), str(tmp_path / "nope.xml"))


def test_importing_the_package_prints_nothing():
    """mujoco.mjx prints "Failed to import warp" when Warp is absent; the package swallows exactly
    that, so `evaluate --json` and friends print only their own output."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", "import regrasp_mjx.envs.env, regrasp_mjx.inference.policy"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout == ""
