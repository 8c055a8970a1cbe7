"""The pose estimator from stereo frames (issue 68): triangulation worked by hand, the arc fit recovering a
known needle pose from exact keypoints (and keeping it through noise and a keypoint found in the wrong
place), the network's shapes and decoding, the error report's split, the estimator file's round trip
and refusals, and, on frames rendered for real (skipped where no OpenGL context can be made), the
dataset writer, a tiny overfit, a training run killed and resumed to the same numbers, and the CLI."""

from __future__ import annotations

import json
import os
import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx import estimator as cli
from regrasp_mjx.vision import error_fit, pose_errors, stereo
from regrasp_mjx.vision import layout as kp_layout
from regrasp_mjx.vision.estimator_file import EstimatorError, load_estimator, predict, save_estimator
from regrasp_mjx.vision.network import STRIDE, NetConfig, decode, init_params, make_network
from regrasp_mjx.vision.training import CheckpointError, init_state, make_epoch, make_keypoints, optimizer, targets
from regrasp_mjx.workflows import estimator_report
from regrasp_mjx.workflows.estimator_training import Settings, deterministic_gpu, train
from regrasp_mjx.workflows.frame_dataset import DatasetError, load_dataset, render_dataset
from regrasp_mjx.workflows.render import RenderUnavailable
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.sampling import episode_poses
from regrasp_mjx.world.scene import load_scene
from tests.cli_helper import run_main
from tests.conftest import ROOT

W, H = 96, 54  # tiny frames: 0.73 mm a pixel at the working distance


@pytest.fixture(scope="module")
def kp():
    return kp_layout.layout(load_scene())


def _fit(kp, rig):
    return stereo.PoseFit(kp.local, kp_layout.object_rows(kp), rig.intrinsics(), stereo.rectified(rig.baseline_m))


def _camera_truth(needle, ee, extrinsics):
    """The objects' poses ``[B, 3, 4, 4]`` in the left camera's frame."""
    obj = endoscope.object_poses(needle, ee)
    mats = np.zeros(obj.shape[:2] + (4, 4))
    mats[..., :3, :3], mats[..., :3, 3], mats[..., 3, 3] = endoscope.quat_matrix(obj[..., 3:]), obj[..., :3], 1.0
    return extrinsics[:, None] @ mats


# ---- stereo geometry --------------------------------------------------------------------------------


def test_triangulation_worked_by_hand():
    """A point 1 mm right, 2 mm down and 50 mm in front of the left camera (f = 100 px, principal point
    (50, 30), baseline 5 mm): the left image sees it at (50 + 100 * 1/50, 30 + 100 * 2/50) = (52, 34),
    the right camera 5 mm to the right at (50 + 100 * (1 - 5)/50, 34) = (42, 34), a disparity of
    f B / Z = 10 px; triangulating those pixels gives the point back."""
    k = jnp.array([[100.0, 0.0, 50.0], [0.0, 100.0, 30.0], [0.0, 0.0, 1.0]])
    right = jnp.asarray(stereo.rectified(0.005))
    point = jnp.array([0.001, 0.002, 0.05])
    np.testing.assert_allclose(stereo.project(point, k, jnp.eye(4)), [52.0, 34.0], atol=1e-4)
    np.testing.assert_allclose(stereo.project(point, k, right), [42.0, 34.0], atol=1e-4)
    got = stereo.triangulate(jnp.array([52.0, 34.0]), jnp.array([42.0, 34.0]), k, right)
    np.testing.assert_allclose(got, [0.001, 0.002, 0.05], atol=1e-8)
    # one pixel less disparity: the point moves back to f B / 9 = 55.6 mm along the same left ray
    far = stereo.triangulate(jnp.array([52.0, 34.0]), jnp.array([43.0, 34.0]), k, right)
    np.testing.assert_allclose(far, np.array([0.02, 0.04, 1.0]) * 0.5 / 9.0, rtol=1e-5)


def test_the_arc_fit_recovers_a_known_pose_from_exact_keypoints(kp, paper_testset):
    """Keypoints of known poses projected by the camera model into both images, fitted back: the
    needle's pose (the arc of its radius), and each tool's, as the camera sees them."""
    needle, start, _ = (np.asarray(x)[:6] for x in episode_poses(paper_testset[0]))
    rig = endoscope.Rig()
    extrinsics = endoscope.invert(endoscope.camera_poses(rig, np.zeros((6, 3)), np.full((6, 3), 0.02)))
    uv, _ = endoscope.project(kp.world(needle, start)[:, None], extrinsics, rig.intrinsics())
    fit = jax.jit(jax.vmap(_fit(kp, rig)))
    poses, rms = fit(jnp.asarray(uv, jnp.float32), jnp.ones(uv.shape[:-1], jnp.float32))
    truth = _camera_truth(needle, start, extrinsics[:, 0])
    poses = np.asarray(poses, np.float64)
    np.testing.assert_allclose(poses[..., :3], truth[..., :3, 3], atol=2e-7)  # 0.2 um (float32)
    np.testing.assert_allclose(endoscope.quat_matrix(poses[..., 3:]), truth[..., :3, :3], atol=2e-5)
    assert np.all(np.asarray(rms) < 1e-3)
    # 0.2 px of noise and the tip found on the tail in the left image: the needle stays within 1 mm
    noisy = uv + np.random.default_rng(0).normal(0.0, 0.2, uv.shape)
    noisy[:, 0, 0] = noisy[:, 0, endoscope.N_ARC - 1]
    poses, _ = fit(jnp.asarray(noisy, jnp.float32), jnp.ones(uv.shape[:-1], jnp.float32))
    off = np.linalg.norm(np.asarray(poses)[:, 0, :3] - truth[:, 0, :3, 3], axis=-1)
    assert off.max() < 1e-3, off


def test_the_refinement_brings_a_wrong_start_back_and_weights_count(kp):
    rig = endoscope.Rig()
    rows = kp_layout.object_rows(kp)[0]
    model = jnp.asarray(kp.local[list(rows)])
    rot = jnp.asarray(endoscope.rotation_matrix(np.array([0.3, -0.5, 1.0])))
    t = jnp.array([0.002, -0.001, 0.05])
    k, right = jnp.asarray(rig.intrinsics()), jnp.asarray(stereo.rectified(rig.baseline_m))
    uv = jnp.stack([stereo.project(model @ rot.T + t, k, cam) for cam in (jnp.eye(4), right)])
    start = jnp.asarray(endoscope.rotation_matrix(np.array([0.05, 0.0, -0.05]))) @ rot
    r, tt, rms = stereo.refine(start, t + jnp.array([5e-4, 0.0, 2e-3]), model, uv, jnp.ones(uv.shape[:2]), k, right)
    np.testing.assert_allclose(tt, t, atol=1e-6)
    np.testing.assert_allclose(r, rot, atol=1e-4)
    assert float(rms) < 0.01
    # a keypoint 20 px off with no weight changes nothing
    bad = uv.at[0, 3].add(20.0)
    w = jnp.ones(uv.shape[:2]).at[0, 3].set(0.0)
    r2, t2, _ = stereo.refine(start, t + jnp.array([5e-4, 0.0, 2e-3]), model, bad, w, k, right)
    np.testing.assert_allclose(t2, t, atol=1e-6)


# ---- the network ------------------------------------------------------------------------------------


def test_the_network_s_shapes_and_the_estimator_s_outputs(kp):
    net = NetConfig(len(kp.names), W, H)
    assert net.grid == (-(-H // STRIDE), -(-W // STRIDE)) == (14, 24)
    params = init_params(net, jax.random.PRNGKey(0))
    rgb = jnp.asarray(np.random.default_rng(0).integers(0, 256, (3, 2, H, W, 3), np.uint8))
    logits, offsets = make_network(net).apply(params, rgb.reshape(6, H, W, 3))
    assert logits.shape == (6, 14, 24, 17) and offsets.shape == (6, 14, 24, 17, 2)
    rig = endoscope.Rig(width=W, height=H)
    run = jax.jit(lambda p, x: predict(net, _fit(kp, rig), p, x))
    out = run(params, rgb)
    assert out["poses"].shape == (3, 3, 7) and out["rms_px"].shape == (3, 3)
    assert out["pixels"].shape == (3, 2, 17, 2) and out["confidence"].shape == (3, 2, 17)
    np.testing.assert_allclose(np.linalg.norm(out["poses"][..., 3:], axis=-1), 1.0, atol=1e-5)
    # keypoints that do not determine a pose (an empty picture: every keypoint on one pixel) give NaN
    blank = run(params, jnp.zeros_like(rgb))
    assert np.isnan(blank["poses"]).any()
    with pytest.raises(ValueError, match="widths must be 4"):
        NetConfig(17, W, H, widths=(8, 8))


def test_decoding_worked_by_hand():
    """One keypoint whose heatmap peaks at cell (row 2, column 5) with its offset (+0.25, -0.5) cells:
    the cell's centre is (4 * 5 + 1.5, 4 * 2 + 1.5) = (21.5, 9.5), the keypoint (22.5, 7.5); a second
    peak of equal height one cell right pulls the estimate half way over only where both are in the
    3 x 3 window, and the confidence is the mass there."""
    net = NetConfig(1, 48, 32)
    gh, gw = net.grid
    logits = jnp.full((1, gh, gw, 1), -30.0).at[0, 2, 5, 0].set(10.0)
    offsets = jnp.zeros((1, gh, gw, 1, 2)).at[0, 2, 5, 0].set(jnp.array([0.25, -0.5]))
    uv, conf = decode(net, logits, offsets)
    np.testing.assert_allclose(uv[0, 0], [22.5, 7.5], atol=1e-4)
    assert float(conf[0, 0]) > 0.999
    two = logits.at[0, 2, 6, 0].set(10.0)
    uv, conf = decode(net, two, jnp.zeros_like(offsets))
    np.testing.assert_allclose(uv[0, 0], [23.5, 9.5], atol=1e-4)  # between the centres 21.5 and 25.5
    far = logits.at[0, 7, 1, 0].set(10.0)  # a second peak far away: half the mass
    _, conf = decode(net, far, offsets)
    assert 0.45 < float(conf[0, 0]) < 0.55


# ---- the error report -------------------------------------------------------------------------------


def test_errors_split_into_the_episode_s_part_and_the_frame_s():
    """Two episodes of three frames: a bias per episode (1 mm along the optical axis; 0.5 mm across)
    plus frame noise; the split returns the biases as the fixed part and the noise as the rest."""
    rng = np.random.default_rng(0)
    truth = np.tile(np.array([0.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0]), (6, 3, 1))
    bias = np.repeat(np.array([[0.0, 0.0, 1e-3], [5e-4, 0.0, 0.0]]), 3, axis=0)
    noise = rng.normal(0.0, 1e-5, (6, 3))
    noise -= np.repeat(noise.reshape(2, 3, 3).mean(1), 3, axis=0)
    est = truth.copy()
    est[:, :, :3] += (bias + noise)[:, None]
    turn = endoscope.rotation_matrix(np.array([0.0, 0.0, np.radians(2.0)]))  # 2 degrees about the optical axis
    est[:, 1, 3:] = [np.cos(np.radians(1.0)), 0.0, 0.0, np.sin(np.radians(1.0))]
    episode = np.repeat([0, 1], 3)
    fixed, per_frame = pose_errors.split((bias + noise), episode)
    np.testing.assert_allclose(fixed, [[0, 0, 1e-3], [5e-4, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(per_frame, noise, atol=1e-12)
    rep = pose_errors.report(est, truth, episode)
    pos = rep["needle"]["position_mm"]
    assert pos["per_episode"]["along"]["median"] == pytest.approx(0.5, abs=1e-6)  # 1.0 and 0.0
    assert pos["per_episode"]["norm"]["median"] == pytest.approx(0.75, abs=1e-6)  # 1.0 and 0.5
    assert pos["per_frame"]["norm"]["p95"] < 0.05
    rot = rep["grasping_tool"]["orientation_deg"]["total"]
    np.testing.assert_allclose(pose_errors.rotvec(turn)[2], np.radians(2.0))
    assert rot["along"]["median"] == pytest.approx(2.0, abs=1e-6) and rot["across"]["median"] == pytest.approx(0.0)
    assert rep["needle"]["failed"] == 0.0 and rep["needle"]["gross"] == 0.0
    est[0, 2, 0] = np.nan
    est[1, 2, 0] += 0.01  # 10 mm off: gross
    rep = pose_errors.report(est, truth, episode)
    assert rep["regrasping_tool"]["failed"] == pytest.approx(1 / 6) and rep["regrasping_tool"][
        "gross"
    ] == pytest.approx(1 / 6)
    assert "| needle | position (mm) | 0.75 / " in "\n".join(pose_errors.markdown(rep, "t"))


# ---- the estimator file -----------------------------------------------------------------------------


def test_the_regrasping_tool_split_by_its_jaws_opening():
    """Four frames, two at the layout's 20 degrees and two opened to 40: each group's regrasping tool
    errors, worked by hand (0.1 and 0.3 mm; 0.2 mm and a gross 9 mm, left out and counted)."""
    truth = np.tile([0.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0], (4, 3, 1))
    estimate = truth.copy()
    estimate[:, 2, 0] += np.array([0.1, 0.3, 0.2, 9.0]) * 1e-3
    out = estimator_report._by_jaws(estimate, truth, np.array([20.0, 20.0, 40.0, 40.0]), 20.0)
    assert out["at_layout"]["frames"] == 2 and out["at_layout"]["left_out"] == 0
    assert out["at_layout"]["position_mm"]["median"] == pytest.approx(0.2)
    assert out["opened"]["frames"] == 2 and out["opened"]["left_out"] == 1
    assert out["opened"]["position_mm"]["median"] == pytest.approx(0.2)
    assert out["opened"]["orientation_deg"]["median"] == pytest.approx(0.0, abs=1e-6)


def test_the_estimator_file_round_trip_and_its_refusals(kp, tmp_path):
    net = NetConfig(len(kp.names), W, H, widths=(8, 8, 8, 8))
    rig = endoscope.Rig(width=W, height=H)
    params = init_params(net, jax.random.PRNGKey(3))
    folder = save_estimator(tmp_path / "est", params, net, kp, rig.intrinsics(), rig.baseline_m, {"training": {"x": 1}})
    est = load_estimator(folder / "estimator.json")
    assert est.net == net and est.keypoints.names == kp.names and est.contract["training"] == {"x": 1}
    for a, b in zip(jax.tree.leaves(est.params), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(a, b)
    rgb = np.random.default_rng(0).integers(0, 256, (3, 2, H, W, 3), np.uint8)
    got = est.poses(rgb, batch=2)  # two calls, the last one padded
    want, _ = make_keypoints(net)(params, jnp.asarray(rgb))
    np.testing.assert_allclose(got["pixels"], want, atol=1e-4)
    assert got["poses"].shape == (3, 3, 7)
    with pytest.raises(EstimatorError, match=f"trained at {W} x {H}"):
        est.poses(np.zeros((1, 2, H + 2, W, 3), np.uint8))
    with pytest.raises(EstimatorError, match="uint8"):
        est.poses(np.zeros((1, 2, H, W, 3), np.float32))
    with pytest.raises(EstimatorError, match="not found"):
        load_estimator(tmp_path / "nowhere")

    def broken(name, edit):
        bad = tmp_path / name
        shutil.copytree(folder, bad)
        edit(bad)
        return bad

    cases = {
        "no_npz": (lambda f: (f / "estimator.npz").unlink(), "estimator file not found"),
        "bad_json": (lambda f: (f / "estimator.json").write_text("{"), "not valid JSON"),
        "truncated": (
            lambda f: (f / "estimator.npz").write_bytes((f / "estimator.npz").read_bytes()[:500]),
            "not a readable",
        ),
    }

    def contract_edit(change):
        def edit(f):
            c = json.loads((f / "estimator.json").read_text())
            change(c)
            (f / "estimator.json").write_text(json.dumps(c))

        return edit

    cases["version"] = (contract_edit(lambda c: c.update(version=99)), "version 1")
    cases["widths"] = (contract_edit(lambda c: c["network"].update(widths=[8, 8, 8, 16])), "arrays differ|has shape")
    cases["keypoints"] = (contract_edit(lambda c: c["network"].update(keypoints=16)), "16|keypoints")
    cases["camera"] = (contract_edit(lambda c: c["camera"].update(baseline_m=-1.0)), "baseline")

    def nan_weights(f):
        with np.load(f / "estimator.npz") as z:
            arrays = {k: z[k] for k in z.files}
        first = sorted(arrays)[0]
        arrays[first] = np.full_like(arrays[first], np.nan)
        np.savez(f / "estimator.npz", **arrays)

    cases["nan"] = (nan_weights, "NaN or inf")
    for name, (edit, message) in cases.items():
        with pytest.raises(EstimatorError, match=message):
            load_estimator(broken(name, edit))


# ---- rendered frames: the dataset, training, resume, evaluation, the command line ------------------


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """A tiny training set (4 episodes x 2 frames, seed 0) and a held-out one (2 x 2, seed 1)."""
    folder = tmp_path_factory.mktemp("frames")
    try:
        render_dataset(folder / "train.npz", 4, 2, 0, W, H, log=lambda *_: None)
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL on this machine ({err})")
    render_dataset(folder / "val.npz", 2, 2, 1, W, H, log=lambda *_: None)
    return folder


def test_the_dataset_writer_renders_labelled_episodes(frames, kp):
    d = load_dataset(frames / "train.npz")
    assert d.rgb.shape == (8, 2, H, W, 3) and d.pixels.shape == (8, 2, len(kp.names), 2)
    np.testing.assert_array_equal(d.episode, [0, 0, 1, 1, 2, 2, 3, 3])
    np.testing.assert_array_equal(d.frame, [0, 1] * 4)
    assert d.keypoints.names == kp.names and d.meta["seed"] == 0 and not (frames / "train.npz.parts").exists()
    # an episode keeps its needle, cameras and randomisation; its tool moves from start to goal
    np.testing.assert_array_equal(d.poses[0, 0], d.poses[1, 0])
    np.testing.assert_array_equal(d.extrinsics[0], d.extrinsics[1])
    assert not np.allclose(d.poses[0, 2], d.poses[1, 2])
    # the labels are the camera model's projections of the poses
    uv, _ = endoscope.project(kp.world(d.poses[:, 0], d.poses[:, 2])[:, None], d.extrinsics, d.intrinsics)
    np.testing.assert_allclose(d.pixels, uv, atol=1e-3)
    cam = d.camera_poses(0)
    np.testing.assert_allclose(cam[:, 1, :3], d.extrinsics[:, 0, :3, 3], atol=1e-12)  # the grasping tool is e_g
    assert not np.array_equal(load_dataset(frames / "val.npz").poses[0], d.poses[0])


def test_the_dataset_draws_jaws_that_open_on_the_way(frames, kp, tmp_path):
    """With ``jaw_open`` each episode's later frames draw the regrasping jaws at an opening drawn in the
    range, their tips' labels turned with them; the earlier frames, the problems and the cameras are
    the seed's as without it. A file written before the jaws could open reads as all at 20 degrees."""
    render_dataset(tmp_path / "o.npz", 2, 2, 0, W, H, log=lambda *_: None, jaw_open=(30.0, 50.0))
    d, plain = load_dataset(tmp_path / "o.npz"), load_dataset(frames / "train.npz")
    assert d.jaw_deg[0] == d.jaw_deg[2] == 20.0 and np.all((d.jaw_deg[[1, 3]] >= 30) & (d.jaw_deg[[1, 3]] <= 50))
    assert d.jaw_deg[1] != d.jaw_deg[3] and d.meta["jaws"]["open_deg"] == [30.0, 50.0]
    np.testing.assert_array_equal(plain.jaw_deg, 20.0)
    turn = np.radians(d.jaw_deg.astype(np.float64) - 20.0) / 2.0
    uv, _ = endoscope.project(kp.world(d.poses[:, 0], d.poses[:, 2], turn)[:, None], d.extrinsics, d.intrinsics)
    np.testing.assert_allclose(d.pixels, uv, atol=1e-3)
    tips = [i for i, n in enumerate(kp.names) if n.startswith("regrasp_jaw_")]
    moved = np.abs(d.pixels[:, :, tips] - plain.pixels[:4, :, tips]).max(axis=(1, 2, 3))
    assert moved[0] < 1e-6 and moved[1] > 0.3, moved  # frame 0 as without opening; frame 1 opened
    np.testing.assert_array_equal(d.rgb[0], plain.rgb[0])
    assert not np.array_equal(d.rgb[1], plain.rgb[1])
    # a file written before the jaws could open: no jaw_deg array; read as the scene's opening
    with np.load(frames / "train.npz", allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files if k != "jaw_deg"}
    np.savez(tmp_path / "old.npz", **arrays)
    np.testing.assert_array_equal(load_dataset(tmp_path / "old.npz").jaw_deg, 20.0)
    for bad in ((10.0, 30.0), (50.0, 30.0), (30.0, 95.0)):
        with pytest.raises(DatasetError, match="jaw_open=.* is not accepted"):
            render_dataset(tmp_path / "b.npz", 2, 2, 0, W, H, log=lambda *_: None, jaw_open=bad)


def test_the_dataset_refusals(frames, tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="not a readable frame dataset"):
        load_dataset(tmp_path / "junk.npz")
    parts = tmp_path / "d.npz.parts"
    parts.mkdir()
    (parts / "manifest.json").write_text(json.dumps({"episodes": 9}))
    with pytest.raises(DatasetError, match="another dataset"):
        render_dataset(tmp_path / "d.npz", 2, 1, 0, W, H, log=lambda *_: None)
    with pytest.raises(DatasetError, match="at most"):
        render_dataset(tmp_path / "e.npz", 10**6, 2, 0, W, H, log=lambda *_: None)


def test_a_tiny_overfit_learns_the_keypoints(frames, kp):
    """Four stereo pairs learned to a fifth of a pixel (median) in 200 updates: the network, its loss
    and its decoding fit together."""
    d = load_dataset(frames / "train.npz")
    rgb, pixels = jnp.asarray(d.rgb[:4]), jnp.asarray(d.pixels[:4], jnp.float32)
    net = NetConfig(len(kp.names), W, H)
    tx = optimizer(3e-3, 200)
    state = init_state(net, tx, jax.random.PRNGKey(0))
    weight = jnp.asarray(targets(net, d.pixels[:4]))
    epoch = make_epoch(net, tx, 4, 1)
    for i in range(200):
        state, metrics = epoch(state, rgb, pixels, weight, jax.random.PRNGKey(i))
    found, conf = make_keypoints(net)(state.params, rgb)
    err = np.linalg.norm(np.asarray(found) - d.pixels[:4], axis=-1)[np.asarray(weight) > 0]
    assert np.median(err) < 0.2 and np.percentile(err, 90) < 1.0, (np.median(err), np.percentile(err, 90))
    assert float(metrics["train_px"]) < 0.5 and float(np.mean(conf)) > 0.5


def test_the_scan_epoch_is_the_host_loop_s(kp):
    """The GPU's one-program epoch (``lax.scan``) takes the CPU's steps: the same parameters after two updates."""
    net = NetConfig(len(kp.names), 32, 18, widths=(4, 4, 4, 4))
    tx = optimizer(1e-3, 2)
    rng = np.random.default_rng(0)
    rgb = jnp.asarray(rng.integers(0, 256, (4, 2, 18, 32, 3), np.uint8))
    pixels = jnp.asarray(rng.uniform(0, 17, (4, 2, len(kp.names), 2)), jnp.float32)
    weight = jnp.ones(pixels.shape[:-1])
    out = []
    for scan in (True, False):
        state = init_state(net, tx, jax.random.PRNGKey(0))
        state, metrics = make_epoch(net, tx, 2, 2, scan=scan)(state, rgb, pixels, weight, jax.random.PRNGKey(1))
        out.append((state, metrics))
    for a, b in zip(jax.tree.leaves(out[0][0]), jax.tree.leaves(out[1][0]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert int(out[0][0].step) == 2


def test_training_killed_and_resumed_gives_the_same_run(frames, tmp_path):
    settings = Settings(epochs=2, batch=4, widths=(8, 8, 8, 8), seed=5)
    lines = []

    def killed(line):
        lines.append(line)
        if line.startswith("epoch 1/2"):
            raise KeyboardInterrupt  # killed once epoch 1's checkpoint is written

    with pytest.raises(KeyboardInterrupt):
        train(frames / "train.npz", frames / "val.npz", tmp_path / "a", settings, log=killed)
    assert "ETA" in lines[-1] and "pairs/s" in lines[-1]
    train(frames / "train.npz", frames / "val.npz", tmp_path / "a", settings, log=lines.append)
    assert any(line.startswith("resuming") for line in lines)
    train(frames / "train.npz", frames / "val.npz", tmp_path / "b", settings, log=lambda *_: None)
    rows = [[json.loads(r) for r in (tmp_path / x / "log.jsonl").read_text().splitlines()] for x in "ab"]
    assert [r["epoch"] for r in rows[0]] == [1, 2]
    for ra, rb in zip(*rows, strict=True):
        for key in ("loss", "train_px", "val_px_median", "val_needle_mm"):
            assert ra[key] == rb[key], key
    a, b = load_estimator(tmp_path / "a" / "estimator"), load_estimator(tmp_path / "b" / "estimator")
    for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(CheckpointError, match="other settings"):
        train(
            frames / "train.npz", frames / "val.npz", tmp_path / "a", Settings(epochs=3, batch=4, widths=(8, 8, 8, 8))
        )
    with pytest.raises(DatasetError, match="training frames' seed"):
        train(frames / "train.npz", frames / "train.npz", tmp_path / "c", settings)
    # the manual's snippet (docs/rendering.md) on this run's estimator
    (snippet,) = re.findall(r"```py\n(.*?)```", (ROOT / "docs" / "rendering.md").read_text(), re.S)
    scope = {"rgb": load_dataset(frames / "val.npz").rgb}
    exec(
        compile(snippet.replace("runs/estimator/estimator", str(tmp_path / "a" / "estimator")), "rendering.md", "exec"),
        scope,
    )
    assert scope["out"]["poses"].shape == (4, 3, 7)
    # the evaluation of the run's estimator on the held-out frames: strict JSON and a table
    rep = estimator_report.evaluate(tmp_path / "a" / "estimator", frames / "val.npz", tmp_path / "eval")
    assert rep["held_out"] and rep["frames"] == 4 and rep["episodes"] == 2
    saved = json.loads((tmp_path / "eval" / "estimator_errors.json").read_text(), parse_constant=pytest.fail)
    assert set(saved) >= {"needle", "grasping_tool", "regrasping_tool", "keypoints_px", "relative", "machine"}
    assert "| regrasping_tool | orientation (deg) |" in (tmp_path / "eval" / "estimator_errors.md").read_text()
    # and every frame's errors, what `estimator fit` reads: the report's numbers come from them
    frames = error_fit.load_frame_errors(tmp_path / "eval")
    assert frames.position_mm.shape == (4, 3, 3) and frames.meta["held_out"] and saved["frame_errors"]
    for o, name in enumerate(("needle", "grasping_tool", "regrasping_tool")):  # 2 epochs: gross errors, mostly
        norm = np.linalg.norm(frames.position_mm[:, o], axis=-1)
        assert rep[name]["failed"] == np.mean(np.isnan(norm)) and rep[name]["gross"] == np.mean(norm > 5.0)
        kept = norm[norm <= 5.0]
        median = rep[name]["position_mm"]["total"]["norm"]["median"]
        assert median is None if not kept.size else median == pytest.approx(np.median(kept))
    with pytest.raises(error_fit.FitError, match="2 frames an episode: the fit needs 3 or more"):
        error_fit.fit(frames)


def _cli(argv):
    return run_main(cli.main, argv)


def test_the_command_line_help_and_bad_arguments(tmp_path, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))  # train adds to it: restored after the test
    code, out, _ = _cli(["--help"])
    assert code == 0 and all(c in out for c in ("render", "train", "evaluate", "bench", "--episodes", "--val"))
    code, out, _ = _cli(["train", "--help"])
    assert code == 0 and "--epochs" in out
    code, _, err = _cli(["render", "--out", str(tmp_path / "x.txt"), "--episodes", "2"])
    assert code == 2 and "ending in .npz" in err
    code, _, err = _cli(["render", "--out", str(tmp_path / "x.npz"), "--episodes", "2", "--width", "8"])
    assert code == 2 and "within [16, 4096]" in err
    code, _, err = _cli(["train", "--data", "a.npz", "--val", "b.npz", "--out", str(tmp_path), "--widths", "1,2"])
    assert code == 2 and "four positive channel counts" in err
    code, _, err = _cli(["train", "--data", "a.npz", "--val", "b.npz", "--out", str(tmp_path), "--lr", "5"])
    assert code == 2 and "learning_rate" in err
    code, _, err = _cli(["evaluate", "--estimator", str(tmp_path / "none"), "--data", "x.npz"])
    assert code == 2 and "estimator folder not found" in err
    code, _, err = _cli(["train", "--data", str(tmp_path / "no.npz"), "--val", "b.npz", "--out", str(tmp_path / "r")])
    assert code == 2 and "frame dataset not found" in err
    assert "--xla_gpu_deterministic_ops=true" in os.environ["XLA_FLAGS"]
    assert deterministic_gpu({"XLA_FLAGS": "--xla_gpu_deterministic_ops=false"}) == "--xla_gpu_deterministic_ops=false"
    code, _, err = _cli(["fly"])
    assert code == 2 and "invalid choice" in err
