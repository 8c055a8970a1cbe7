"""The regrasping jaws at another opening (world/jaw.py) and opened before the first move
(inference/jaw_opening.py): hand-worked geometry, the sweep's proof between check points, the ladder's
choice, and the executor's passes."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.core.config import ConfigError, SceneConfig
from regrasp_mjx.envs.camera_errors import CameraErrors, Tracking
from regrasp_mjx.inference import jaw_opening
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.world import jaw
from regrasp_mjx.world.scene import load_scene


@pytest.fixture(scope="module")
def default_policy():
    # a policy that keeps its jaws on the way (the default until 2026-11-29): the start-time opening's subject
    return load_policy("student_v3")


JAW_LENGTH = math.hypot(0.0016670, 0.0094542)  # the MJCF's regrasp_jaw_a: from the pivot to (0, 1.667, 9.4542) mm


def test_opened_jaws_are_the_scene_built_at_that_opening():
    scene = load_scene()
    for deg in (30.0, 40.0, 80.0):
        wide = load_scene(SceneConfig(jaw_angle_deg=deg))
        np.testing.assert_allclose(jaw.opened_ends(scene, deg), wide.capsule_frames.tool_ends, atol=1e-12)
    # by hand: at 40 degrees each jaw's tip is 20 degrees off the tool axis, the pivot stays
    a, b = (
        ends[np.argsort(np.linalg.norm(ends, axis=1))] for ends in jaw.opened_ends(scene, 40.0)[jaw.jaw_rows(scene)]
    )
    tip = JAW_LENGTH * np.array([0.0, math.sin(math.radians(20)), math.cos(math.radians(20))])
    np.testing.assert_allclose(a[1], tip, atol=1e-9)  # [pivot, tip] each
    np.testing.assert_allclose(b[1], tip * [1, -1, 1], atol=1e-9)
    np.testing.assert_allclose(a[0], 0.0, atol=1e-12)
    assert jaw.jaw_reach(scene) == pytest.approx(JAW_LENGTH, abs=1e-9)


def test_sample_angles_and_rungs():
    np.testing.assert_allclose(jaw.sample_angles(20.0, 23.5), [20.0, 20.875, 21.75, 22.625, 23.5])
    np.testing.assert_allclose(jaw_opening.rungs(20.0, 45.0), [20.0, 30.0, 40.0, 45.0])
    np.testing.assert_allclose(jaw_opening.rungs(20.0, 20.0), [20.0])


def _pose(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    import jaxlie

    return np.concatenate([position, np.asarray(jaxlie.SO3.from_matrix(rotation).wxyz)])


def _wire_past_the_tip(scene, deg: float, gap: float):
    """A needle pose whose middle chord lies along the hinge just past jaw a's tip at opening ``deg``:
    ``gap`` [m] from the tip's capsule there (negative: into it), the jaw passing it by on either side
    of that opening, the needle bending away; the tool at the identity 50 mm from the grasping tool."""
    frames = scene.capsule_frames
    ee = np.array([0.05, 0.05, 0.05])
    half = math.radians(deg) / 2.0
    out = np.array([0.0, math.sin(half), math.cos(half)])  # along the jaw, from the pivot
    chord = frames.chords[len(frames.chords) // 2]
    p0, p1 = frames.other_ends[chord]
    radius = frames.other_radii[chord] + frames.tool_radii[jaw.jaw_rows(scene)[0]]
    mid, along = (p0 + p1) / 2.0, (p1 - p0) / np.linalg.norm(p1 - p0)
    inward = -mid - (-mid @ along) * along  # from the chord to the needle's centre
    inward /= np.linalg.norm(inward)
    world = np.stack([[1.0, 0.0, 0.0], out, np.cross([1.0, 0.0, 0.0], out)], 1)
    local = np.stack([along, inward, np.cross(along, inward)], 1)
    rotation = world @ local.T
    needle = _pose(rotation, ee + out * (JAW_LENGTH + radius + gap) - rotation @ mid)
    return needle, np.concatenate([ee, [1.0, 0.0, 0.0, 0.0]])


def test_a_jaw_opening_into_the_wire_is_caught_between_check_points():
    """Check points 4 degrees apart (20, 24, 28, 32) and the wire 5 um into the tip's path at 26
    degrees, the jaw passing it by on either side: every check point sees it clear, the scene built at
    26 degrees sees the contact, and the sweep is not proved clear (the slack); 0.1 mm beyond the slack
    it is."""
    scene = load_scene()
    angles, fn = jaw.opening_fn(scene, 32.0, step_deg=4.0)
    np.testing.assert_allclose(angles, [20.0, 24.0, 28.0, 32.0])
    slack = JAW_LENGTH * math.radians(4.0) / 4.0
    r, w = np.float32(5.4e-3), np.float32(0.25e-3)

    def sweep(needle, ee):
        n, e = (np.asarray(x, np.float32)[None] for x in (needle, ee))
        return np.asarray(fn(n[:, :3], n[:, 3:], e[:, :3], e[:, 3:], r[None], w[None]))[0]

    needle, ee = _wire_past_the_tip(scene, 26.0, -5e-6)
    exact = load_scene(SceneConfig(jaw_angle_deg=26.0)).distance_fn()
    at = np.asarray(exact(*(jnp.asarray(x, jnp.float32) for x in (needle[:3], needle[3:], ee[:3], ee[3:]))))
    assert at.min() < 0.0  # the jaw at 26 degrees touches the wire
    assert np.all(sweep(needle, ee) + slack > 0.0)  # no check point sees the contact
    assert np.any(sweep(needle, ee) < 0.0)  # the slack does: not proved clear
    assert jaw.widest_clear(angles, sweep(needle, ee)[None], np.array([20.0, 32.0]), 0.0)[0] == 20.0
    far, ee = _wire_past_the_tip(scene, 26.0, 1e-4 + slack)
    assert np.all(sweep(far, ee) >= 0.0)
    assert jaw.widest_clear(angles, sweep(far, ee)[None], np.array([20.0, 32.0]), 0.0)[0] == 32.0


def test_widest_clear_takes_the_last_rung_of_the_clear_prefix():
    angles = np.arange(20.0, 41.0)
    c = np.full((3, len(angles)), 1e-3)
    c[1, 15] = 0.0  # 35 degrees not clear of a 0.5 mm margin
    c[2, 0] = -1.0  # the start itself within the margin: stays
    got = jaw.widest_clear(angles, c, np.array([20.0, 30.0, 40.0]), 0.5e-3)
    np.testing.assert_allclose(got, [40.0, 30.0, 20.0])


def test_relative_view_error_by_hand():
    camera = CameraErrors(Tracking(bias_mm=1.0), Tracking(white_mm=0.5), depth_factor=2.0)
    # needle: a 1 mm bias spread over 3 axes; each tool's white noise over 4 frames; depth doubles it
    assert camera.relative_sd_mm(4) == pytest.approx(2.0 * math.sqrt(1.0 / 3.0 + 2 * 0.25 / 4), rel=1e-6)
    assert CameraErrors().relative_sd_mm(10) == 0.0


def test_bad_jaw_settings_are_refused(default_policy):
    for deg in (10.0, 81.0, float("nan"), "40"):
        with pytest.raises(ConfigError, match="jaw_deg"):
            jaw_opening.check(default_policy, deg, None)
    with pytest.raises(ConfigError, match="jaw_sigmas"):
        jaw_opening.check(default_policy, 40.0, -1.0)
    assert jaw_opening.check(default_policy, None, None) == (20.0, 2.0)  # the policy's own: kept


@pytest.mark.slow  # 124 s on the 2-core VM (the quick tier's 20 minutes; CI runs the long tier too)
def test_execute_opens_where_the_view_allows_and_each_row_is_its_openings_pass(default_policy, paper_testset):
    """Exact views: the decision is the truth's, so no sweep collides; a row opened to 30 degrees
    has the outcome of the 30 degree policy's own pass, the others the 20 degree one's."""
    from regrasp_mjx.world.sampling import episode_poses

    needle, start, goal = (x[:12] for x in episode_poses(paper_testset[0]))
    r = default_policy.execute(needle, start, goal, seed=3, jaw_deg=30.0, jaw_sigmas=0.0)
    assert set(np.unique(r["jaw_deg"])) <= {20.0, 30.0} and (r["jaw_deg"] == 30.0).any()
    assert not r["opening_collision"].any()
    wide = jaw_opening.opened(default_policy, 30.0).execute(needle, start, goal, seed=3)
    narrow = default_policy.execute(needle, start, goal, seed=3)
    for k in ("success", "collision", "steps", "poses"):
        expect = np.where((r["jaw_deg"] == 30.0).reshape((-1,) + (1,) * (r[k].ndim - 1)), wide[k], narrow[k])
        np.testing.assert_array_equal(r[k], expect, err_msg=k)
    assert jax.tree.map(np.shape, r["start_seen"]) == (12, 14)
