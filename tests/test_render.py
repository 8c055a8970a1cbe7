"""The renderer: interpolated paths, GIFs, capsule sketches and offscreen MuJoCo images, with clear
errors where no OpenGL context can be made."""

from __future__ import annotations

import math

import numpy as np
import pytest

from regrasp_mjx.workflows import render
from regrasp_mjx.world.sampling import episode_poses


def _pose(ep, field, i):
    return episode_poses(ep)[("needle", "start", "goal").index(field)][i]


def test_interpolate_is_linear_in_position_and_slerps_rotation():
    a = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    half = math.sqrt(0.5)
    b = np.array([4.0, 0.0, 0.0, half, 0.0, 0.0, half])  # 90 deg about z
    out = render.interpolate(np.stack([a, b, b]), 4)
    assert out.shape == (9, 7)
    np.testing.assert_allclose(out[0], a)
    np.testing.assert_allclose(out[-1], b)
    np.testing.assert_allclose(out[2, :3], [2.0, 0.0, 0.0])  # halfway
    np.testing.assert_allclose(out[2, 3:], [math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)], atol=1e-12)  # 45 deg
    np.testing.assert_allclose(out[4:], np.repeat(b[None], 5, axis=0), atol=1e-12)  # a zero step stays put
    with pytest.raises(ValueError, match="substeps"):
        render.interpolate(np.stack([a, b]), 0)
    with pytest.raises(ValueError, match=r"\[T, 7\]"):
        render.interpolate(np.zeros((3, 6)), 2)


def test_write_gif_round_trip_and_bad_frames(tmp_path):
    from PIL import Image

    frames = np.zeros((4, 6, 8, 3), np.uint8)
    frames[:, :, :4] = 255
    frames[:, 0, 7] = np.array([0, 60, 120, 180])[:, None]  # four different frames (Pillow merges equal ones)
    path = render.write_gif(tmp_path / "sub" / "a.gif", frames, fps=10)
    with Image.open(path) as im:
        assert im.size == (8, 6) and im.n_frames == 4
        assert im.info["duration"] == 100 and im.info["loop"] == 0
        im.seek(2)
        np.testing.assert_array_equal(np.asarray(im.convert("RGB"))[0, 7], [120, 120, 120])
    assert not list((tmp_path / "sub").glob("*.tmp"))
    with pytest.raises(ValueError, match="uint8"):
        render.write_gif(tmp_path / "b.gif", frames.astype(np.float32))
    with pytest.raises(ValueError, match="fps"):
        render.write_gif(tmp_path / "b.gif", frames, fps=0)


def test_capsule_segments_follow_the_poses(env):
    ident = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    shift = np.array([0.01, -0.02, 0.03, 0.0, 1.0, 0.0, 0.0])  # 180 deg about x: (x, y, z) -> (x, -y, -z)
    caps = render.capsule_segments(env.scene, ident, shift)
    assert [len(caps[k]) for k in ("grasp", "needle", "regrasp")] == [
        len(env.scene.grasp_capsules),
        len(env.scene.needle_capsules),
        len(env.scene.regrasp_capsules),
    ]
    for (p0, p1, r), c in zip(caps["regrasp"], env.scene.regrasp_capsules):
        np.testing.assert_allclose(p0, shift[:3] + c.p0 * [1, -1, -1], atol=1e-12)
        np.testing.assert_allclose(p1, shift[:3] + c.p1 * [1, -1, -1], atol=1e-12)
        assert r == c.radius
    for (p0, _, _), c in zip(caps["grasp"], env.scene.grasp_capsules):
        np.testing.assert_allclose(p0, c.p0)  # the grasping tool is the world frame
    with pytest.raises(ValueError, match="ee must be a finite pose"):
        render.capsule_segments(env.scene, ident, [0.0] * 6)


def test_sketch_draws_every_capsule(env, paper_testset):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes, _ = paper_testset
    needle, start, goal = (_pose(episodes, f, 0) for f in ("needle", "start", "goal"))
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    render.sketch(ax, env.scene, needle, start, goal=goal, path=np.stack([start, goal]), half_mm=100.0)
    n_caps = len(env.scene.grasp_capsules) + len(env.scene.needle_capsules) + len(env.scene.regrasp_capsules)
    assert len(ax.lines) == n_caps + len(env.scene.regrasp_capsules) + 1  # + goal ghost + path
    assert ax.get_xlim() == pytest.approx((needle[0] * 1e3 - 100, needle[0] * 1e3 + 100))
    ax.clear()
    render.sketch(ax, env.scene, needle, start, half_mm=7.0)  # close up (the arc: 5.4 mm): far parts cut
    assert len(env.scene.needle_capsules) <= len(ax.lines) < n_caps
    for line in ax.lines:
        xs, ys, zs = line.get_data_3d()
        assert np.all(np.abs(np.stack([xs, ys, zs]).T - needle[:3] * 1e3) <= 7.0 + 1e-9)
    plt.close(fig)


def test_clip_cuts_segments_to_the_box():
    lo, hi = np.zeros(3), np.ones(3)
    np.testing.assert_allclose(
        render._clip(np.array([[-1.0, 0.5, 0.5], [2.0, 0.5, 0.5]]), lo, hi), [[0, 0.5, 0.5], [1, 0.5, 0.5]]
    )
    inside = np.array([[0.2, 0.2, 0.2], [0.8, 0.3, 0.1]])
    np.testing.assert_allclose(render._clip(inside, lo, hi), inside)
    assert render._clip(np.array([[2.0, 0.0, 0.0], [3.0, 1.0, 1.0]]), lo, hi) is None
    assert render._clip(np.array([[0.5, 2.0, 0.5], [0.5, 2.0, 0.9]]), lo, hi) is None  # parallel, outside


@pytest.fixture(scope="module")
def renderer(env):
    try:
        r = render.SceneRenderer(env.scene, width=160, height=120)
    except render.RenderUnavailable as err:
        pytest.skip(f"no OpenGL on this machine ({err}); the sketch fallback is tested above")
    yield r
    r.close()


def test_renderer_draws_the_scene_the_goal_and_the_path(renderer, paper_testset):
    episodes, _ = paper_testset
    needle, start, goal = (_pose(episodes, f, 0) for f in ("needle", "start", "goal"))
    plain = renderer.image(needle, start)
    assert plain.shape == (120, 160, 3) and plain.dtype == np.uint8
    background = np.all(plain == render.BACKGROUND, axis=-1).mean()
    assert 0.2 < background < 0.98  # the tools are in the picture, not filling it
    ghost = renderer.image(needle, start, goal=goal, frame_for=start)
    assert np.any(ghost != plain)  # the goal ghost shows
    assert np.array_equal(renderer.image(needle, start), plain)  # the ghost does not stick
    moved = renderer.image(needle, goal, frame_for=start)
    assert np.any(moved != plain)
    frames = renderer.video(needle, np.stack([start, goal]), goal=goal, substeps=3, hold=2)
    assert frames.shape == (3 + 1 + 2, 120, 160, 3)
    np.testing.assert_array_equal(frames[0], renderer.image(needle, start, goal, start[None, :3], frame_for=start))
    with pytest.raises(ValueError, match="needle must be a finite pose"):
        renderer.image([np.nan] * 7, start)
    with pytest.raises(ValueError, match="path must be finite points"):
        renderer.image(needle, start, path=np.zeros((3, 2)))


def test_renderer_bad_arguments(env):
    with pytest.raises(ValueError, match="width and height"):
        render.SceneRenderer(env.scene, width=5000)
    with pytest.raises(ValueError, match="camera 'nope'"):
        render.SceneRenderer(env.scene, camera="nope")


def test_no_opengl_backend_is_a_clear_error(env, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "vulkan")
    with pytest.raises(render.RenderUnavailable, match="MUJOCO_GL='vulkan' is not accepted here: egl, osmesa or glfw"):
        render.SceneRenderer(env.scene)


def test_a_context_without_a_display_is_render_unavailable(env, monkeypatch):
    """GLFW without a display: the machine-without-OpenGL case the notebooks fall back from."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setenv("MUJOCO_GL", "glfw")
    with (
        pytest.warns(UserWarning, match="DISPLAY"),
        pytest.raises(render.RenderUnavailable, match="no offscreen OpenGL context with MUJOCO_GL=glfw"),
    ):
        render.SceneRenderer(env.scene)


def test_a_closed_renderer_refuses_to_draw(env, paper_testset):
    try:
        r = render.SceneRenderer(env.scene, width=32, height=32)
    except render.RenderUnavailable as err:
        pytest.skip(f"no OpenGL on this machine ({err})")
    r.close()
    r.close()  # twice is fine
    episodes, _ = paper_testset
    with pytest.raises(RuntimeError, match="closed"):
        r.image(_pose(episodes, "needle", 0), _pose(episodes, "start", 0))
