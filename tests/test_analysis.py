"""The analysis helpers the notebooks use: logs, the funnel of Fig. 5, Table II, figure output, and
the renderer (offscreen MuJoCo where OpenGL works, the matplotlib sketch everywhere)."""

from __future__ import annotations

import json
import math

import jax
import numpy as np
import pytest

from regrasp_mjx import analysis, render
from regrasp_mjx.evaluate import episode_poses
from regrasp_mjx.host import HostChecker
from tests.conftest import ROOT

RESULTS = ROOT / "experiments" / "results"


def _pose(ep, field, i):
    return episode_poses(ep)[("needle", "start", "goal").index(field)][i]


# ---- logs --------------------------------------------------------------------------------------
def test_write_results_writes_the_table_and_the_rows_whole_and_nothing_without_a_folder(tmp_path):
    from regrasp_mjx.atomic import write_results

    write_results(tmp_path / "r", "t", ["| a |", "| 1 |"], {"rows": [1.5]})
    assert (tmp_path / "r" / "t.md").read_text() == "| a |\n| 1 |\n"
    assert json.loads((tmp_path / "r" / "t.json").read_text()) == {"rows": [1.5]}
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["t.json", "t.md"]  # no temporary left
    write_results(None, "t", ["x"], {})  # experiments run without --out write nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]


def test_read_log_groups_seeds_sorts_epochs_and_flattens(tmp_path):
    rows = [
        {"epoch": 2, "seed": 1, "test": {"success_rate": 0.5}, "wall_s": 20.0},
        {"epoch": 1, "seed": 1, "test": {"success_rate": 0.25}, "wall_s": 10.0},
        {"epoch": 1, "seed": 0, "test": {"success_rate": 0.1}, "wall_s": 9.0, "extra": None},
        {"epoch": 2, "seed": 0, "test": {"success_rate": 0.2}, "wall_s": 19.0, "extra": 3},
    ]
    path = tmp_path / "log.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    log = analysis.read_log(path)
    assert list(log) == [0, 1]
    np.testing.assert_array_equal(log[1]["epoch"], [1, 2])
    np.testing.assert_array_equal(log[1]["test.success_rate"], [0.25, 0.5])
    np.testing.assert_array_equal(log[0]["extra"], [np.nan, 3.0])  # None -> NaN
    epochs, band = analysis.seed_band(log, "wall_s")
    np.testing.assert_array_equal(epochs, [1, 2])
    np.testing.assert_array_equal(band, [[9.0, 19.0], [10.0, 20.0]])
    with pytest.raises(analysis.ResultsError, match="'extra' is not in the log of seeds \\[1\\]"):
        analysis.seed_band(log, "extra")


def test_read_log_bad_files_are_clear_errors(tmp_path):
    with pytest.raises(analysis.ResultsError, match="training log not found"):
        analysis.read_log(tmp_path / "missing.jsonl")
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"epoch": 1}\n{"epoch": 2\n')
    with pytest.raises(analysis.ResultsError, match="bad.jsonl:2 is not JSON"):
        analysis.read_log(bad)
    bad.write_text('{"epoch": 1}\n[1, 2]\n')
    with pytest.raises(analysis.ResultsError, match=":2 is not a log row"):
        analysis.read_log(bad)
    bad.write_text("\n")
    with pytest.raises(analysis.ResultsError, match="has no rows"):
        analysis.read_log(bad)


def test_shipped_table1_logs_read():
    path = RESULTS / "table1_paper" / "log.jsonl"  # three settings x 3 seeds in one log
    assert analysis.settings_in_log(path) == ["ddpg_bc", "targeted", "mixed"]
    log = analysis.read_log(path, "mixed")
    epochs, success = analysis.seed_band(log, "test.success_rate")
    assert sorted(log) == [0, 1, 2] and success.shape == (3, 200) and epochs[0] == 1 and epochs[-1] == 200
    assert success[:, 0].max() < 0.5 < success[:, -1].min()  # learned
    with pytest.raises(analysis.ResultsError, match="no rows of setting 'nope'"):
        analysis.read_log(path, "nope")
    # a log of one setting has none named
    assert analysis.settings_in_log(RESULTS / "ablation" / "ours" / "log.jsonl") == []


def test_in_needle_frame_by_hand():
    half = math.sqrt(0.5)
    needle = np.array([1.0, 2.0, 3.0, half, 0.0, 0.0, half])  # 90 deg about z
    points = np.array([[1.0, 2.001, 3.0], [1.0, 2.0, 3.002]])
    # A point 1 mm along e_g's y lies along the needle's x; z stays z.
    np.testing.assert_allclose(
        analysis.in_needle_frame_mm(needle, points), [[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]], atol=2e-4
    )
    both = analysis.in_needle_frame_mm(np.stack([needle, needle]), points)
    np.testing.assert_allclose(both, analysis.in_needle_frame_mm(needle, points))


# ---- Fig. 5 ------------------------------------------------------------------------------------
def test_free_fraction_funnel_shape(env, paper_testset):
    episodes, _ = paper_testset
    sub = jax.tree.map(lambda x: x[:60], episodes)
    free = analysis.free_fraction(env, sub, [0.0, 1.5, 300.0], samples=32, seed=1)
    # At the goal every pose is free (goals are drawn collision-free); 300 mm away the 54 mm tool
    # cannot reach anything; 1.5 mm off most directions push a jaw into the wire.
    assert free[0] == 1.0 and free[2] == 1.0
    assert free[1] < 0.6
    same = analysis.free_fraction(env, sub, [0.0, 1.5, 300.0], samples=32, seed=1)
    np.testing.assert_array_equal(free, same)  # a seed gives the same numbers


def test_free_fraction_agrees_with_the_host_checker(env, paper_testset):
    """The same estimate made independently: numpy-drawn offsets checked by CPU MuJoCo."""
    episodes, _ = paper_testset
    n, samples, d = 40, 50, 1.5
    sub = jax.tree.map(lambda x: x[:n], episodes)
    batched = analysis.free_fraction(env, sub, [d], samples=samples, seed=3)[0]
    checker = HostChecker(env.scene)
    rng = np.random.default_rng(0)
    free = 0
    for i in range(n):
        needle, goal = _pose(episodes, "needle", i), _pose(episodes, "goal", i)
        for _ in range(samples):
            u = rng.normal(size=3)
            pos = goal[:3] + d * 1e-3 * u / np.linalg.norm(u)
            free += not checker.collides(needle[:3], needle[3:], pos, goal[3:])
    host = free / (n * samples)
    sigma = math.sqrt(host * (1 - host) / (n * samples))
    assert abs(batched - host) < 4 * sigma * math.sqrt(2) + 0.02, (batched, host)


def test_free_fraction_bad_arguments(env, paper_testset):
    episodes, _ = paper_testset
    for kwargs, match in [
        ({"distances_mm": []}, "non-empty"),
        ({"distances_mm": [1.0, -1.0]}, ">= 0"),
        ({"distances_mm": [np.nan]}, "finite"),
        ({"distances_mm": [1.0], "samples": 0}, "samples"),
        ({"distances_mm": [1.0], "rot_deg": 270.0}, "rot_deg"),
    ]:
        with pytest.raises(ValueError, match=match):
            analysis.free_fraction(env, episodes, **kwargs)


# ---- Table II ----------------------------------------------------------------------------------
def test_table2_from_shipped_results():
    rows = analysis.table2(RESULTS)
    by = {r["method"]: r for r in rows}
    assert by["BIT* (R)"]["success"] == 1.0 and by["BIT* (R)"]["kind"] == "planner"
    assert abs(by["BIT* (R)"]["median_ms"] - 26.08) < 0.01
    shipped = by["policy, shipped (distilled 2x256 network + shield)"]
    assert shipped["success"] == 1.0 and shipped["kind"] == "policy" and abs(shipped["path_mm"] - 4.21) < 0.01
    assert shipped["median_ms"] < 1.0  # one core of the H100 host (issue 14's target)
    assert by["policy, 3-network ensemble + shield (earlier default)"]["success"] == 1.0
    assert by["paper: BIT* (R)"]["mean_ms"] == 2590.5 and by["paper: BFMT* (R)"]["mean_ms"] is None
    # Another jaw angle: only that angle's planner rows.
    planners_35 = [r["method"] for r in analysis.table2(RESULTS, jaw_angle_deg=35.0) if r["kind"] == "planner"]
    assert planners_35 == ["straight line", "BIT* (R)"]


def test_table2_and_markdown_errors_and_format(tmp_path):
    with pytest.raises(analysis.ResultsError, match="planners.csv"):
        analysis.table2(tmp_path)
    (tmp_path / "planners.csv").write_text((RESULTS / "planners.csv").read_text())
    with pytest.raises(analysis.ResultsError, match="no rows for a jaw angle of 50.0"):
        analysis.table2(tmp_path, jaw_angle_deg=50.0)
    with pytest.raises(analysis.ResultsError, match="eval_cpu1_single.json"):
        analysis.table2(tmp_path)
    text = analysis.markdown_table(
        [{"a": "x", "b": 0.12345}, {"a": "y", "b": None}], [("a", "name", ""), ("b", "value", ".2f")]
    )
    assert text == "| name | value |\n| --- | --- |\n| x | 0.12 |\n| y | - |"


# ---- figures -----------------------------------------------------------------------------------
def test_save_figure_only_when_asked(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(2, 2))
    monkeypatch.delenv(analysis.FIGURES_ENV, raising=False)
    assert analysis.save_figure(fig, "x.png") is None
    monkeypatch.setenv(analysis.FIGURES_ENV, str(tmp_path / "figs"))
    path = analysis.save_figure(fig, "x.png")
    assert path == tmp_path / "figs" / "x.png" and path.read_bytes()[:4] == b"\x89PNG"
    frames = np.zeros((3, 8, 10, 3), np.uint8)
    gif = analysis.save_figure(frames, "v.gif")
    assert gif.read_bytes()[:3] == b"GIF"
    plt.close(fig)
    with pytest.raises(analysis.ResultsError, match="no experiments/results"):
        analysis.repo_root(tmp_path)
    assert analysis.repo_root(ROOT / "notebooks") == ROOT


# ---- rendering ---------------------------------------------------------------------------------
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
