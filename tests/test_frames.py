"""Labelled stereo frames rendered for real (MuJoCo's OpenGL renderer; skipped with the reason where no
OpenGL context can be made): the pictures agree with the camera model (the needle's pixels lie on its
projected arc and back-project onto its wire, the stereo pair's disparity is f B / depth), the labels
agree with the pictures, the same seed gives the same frames, and the regrasping jaws are drawn at the
opening asked. Images are 160 x 90: at 64 px across
the 0.5 mm wire is half a pixel wide and drops out of the picture here and there."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.workflows import frames_mjx
from regrasp_mjx.workflows.frames import CLASSES, FrameRenderer
from regrasp_mjx.workflows.render import RenderUnavailable
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.sampling import episode_poses
from tests.conftest import ROOT

RIG = endoscope.Rig(width=160, height=90)
NEEDLE, GRASP, REGRASP = (CLASSES.index(c) for c in ("needle", "grasping_tool", "regrasping_tool"))


@pytest.fixture(scope="module")
def renderer():
    try:
        r = FrameRenderer(rig=RIG)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL on this machine ({err}); the camera model is tested in tests/test_endoscope.py")
    yield r
    r.close()


@pytest.fixture(scope="module")
def batch(renderer, paper_testset):
    needle, start, _ = (np.asarray(x) for x in episode_poses(paper_testset[0]))
    rows = np.arange(6)
    return needle[rows], start[rows], renderer.render(needle[rows], start[rows], seeds=100 + rows)


def _back_project(depth: np.ndarray, k: np.ndarray, camera_to_world: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The e_g points ``[N, 3]`` that the pixels ``mask`` ``[H, W]`` show, from their depth."""
    rows, cols = np.nonzero(mask)
    z = depth[rows, cols].astype(np.float64)
    cam = np.stack([(cols - k[0, 2]) * z / k[0, 0], (rows - k[1, 2]) * z / k[1, 1], z], axis=1)
    return cam @ camera_to_world[:3, :3].T + camera_to_world[:3, 3]


def test_frames_have_their_shapes_and_show_the_scene(batch):
    _, _, f = batch
    b, k = 6, endoscope.N_ARC + 6
    assert f.rgb.shape == (b, 2, 90, 160, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (b, 2, 90, 160) and f.depth.dtype == np.float32
    assert f.segmentation.shape == (b, 2, 90, 160) and f.segmentation.dtype == np.int8
    assert f.extrinsics.shape == (b, 2, 4, 4) and f.poses.shape == (b, 3, 7)
    assert f.pixels.shape == (b, 2, k, 2) and f.visible.shape == f.keypoint_depth.shape == (b, 2, k)
    for i in range(b):
        for c in range(2):
            shown = set(np.unique(f.segmentation[i, c]))
            assert {NEEDLE, GRASP, REGRASP, CLASSES.index("tissue")} <= shown, (i, c, shown)
    assert np.all((f.depth > 0.02) & (f.depth < 0.2))  # the tissue behind everything, nothing at the far plane
    assert f.visible[:, :, 0].sum() >= 4  # the needle's tip is seen in most pictures
    assert f.visible.mean() > 0.6


def test_the_needle_s_pixels_lie_on_its_projected_arc_and_its_keypoints_on_needle_pixels(renderer, batch):
    _, _, f = batch
    r = renderer.endo.scene.config.needle_radius_mm * 1e-3
    alpha = np.linspace(math.pi / 2, 3 * math.pi / 2, 400)
    arc = np.stack([np.zeros_like(alpha), r * np.cos(alpha), r * np.sin(alpha)], axis=1)
    for i in range(len(f.poses)):
        rot = endoscope.quat_matrix(f.poses[i, 0, 3:])
        curve = f.poses[i, 0, :3] + arc @ rot.T
        for c in range(2):
            uv, _ = endoscope.project(curve, f.extrinsics[i, c], f.intrinsics)
            rows, cols = np.nonzero(f.segmentation[i, c] == NEEDLE)
            assert len(rows) > 10
            gap = np.min(np.hypot(cols[:, None] - uv[None, :, 0], rows[:, None] - uv[None, :, 1]), axis=1)
            assert gap.max() < 1.5, (i, c, gap.max())  # every needle pixel within a pixel and a half of the arc
            for k in np.nonzero(f.visible[i, c, : endoscope.N_ARC])[0]:
                u, v = np.rint(f.pixels[i, c, k]).astype(int)
                assert np.any(f.segmentation[i, c, v - 1 : v + 2, u - 1 : u + 2] == NEEDLE), (i, c, k)


def test_the_depth_of_the_needle_s_pixels_puts_them_on_its_wire(renderer, batch):
    """Each needle pixel, back-projected with its depth, the intrinsics and the extrinsics, lies on the
    wire's surface: its distance to the arc is the wire's radius (the render mesh's facets aside)."""
    _, _, f = batch
    cfg = renderer.endo.scene.config
    r, w = cfg.needle_radius_mm * 1e-3, cfg.wire_radius_mm * 1e-3
    for i in range(len(f.poses)):
        rot = endoscope.quat_matrix(f.poses[i, 0, 3:])
        for c in range(2):
            points = _back_project(
                f.depth[i, c], f.intrinsics, endoscope.invert(f.extrinsics[i, c]), f.segmentation[i, c] == NEEDLE
            )
            local = (points - f.poses[i, 0, :3]) @ rot  # in the needle's frame: the arc in its y-z plane
            to_arc = np.hypot(local[:, 0], np.hypot(local[:, 1], local[:, 2]) - r)
            assert np.all(to_arc < w + 2e-5), (i, c, to_arc.max())  # inside the wire
            on_surface = np.abs(to_arc - w) < 2e-5  # but on the flat ends at the tip and the thread
            assert on_surface.mean() > 0.9, (i, c, on_surface.mean())
        # and the keypoints' depths agree with the depth image where they are seen
        for c in range(2):
            for k in np.nonzero(f.visible[i, c, : endoscope.N_ARC])[0]:
                u, v = np.rint(f.pixels[i, c, k]).astype(int)
                win = (slice(v - 1, v + 2), slice(u - 1, u + 2))
                near = f.depth[i, c][win][f.segmentation[i, c][win] == NEEDLE]
                assert np.min(np.abs(near - f.keypoint_depth[i, c, k])) < w + 2e-4


def test_the_stereo_pair_s_disparity_is_f_b_over_depth(batch):
    """Each needle pixel of one image, moved by the disparity f B / depth its depth gives (left to
    right: to the left, on the same row), lands on the needle in the other image, within a pixel (but
    where the other camera sees that part hidden); each keypoint's projected disparity is f B / z."""
    _, _, f = batch
    f_px, base = RIG.focal_px, RIG.baseline_m
    for i in range(len(f.poses)):
        for c, sign in ((0, -1.0), (1, 1.0)):
            rows, cols = np.nonzero(f.segmentation[i, c] == NEEDLE)
            moved = np.rint(cols + sign * f_px * base / f.depth[i, c][rows, cols]).astype(int)
            other = np.pad(f.segmentation[i, 1 - c] == NEEDLE, 1)
            hits = np.zeros(len(rows), bool)
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    hits |= other[np.clip(rows + 1 + dr, 0, 91), np.clip(moved + 1 + dc, 0, 161)]
            assert hits.mean() > 0.9, (i, c, hits.mean())
    disparity = f.pixels[:, 0, :, 0] - f.pixels[:, 1, :, 0]
    np.testing.assert_allclose(disparity, f_px * base / f.keypoint_depth[:, 0], rtol=1e-9)
    np.testing.assert_allclose(f.pixels[:, 0, :, 1], f.pixels[:, 1, :, 1], atol=1e-9)


def test_the_true_poses_and_cameras_are_the_labels(batch):
    needle, start, f = batch
    np.testing.assert_array_equal(f.poses[:, 0], needle)
    np.testing.assert_array_equal(f.poses[:, 2], start)
    np.testing.assert_allclose(f.poses[:, 1], np.broadcast_to([0, 0, 0, 1, 0, 0, 0], (6, 7)))
    np.testing.assert_allclose(f.intrinsics, RIG.intrinsics())
    cams = endoscope.camera_poses(RIG, f.draws.camera_shift, f.draws.camera_rotvec)
    np.testing.assert_allclose(f.extrinsics, endoscope.invert(cams), atol=1e-12)
    in_camera = f.camera_poses(1)
    np.testing.assert_allclose(in_camera[:, 1], f.extrinsics[:, 1], atol=1e-12)  # the grasping tool is e_g
    np.testing.assert_allclose(
        in_camera[:, 0, :3, 3], (f.extrinsics[:, 1, :3, :3] @ needle[:, :3, None])[..., 0] + f.extrinsics[:, 1, :3, 3]
    )


def test_the_same_seed_gives_the_same_frames_and_another_seed_others(renderer, batch):
    needle, start, f = batch
    again = renderer.render(needle[:2], start[:2], seeds=[100, 101])
    for name in ("rgb", "depth", "segmentation", "pixels", "visible", "extrinsics"):
        np.testing.assert_array_equal(getattr(again, name), getattr(f, name)[:2], err_msg=name)
    other = renderer.render(needle[:2], start[:2], seeds=[7, 8])
    assert not np.allclose(other.extrinsics, f.extrinsics[:2])
    assert not np.allclose(other.draws.tissue_rgb, f.draws.tissue_rgb[:2])
    assert np.abs(other.rgb.astype(int) - f.rgb[:2]).mean() > 5
    later = renderer.render(needle[:2], start[:2], seeds=[100, 101], frame=1)  # the next frame: new noise only
    np.testing.assert_array_equal(later.depth, f.depth[:2])
    assert not np.array_equal(later.rgb, f.rgb[:2]) or not f.draws.noise[:2].any()
    clean = renderer.render(needle[:2], start[:2], seeds=[100, 101], degrade=False)
    np.testing.assert_array_equal(clean.segmentation, f.segmentation[:2])
    assert not np.array_equal(clean.rgb, f.rgb[:2])


def test_the_jaws_are_drawn_at_the_opening_asked(renderer, batch):
    """``jaw_deg=40`` on the 20-degree scene draws the regrasping jaws as a renderer of the 40-degree scene
    draws its own (the same pixels, depth and classes; the jaws' tips' labels with them), per state; None
    and the scene's own 20 draw them as before; the next frame without ``jaw_deg`` is at the scene's again."""
    needle, start, f = batch
    rows, seeds = slice(0, 3), [100, 101, 102]
    wide = FrameRenderer(SceneConfig(jaw_angle_deg=40.0), rig=RIG)
    try:
        ref = wide.render(needle[rows], start[rows], seeds=seeds)
    finally:
        wide.close()
    opened = renderer.render(needle[rows], start[rows], seeds=seeds, jaw_deg=[40.0, 20.0, 40.0])
    tips = [f.names.index(f"regrasp_jaw_{s}_tip") for s in ("a", "b")]
    for i, want in ((0, ref), (1, f), (2, ref)):  # the second state at the scene's opening
        # the same pictures (the jaws' geoms placed alike to 1e-16: a pixel at an edge may go either way)
        for name in ("rgb", "depth", "segmentation"):
            differ = (getattr(opened, name)[i] != getattr(want, name)[i]).mean()
            assert differ <= 1e-3, (name, i, differ)
        np.testing.assert_allclose(opened.pixels[i], want.pixels[i], atol=1e-9, err_msg=str(i))
        np.testing.assert_array_equal(opened.visible[i], want.visible[i], err_msg=str(i))
    moved = opened.segmentation[[0, 2]] != f.segmentation[[0, 2]]
    assert moved.sum() > 20 and np.isin(opened.segmentation[[0, 2]][moved], [REGRASP]).mean() > 0.2  # the jaws
    assert np.abs(opened.pixels[[0, 2]][:, :, tips] - f.pixels[[0, 2]][:, :, tips]).max() > 2.0  # tips' labels
    np.testing.assert_array_equal(np.delete(opened.pixels, tips, axis=2), np.delete(f.pixels[rows], tips, axis=2))
    again = renderer.render(needle[rows], start[rows], seeds=seeds)  # no opening: the scene's, whatever came before
    np.testing.assert_array_equal(again.segmentation, f.segmentation[rows])
    same = renderer.render(needle[rows], start[rows], seeds=seeds, jaw_deg=20.0)
    np.testing.assert_array_equal(same.rgb, f.rgb[rows])
    for bad in (0.0, 81.0, np.nan, [40.0, 40.0], "wide"):
        with pytest.raises(ValueError, match="jaw_deg must be"):
            renderer.render(needle[rows], start[rows], seeds=seeds, jaw_deg=bad)


def test_bad_arguments_and_a_closed_renderer(renderer, batch):
    needle, start, _ = batch
    with pytest.raises(ValueError, match="needle must be finite poses"):
        renderer.render(np.full(7, np.nan), start[0], 0)
    with pytest.raises(ValueError, match="unit norm"):
        renderer.render(needle[0], start[0] * 2, 0)
    with pytest.raises(ValueError, match="same number"):
        renderer.render(needle[:2], start[:3], 0)
    r = FrameRenderer(rig=endoscope.Rig(width=32, height=18))
    r.close()
    r.close()
    with pytest.raises(RuntimeError, match="closed"):
        r.render(needle[0], start[0], 0)


def _snippet(marker: str) -> str:
    """The python snippet of docs/rendering.md that names ``marker`` (the page has three: the frames', the
    estimator's, the pixel loop's)."""
    text = (ROOT / "docs" / "rendering.md").read_text()
    (snippet,) = [s for s in re.findall(r"```python\n(.*?)```", text, re.S) if marker in s]
    return snippet


def test_the_docs_snippet_runs(renderer, capsys):
    exec(compile(_snippet("FrameRenderer"), "docs/rendering.md", "exec"), {"__name__": "__docs__"})
    assert "stereo pairs" in capsys.readouterr().out


def test_the_docs_pixel_loop_snippet_runs(renderer):
    """The pixel loop's snippet as written, but for its estimator: the oracle its comment names, at 64 x 36
    (no estimator has been trained here; the loop is the same), its frames rendered for real."""
    snippet = _snippet("execute_from_pixels")
    trained = 'load_estimator("runs/estimator/estimator")'
    assert trained in snippet and "OracleEstimator.of(Rig(), noise_px=0.1)" in snippet
    snippet = snippet.replace(trained, "OracleEstimator.of(Rig(width=64, height=36), noise_px=0.1)")
    scope = {"__name__": "__docs__"}
    exec(compile(snippet, "docs/rendering.md", "exec"), scope)
    out = scope["out"]
    assert out["success"].shape == out["steps"].shape == (4,) and out["estimate_error_mm"].shape[0] == 4
    assert (out["frames"] >= out["steps"]).all() and out["frames"].min() >= 1


def test_the_batched_renderer_says_what_it_needs():
    if frames_mjx.mjxw.WARP_INSTALLED:
        pytest.skip("Warp is installed here: the next test runs the batched renderer")
    with pytest.raises(RenderUnavailable, match=re.escape('pip install -e ".[render-gpu]"')):
        frames_mjx.MjxFrameRenderer(2, rig=RIG)


def test_the_batched_renderer_draws_what_the_opengl_one_draws(paper_testset):
    """MuJoCo Warp's ray tracer (on Warp's CPU device here; CI does not install Warp) against the OpenGL
    renderer on the same states, seed and jaw openings (one world's jaws opened, the other's at the
    scene's): the same labels, bit for bit; the same classes and depth but at a few edge pixels; the
    RGB close (two shaders of one scene); one compiled program for calls that differ in openings and
    frame."""
    if not frames_mjx.mjxw.WARP_INSTALLED:
        pytest.skip(f"Warp is not installed here ({frames_mjx.INSTALL})")
    rig = endoscope.Rig(width=64, height=36)
    try:
        gl = FrameRenderer(rig=rig)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL to compare with ({err})")
    needle, start, _ = (np.asarray(x)[[0, 7]] for x in episode_poses(paper_testset[0]))
    mjx = frames_mjx.MjxFrameRenderer(2, rig=rig, seed=3)
    try:
        ref = gl.render(needle, start, seeds=3, jaw_deg=[40.0, 20.0])
    finally:
        gl.close()
    f = mjx.render(needle, start, seeds=3, jaw_deg=[40.0, 20.0])
    assert f.rgb.shape == (2, 2, 36, 64, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == f.segmentation.shape == (2, 2, 36, 64)
    assert f.depth.dtype == np.float32 and f.segmentation.dtype == np.int8
    for name in ("keypoints", "pixels", "keypoint_depth", "visible", "extrinsics", "poses"):
        np.testing.assert_array_equal(getattr(f, name), getattr(ref, name), err_msg=name)
    assert (f.segmentation == ref.segmentation).mean() > 0.995  # measured 0.9995 at 64 x 36
    assert (np.abs(f.depth - ref.depth) < 5e-4).mean() > 0.995
    assert np.abs(f.rgb.astype(int) - ref.rgb).mean() < 8.0  # measured 2.7 of 255
    closed = mjx.render(needle, start, seeds=3, frame=1)  # the scene's opening: world 0's jaws move back
    assert (closed.segmentation[0] != f.segmentation[0]).sum() > 5
    np.testing.assert_array_equal(closed.segmentation[1], f.segmentation[1])
    # the device's part alone (what the benchmark times, left on the device): render's very pictures
    qpos = np.stack([mjx.endo.qpos(n, e) for n, e in zip(needle, start)])
    rgb, depth, seg = (np.asarray(x) for x in mjx.pictures(qpos, np.zeros(2), np.full(2, 3), frame=1))
    np.testing.assert_array_equal(rgb, closed.rgb)
    np.testing.assert_array_equal(seg, closed.segmentation)
    assert mjx._program._cache_size() == 1
