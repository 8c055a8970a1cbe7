"""The closed loop from pixels (issue 68, step 5): the oracle estimator (keypoints projected from the true
poses, then the learned estimator's fit) returns the true poses, and a biased one moves the needle by what
the projection says; the loop through the oracle, on frames rendered for real (skipped where no OpenGL
context can be made), takes the policy's own plan step by step, and (slow) reproduces the simulated camera
loop's outcomes, steps and frames at the policy's own settings, with jaws that open on the way its openings too;
the learned estimator's path sees rendered frames; the command line writes its report, resumes a killed run to
the same rows and refuses bad input."""

from __future__ import annotations

import dataclasses
import json
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import regrasp_mjx
from regrasp_mjx import estimator as cli
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.host_loop import folder_lock
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.vision import stereo
from regrasp_mjx.vision.estimator_file import load_estimator, save_estimator
from regrasp_mjx.vision.network import NetConfig, init_params
from regrasp_mjx.vision.oracle import OracleError, OracleEstimator
from regrasp_mjx.workflows import pixel_loop, pixel_report
from regrasp_mjx.workflows.frames import FrameRenderer
from regrasp_mjx.workflows.pixel_eyes import Eyes, PixelLoopError, episode_seeds, frame_errors, matrices, rig_of
from regrasp_mjx.workflows.pixel_loop import execute_from_pixels
from regrasp_mjx.workflows.render import RenderUnavailable
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.sampling import episode_poses
from tests.cli_helper import run_main

W, H = 64, 36  # tiny frames
OPEN40 = "experiments/results/jaw_on_the_way/policy_open40"  # a teacher whose jaws open on the way to 40 degrees
ROWS = 2  # every loop here runs 2 problems side by side: one compiled judge


@pytest.fixture(scope="module")
def problems(paper_testset):
    return tuple(np.asarray(x) for x in episode_poses(paper_testset[0]))


@pytest.fixture(scope="module")
def policy():
    return regrasp_mjx.load_policy()


@pytest.fixture(scope="module")
def renderer():
    try:
        r = FrameRenderer(rig=endoscope.Rig(width=W, height=H))
    except RenderUnavailable as err:
        pytest.skip(f"no OpenGL on this machine ({err}); the oracle without images is tested without it")
    yield r
    r.close()


def _cameras(rig, seeds):
    d = dr.draws(np.asarray(seeds))
    return endoscope.invert(endoscope.camera_poses(rig, np.asarray(d.camera_shift), np.asarray(d.camera_rotvec)))


# ---- the oracle ------------------------------------------------------------------------------------------


def test_the_oracle_returns_the_true_poses(problems):
    needle, start, _ = problems
    rig = endoscope.Rig()
    oracle = OracleEstimator.of(rig)
    poses, extrinsics = endoscope.object_poses(needle[:8], start[:8]), _cameras(rig, range(8))
    out = oracle.estimate(poses, extrinsics)
    mm, deg = frame_errors(out["poses"], extrinsics[:, 0, None] @ matrices(poses))
    assert out["poses"].shape == (8, 3, 7) and out["pixels"].shape == (8, 2, len(oracle.keypoints.names), 2)
    assert mm.max() < 1e-3 and deg.max() < 1e-3, (mm.max(), deg.max())  # micrometres, millidegrees: float32's fit
    assert np.all(out["rms_px"] < 1e-3)


def test_the_fit_told_the_jaws_opening_returns_the_true_tool(problems):
    """Jaws opened to 40 degrees (their tips 10 degrees further out each, as the frames draw them): a fit
    told the opening gives the true regrasping tool; one that models them at the layout's 20 does not
    (the tips' mismatch turns the tool); the needle and the grasping tool are alike in both."""
    needle, start, _ = problems
    rig = endoscope.Rig()
    oracle = OracleEstimator.of(rig)
    poses, extrinsics = endoscope.object_poses(needle[:6], start[:6]), _cameras(rig, range(6))
    truth = extrinsics[:, 0, None] @ matrices(poses)
    told = oracle.estimate(poses, extrinsics, jaw_deg=40.0)
    mm, deg = frame_errors(told["poses"], truth)
    assert mm[:, :3].max() < 1e-3 and deg[:, :3].max() < 1e-3, (mm.max(), deg.max())
    uv_open = oracle.pixels(poses, extrinsics, jaw_deg=40.0)
    tips = list(oracle.fit.tips)
    assert len(tips) == 2 and np.abs(uv_open - oracle.pixels(poses, extrinsics))[:, :, tips].max() > 1.0
    conf = jnp.ones(uv_open.shape[:-1])
    untold = np.asarray(jax.vmap(oracle.fit)(jnp.asarray(uv_open, jnp.float32), conf)[0], np.float64)
    mm_u, deg_u = frame_errors(untold, truth)
    assert mm_u[:, :2].max() < 1e-3 and np.median(deg_u[:, 2]) > 1.0, (mm_u, deg_u)
    with pytest.raises(OracleError, match="jaw_deg is not accepted"):
        oracle.estimate(poses, extrinsics, jaw_deg=95.0)


def test_a_biased_oracle_moves_the_needle_by_what_the_projection_says(problems):
    """Every needle keypoint shifted by the same pixels in both images (no change of disparity) moves the
    needle across the optical axis by what those pixels are at its keypoints' depths (the mean of their
    triangulated shifts); depth and the tools stay."""
    needle, start, _ = problems
    rig = endoscope.Rig()
    exact = OracleEstimator.of(rig)
    poses, extrinsics = endoscope.object_poses(needle[:6], start[:6]), _cameras(rig, range(6))
    truth = exact.estimate(poses, extrinsics)["poses"]
    rows = exact.rows("needle")
    k, right = jnp.asarray(rig.intrinsics()), jnp.asarray(stereo.rectified(rig.baseline_m))
    uv = exact.pixels(poses, extrinsics)[:, :, rows]

    def triangulated(px):
        return np.asarray(stereo.triangulate(jnp.asarray(px[:, 0]), jnp.asarray(px[:, 1]), k, right))

    for shift in ((1.5, 0.0), (0.0, -1.0)):  # pixels (u, v), both images
        bias = np.zeros((2, len(exact.keypoints.names), 2))
        bias[:, rows] = shift
        biased = OracleEstimator.of(rig, bias_px=bias).estimate(poses, extrinsics)["poses"]
        moved = (biased[:, 0, :3] - truth[:, 0, :3]) * 1e3  # mm, left camera frame
        said = (triangulated(uv + shift) - triangulated(uv)).mean(axis=1) * 1e3
        axis = 0 if shift[0] else 1
        assert np.all(np.abs(said[:, axis]) > 0.2), said  # a pixel is 0.22 mm at the working distance
        np.testing.assert_allclose(moved[:, axis], said[:, axis], rtol=0.08)
        assert np.abs(moved[:, 1 - axis]).max() < 0.01 and np.abs(moved[:, 2]).max() < 0.03, moved
        np.testing.assert_allclose(biased[:, 1:], truth[:, 1:], atol=1e-6)  # the tools' keypoints are not biased


def test_the_oracle_s_noise_is_keyed_and_its_refusals(problems):
    needle, start, _ = problems
    rig = endoscope.Rig()
    poses, extrinsics = endoscope.object_poses(needle[:2], start[:2]), _cameras(rig, range(2))
    noisy = OracleEstimator.of(rig, noise_px=0.5, seed=3)
    keys = np.array([[7, 0], [7, 1]])
    a, b = noisy.estimate(poses, extrinsics, keys), noisy.estimate(poses, extrinsics, keys)
    np.testing.assert_array_equal(a["pixels"], b["pixels"])  # the same episode and frame, the same noise
    c = noisy.estimate(poses[::-1], extrinsics[::-1], keys[::-1])  # a row's noise is its key's, wherever it is
    np.testing.assert_allclose(c["pixels"][::-1], a["pixels"], atol=1e-12)
    assert not np.allclose(noisy.estimate(poses, extrinsics, keys + 1)["pixels"], a["pixels"])
    assert 0.3 < np.std(a["pixels"] - noisy.pixels(poses, extrinsics)) < 0.7
    with pytest.raises(OracleError, match="bias_px of shape"):
        OracleEstimator.of(rig, bias_px=np.zeros(5))
    with pytest.raises(OracleError, match="noise_px"):
        OracleEstimator.of(rig, noise_px=-1.0)
    with pytest.raises(OracleError, match="e_g itself"):
        noisy.estimate(poses[:, [1, 0, 2]], extrinsics)
    with pytest.raises(OracleError, match="keys"):
        noisy.estimate(poses, extrinsics, np.array([[1, -1], [0, 0]]))
    with pytest.raises(OracleError, match="one of"):
        noisy.rows("needle_holder")


# ---- the loop ----------------------------------------------------------------------------------------------


def test_the_loop_through_the_oracle_plans_as_the_policy(policy, problems, renderer, monkeypatch):
    """Frames rendered at the true poses, the oracle's estimate, CameraLoop at one warm-up frame and the
    full stop tolerance: the policy's own plan, step by step (as CameraLoop with exact camera frames)."""
    monkeypatch.setattr(pixel_loop, "PROGRESS_STEPS", 4)
    needle, start, goal = (x[:ROWS] for x in problems)
    oracle = OracleEstimator.of(renderer.rig)
    lines = []
    out = execute_from_pixels(
        policy,
        oracle,
        needle,
        start,
        goal,
        batch=ROWS,
        renderer=renderer,
        warmup_frames=1,
        stop_tolerance=1.0,
        log=lines.append,
    )
    for i in range(ROWS):
        plan = policy.plan(needle[i], start[i], goal[i], check_grasp=False)
        steps = int(plan.steps)
        assert bool(out["success"][i]) == bool(plan.success) and int(out["steps"][i]) == steps
        np.testing.assert_allclose(out["poses"][i, : steps + 1], plan.poses, atol=2e-6)
    assert out["success"].all() and not out["collision"].any() and out["stopped"].all()
    np.testing.assert_array_equal(out["frames"], out["steps"] + 1)  # one frame a step and the one that stopped
    assert out["refused"].sum() == 0 and out["estimate_error_mm"].shape[-1] == 5
    taken = np.arange(out["estimate_error_mm"].shape[1])[None] < out["frames"][:, None]
    assert np.nanmax(out["estimate_error_mm"][taken]) < 1e-3 and np.isnan(out["estimate_error_mm"][~taken]).all()
    np.testing.assert_array_equal(out["seeds"], episode_seeds(ROWS, 0))
    assert lines and all(re.match(r"  rows 0-1 of 2 step [48]: \d of 2 rows live, \d+ stereo pairs", x) for x in lines)


def test_the_frames_draw_the_jaws_the_loop_commands(policy, problems, renderer, monkeypatch):
    """The shipped default opens its jaws on the way (to 40 degrees): every stereo pair the loop renders
    draws each row's regrasping jaws where its loop last commanded them, the scene's 20 degrees up to the
    step they open before and 40 after it (read off the picture model as each picture is drawn: the angle
    between the two jaw meshes), the tool where the row's true pose is at that step."""
    assert policy.env_config.jaw_open_deg == 40.0 and policy.env_config.scene.jaw_angle_deg == 20.0
    model, data, scene = renderer.model, renderer._data, renderer.endo.scene
    a, b = (model.geom(f"regrasp_jaw_{s}_visual").id for s in ("a", "b"))
    drawn = []  # (needle, ee, opening) of each picture

    def shoot(cam, shoot=renderer._shoot):
        if cam is renderer._cams[0]:  # one record a stereo pair
            turn = data.geom_xmat[a].reshape(3, 3) @ data.geom_xmat[b].reshape(3, 3).T
            q = data.qpos.copy()
            drawn.append(
                (
                    q[scene.needle_qpos : scene.needle_qpos + 7],
                    q[scene.regrasp_qpos : scene.regrasp_qpos + 7],
                    np.degrees(np.arccos(np.clip((np.trace(turn) - 1.0) / 2.0, -1.0, 1.0))),
                )
            )
        return shoot(cam)

    monkeypatch.setattr(renderer, "_shoot", shoot)
    needle, start, goal = (x[:ROWS] for x in problems)
    out = execute_from_pixels(
        policy, OracleEstimator.of(renderer.rig), needle, start, goal, batch=ROWS, renderer=renderer, warmup_frames=1
    )
    assert len(drawn) == out["frames"].sum() and (out["opened_at"] >= 0).all(), out["opened_at"]
    seen = np.zeros((ROWS, 2), np.int64)  # pictures drawn closed and open, per row
    for n, ee, opening in drawn:
        i = int(np.argmin(np.linalg.norm(needle[:, :3] - n[:3], axis=1)))
        gaps = np.linalg.norm(out["poses"][i, :, :3] - ee[:3], axis=1)
        t = int(np.argmin(gaps))  # the step the picture was drawn at (the first, where a row holds at its end)
        assert gaps[t] < 1e-7 and np.allclose(n, needle[i])
        opened = t > out["opened_at"][i]
        assert opening == pytest.approx(40.0 if opened else 20.0, abs=1e-6), (i, t, out["opened_at"][i])
        seen[i, int(opened)] += 1
    assert (seen > 0).all(), seen  # each row drawn both ways
    np.testing.assert_array_equal(out["jaw_deg"], 40.0)


@pytest.mark.slow
def test_the_loop_through_the_oracle_is_the_simulated_camera_loop(policy, problems, renderer):
    """At the policy's own settings (warm-up frames, stop tolerance) and no error, the loop from pixels
    through the oracle ends each problem as ``Policy.execute`` does, in as many steps and frames."""
    needle, start, goal = (x[:ROWS] for x in problems)
    out = execute_from_pixels(
        policy, OracleEstimator.of(renderer.rig), needle, start, goal, batch=ROWS, renderer=renderer
    )
    ref = policy.execute(needle, start, goal)
    for key in ("success", "collision", "time_out", "stopped", "steps", "frames"):
        np.testing.assert_array_equal(out[key], ref[key], err_msg=key)
    np.testing.assert_allclose(out["poses"], ref["poses"], atol=2e-6)


@pytest.mark.slow
def test_the_loop_through_the_oracle_opens_the_jaws_as_the_simulated_loop(problems):
    """policy_open40 (jaws that open on the way to 40 degrees) through the oracle without images, at its own
    settings and no error: each row opens its jaws before the step ``Policy.execute``'s loop does and ends
    as it does, in as many steps and frames (the judge carrying the commanded openings out)."""
    policy = regrasp_mjx.load_policy(OPEN40)
    needle, start, goal = (x[:ROWS] for x in problems)
    out = execute_from_pixels(
        policy, OracleEstimator.of(endoscope.Rig(width=W, height=H)), needle, start, goal, batch=ROWS, render=False
    )
    ref = policy.execute(needle, start, goal)
    for key in ("success", "collision", "time_out", "stopped", "steps", "frames", "looked", "jaw_deg", "opened_at"):
        np.testing.assert_array_equal(out[key], ref[key], err_msg=key)
    np.testing.assert_allclose(out["poses"], ref["poses"], atol=2e-6)
    assert (ref["opened_at"] >= 0).all() and ref["success"].all()


def test_the_learned_estimator_sees_rendered_frames(renderer, problems, tmp_path, monkeypatch):
    """The learned path: a stereo pair rendered for each row, the estimator's poses (an untrained network
    here: shapes, not accuracy), the truth beside them; its cameras checked against the endoscope's."""
    needle, start, _ = problems
    kp = OracleEstimator.of(renderer.rig).keypoints
    net = NetConfig(len(kp.names), W, H)
    rig = renderer.rig
    folder = save_estimator(
        tmp_path / "est", init_params(net, jax.random.PRNGKey(0)), net, kp, rig.intrinsics(), rig.baseline_m
    )
    est = load_estimator(folder)
    assert rig_of(est) == rig
    eyes = Eyes(est, rig, renderer, episode_seeds(3, 0), needle[:3], 3)
    seen, truth = eyes.look(np.array([0, 2]), start[[0, 2]])
    assert seen["poses"].shape == (2, 3, 7) and truth.shape == (2, 3, 4, 4) and eyes.pairs == 2
    np.testing.assert_array_equal(eyes.next_frame, [1, 0, 1])
    other = save_estimator(
        tmp_path / "other", init_params(net, jax.random.PRNGKey(0)), net, kp, rig.intrinsics() * 1.1, rig.baseline_m
    )
    with pytest.raises(PixelLoopError, match="not the endoscope's"):
        rig_of(load_estimator(other))
    policy = regrasp_mjx.load_policy()
    with pytest.raises(PixelLoopError, match="render=False"):
        execute_from_pixels(policy, est, needle[:1], start[:1], render=False)
    # the frames draw the jaws open, but the estimator's training frames never did (said); one trained on
    # frames whose jaws opened to 20-60 degrees runs without a word
    opened = save_estimator(
        tmp_path / "opened",
        init_params(net, jax.random.PRNGKey(0)),
        net,
        kp,
        rig.intrinsics(),
        rig.baseline_m,
        jaws={"layout_deg": 20.0, "trained_deg": [20.0, 60.0]},
    )
    assert load_estimator(opened).trained_jaw_deg == (20.0, 60.0) and est.trained_jaw_deg == (20.0, 20.0)
    with monkeypatch.context() as m:
        m.setattr(pixel_loop, "_judge", lambda _policy: (_ for _ in ()).throw(RuntimeError("the loop runs")))
        with pytest.warns(UserWarning, match="opens its jaws on the way .* training frames drew them at 20-20 deg"):
            with pytest.raises(RuntimeError, match="the loop runs"):
                execute_from_pixels(regrasp_mjx.load_policy(OPEN40), est, needle[:1], start[:1], renderer=renderer)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(RuntimeError, match="the loop runs"):
                execute_from_pixels(
                    regrasp_mjx.load_policy(OPEN40), load_estimator(opened), needle[:1], start[:1], renderer=renderer
                )
    # the fit is told each row's opening: a pair seen with its jaws at 40 fits as the estimator says at 40
    calls = []
    real_poses = est.poses
    with monkeypatch.context() as m:
        m.setattr(
            type(est),
            "poses",
            lambda self, rgb, batch, jaw_deg=None: calls.append(jaw_deg) or real_poses(rgb, batch, jaw_deg),
        )
        Eyes(est, rig, renderer, episode_seeds(3, 0), needle[:3], 3).look(
            np.array([0, 2]), start[[0, 2]], np.array([20.0, 40.0])
        )
    np.testing.assert_array_equal(calls[0], [20.0, 40.0, 40.0])  # padded to the batch with its last row


def test_the_loop_s_refusals(policy, problems, monkeypatch):
    needle, start, goal = (x[:1] for x in problems)
    oracle = OracleEstimator.of(endoscope.Rig(width=W, height=H))
    with pytest.raises(PixelLoopError, match="not accepted: a loaded Estimator"):
        execute_from_pixels(policy, object(), needle, start, goal)
    with pytest.raises(PixelLoopError, match="batch=0"):
        execute_from_pixels(policy, oracle, needle, start, goal, batch=0, render=False)
    with pytest.raises(PixelLoopError, match="seeds of shape"):
        execute_from_pixels(policy, oracle, needle, start, goal, seeds=[1, 2], render=False)
    with pytest.raises(PixelLoopError, match="warmup_frames=0"):
        execute_from_pixels(policy, oracle, needle, start, goal, warmup_frames=0, render=False)
    with pytest.raises(PixelLoopError, match="needle"):
        execute_from_pixels(policy, oracle, needle * np.nan, start, goal, render=False)
    with monkeypatch.context() as m:
        looks = {"look_frames": 30, "warmup_frames": 10, "stop_tolerance": 0.8, "jaw_deg": None, "jaw_sigmas": 0.0}
        m.setattr(type(policy), "closed_loop_defaults", property(lambda self: looks))
        m.setattr(pixel_loop, "_judge", lambda _policy: (_ for _ in ()).throw(RuntimeError("the loop runs")))
        with pytest.warns(UserWarning, match=r"looks before its last moves \(look_frames 30\).* will not look"):
            with pytest.raises(RuntimeError, match="the loop runs"):  # without the camera's sizes: no looking, said
                execute_from_pixels(policy, oracle, needle, start, goal, render=False)
        with pytest.raises(PixelLoopError, match="camera errors 'lab-bad' are not accepted"):  # given to CameraLoop
            execute_from_pixels(policy, oracle, needle, start, goal, render=False, camera="lab-bad")


# ---- the command line --------------------------------------------------------------------------------------


def _cli(argv):
    return run_main(cli.main, argv)


def test_the_command_writes_its_report_and_resumes_a_killed_run(tmp_path, policy):
    """``estimator loop`` through the oracle without images (fast): strict JSON, a markdown table and the
    rows; a run killed after its first batch goes on from there, to the rows of a run never killed."""
    # 320 x 180 (no images drawn): 0.05 px of noise is about 0.1 mm of needle in e_g a frame
    base = ["loop", "--estimator", "oracle", "--n", "3", "--batch", str(ROWS), "--no-render", "--noise-px", "0.05"]
    base += ["--seed", "5"]
    code, out, err = _cli(base + ["--out", str(tmp_path / "whole")])
    assert code == 0, err
    printed = json.loads(out.strip().splitlines()[-1])
    assert printed["problems"] == "paper300[:3]" and printed["success_rate"] == 1.0
    rep = json.loads((tmp_path / "whole" / "pixel_loop.json").read_text())  # strict JSON: no NaN
    assert (
        rep["summary"]["problems"] == 3
        and rep["settings"]["warmup_frames"] == policy.closed_loop_defaults["warmup_frames"]
    )
    assert 0.01 < rep["summary"]["estimate_per_frame"]["needle_in_e_g"]["position_mm"]["median"] < 0.2
    table = (tmp_path / "whole" / "pixel_loop.md").read_text()
    assert "| 3 | 1.000 | 0.000 | 0.000 | 0.000 |" in table
    assert not (tmp_path / "whole" / "pixel_loop.parts").exists()

    args = pixel_report.LoopArgs("default", "oracle", "paper300", None, 3, 5, ROWS, noise_px=0.05, render=False)

    def killed(line):
        if line.startswith("pixels: batch 1/2"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        pixel_report.run(args, tmp_path / "killed", policy, log=killed)
    assert sorted(p.name for p in (tmp_path / "killed" / "pixel_loop.parts").iterdir()) == [
        "manifest.json",
        "rows_000000.npz",
    ]
    lines = []
    pixel_report.run(args, tmp_path / "killed", policy, log=lines.append)
    assert "(1 done before)" in lines[0] and len([x for x in lines if x.startswith("pixels: batch")]) == 1
    with (
        np.load(tmp_path / "whole" / "pixel_loop_rows.npz") as a,
        np.load(tmp_path / "killed" / "pixel_loop_rows.npz") as b,
    ):
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)

    # two shards side by side, then the report: the rows of the run in one process; no report while a shard runs
    sharded = tmp_path / "sharded"
    for i in (1, 0):
        code, out, err = _cli(base + ["--out", str(sharded), "--shard", f"{i}/2"])
        assert code == 0 and json.loads(out.strip().splitlines()[-1]) == {
            "out": str(sharded),
            "shard": [i, 2],
            "done": True,
        }, err
        assert not (sharded / "pixel_loop.json").exists()
    with folder_lock(sharded, shared=True):  # a shard still running (or only starting)
        code, _, err = _cli(base + ["--out", str(sharded)])
        assert code == 2 and "in use" in err, err
        code, _, err = _cli(base + ["--out", str(sharded), "--shard", "0/3"])  # shards of another N
        assert code == 2 and "holds shards of --shard I/2" in err, err
    code, out, err = _cli(base + ["--out", str(sharded)])
    assert code == 0, err
    with np.load(tmp_path / "whole" / "pixel_loop_rows.npz") as a, np.load(sharded / "pixel_loop_rows.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert json.loads((sharded / "pixel_loop.json").read_text())["seconds"] > 0
    code, _, err = _cli(base + ["--out", str(sharded), "--shard", "2/2"])
    assert code == 2 and "I/N with 0 <= I < N" in err

    (tmp_path / "other" / "pixel_loop.parts").mkdir(parents=True)
    (tmp_path / "other" / "pixel_loop.parts" / "manifest.json").write_text(json.dumps({"seed": 1}))
    code, _, err = _cli(base + ["--out", str(tmp_path / "other")])
    assert code == 2 and "holds the batches of another run" in err


def test_the_command_looks_by_the_camera_named(tmp_path, policy):
    """``--camera`` reaches the loop: the shipped default looks before its last moves by the preset named
    (the rows' looked frames, the report's settings and line); ``none`` never looks. Through the oracle
    without images, 2 problems."""
    base = ["loop", "--estimator", "oracle", "--n", str(ROWS), "--batch", str(ROWS), "--no-render", "--seed", "5"]
    code, out, err = _cli(base + ["--camera", "rendered", "--out", str(tmp_path / "rendered")])
    assert code == 0, err
    assert json.loads(out.strip().splitlines()[-1])["camera"] == "rendered"
    rep = json.loads((tmp_path / "rendered" / "pixel_loop.json").read_text())
    settings = rep["settings"]
    assert settings["camera"] == "rendered" and settings["look_frames"] == policy.closed_loop_defaults["look_frames"]
    assert settings["camera_sizes"] == dataclasses.asdict(camera_presets.preset("rendered"))
    assert settings["jaws_drawn"] == "not drawn" and settings["jaw_open_deg"] == 40.0  # --no-render: no images
    table = (tmp_path / "rendered" / "pixel_loop.md").read_text()
    assert "looking up to 60 frames by the camera errors rendered" in table and "40 deg (no images drawn)" in table
    with np.load(tmp_path / "rendered" / "pixel_loop_rows.npz") as rows:
        looked = rows["looked"]
    assert (looked > 0).all(), looked  # the preset's sizes leave the view too uncertain to stop on unlooked
    code, _, err = _cli(base + ["--camera", "none", "--out", str(tmp_path / "none")])
    assert code == 0, err
    assert json.loads((tmp_path / "none" / "pixel_loop.json").read_text())["settings"]["camera"] is None
    with np.load(tmp_path / "none" / "pixel_loop_rows.npz") as rows:
        assert (rows["looked"] == 0).all()


def test_the_command_s_camera_default_and_bad_names(tmp_path, monkeypatch):
    """``--camera``'s default: ``rendered`` (fitted to the learned estimator's errors) with a learned
    estimator, none with the oracle; a name given is passed through; a bad name is refused listing the
    accepted ones, and a fitted preset without its file says how to make it."""
    taken = []

    def run(args, *_a, **_k):
        taken.append(args.camera)
        raise PixelLoopError("stopped here")

    out = ["--out", str(tmp_path / "o")]
    mine = tmp_path / "mine.json"  # a fit of one's own estimator's errors
    mine.write_text(camera_presets.FITTED["rendered"].read_text())
    with monkeypatch.context() as m:
        m.setattr(pixel_report, "run", run)
        for argv in (
            ["--estimator", str(tmp_path / "est")],
            ["--estimator", "oracle"],
            ["--estimator", str(tmp_path / "est"), "--camera", "lab-good"],
            ["--estimator", "oracle", "--camera", "rendered"],
            ["--estimator", str(tmp_path / "est"), "--camera", "none"],
            ["--estimator", str(tmp_path / "est"), "--camera", str(mine)],
        ):
            code, _, err = _cli(["loop", *argv, *out])
            assert code == 2 and "stopped here" in err, err
    assert taken == ["rendered", None, "lab-good", "rendered", None, str(mine)]
    # a fit file of one's own: its sizes, as the preset fitted to the same file
    args = pixel_report.LoopArgs("default", "oracle", camera=str(camera_presets.FITTED["rendered"]))
    assert pixel_report.camera_of(args) == camera_presets.preset("rendered")
    with pytest.raises(ConfigError, match="no fitted file yet"):
        pixel_report.camera_of(dataclasses.replace(args, camera=str(tmp_path / "none.json")))
    code, _, err = _cli(["loop", "--estimator", "oracle", "--camera", "lab-bad", *out])
    assert code == 2 and "argument --camera: 'lab-bad' is not accepted" in err
    assert all(f"'{name}'" in err for name in (*camera_presets.PRESETS, "none")), err
    monkeypatch.setitem(camera_presets.FITTED, "rendered", tmp_path / "no_fit.json")
    code, _, err = _cli(["loop", "--estimator", str(tmp_path / "est"), *out])  # the default, without its file
    assert code == 2 and "--camera rendered: camera errors 'rendered': no fitted file yet" in err, err
    assert "python -m regrasp_mjx.estimator fit" in err


def test_the_command_s_bad_arguments(tmp_path):
    out = ["--out", str(tmp_path / "o")]
    code, _, err = _cli(["loop", "--estimator", str(tmp_path / "none"), "--noise-px", "1"] + out)
    assert code == 2 and "the oracle's" in err
    code, _, err = _cli(["loop", "--estimator", str(tmp_path / "none"), "--width", "64"] + out)
    assert code == 2 and "the size it was trained at" in err
    code, _, err = _cli(["loop", "--estimator", str(tmp_path / "none"), "--n", "1"] + out)
    assert code == 2 and "estimator folder not found" in err
    code, _, err = _cli(["loop", "--estimator", "oracle", "--heldout", "5"] + out)
    assert code == 2 and "N:SEED" in err
    code, _, err = _cli(["loop", "--estimator", "oracle", "--width", "8"] + out)
    assert code == 2 and "within [16, 4096]" in err
    code, _, err = _cli(["loop", "--estimator", "oracle", "--n", "400", "--no-render"] + out)
    assert code == 2 and "n=400 is not accepted" in err
    code, _, err = _cli(["loop", "--estimator", "oracle", "--policy", "nope", "--no-render"] + out)
    assert code == 2 and "nope" in err
    code, _, err = _cli(["loop", "--estimator", "oracle", "--testset", "general1000", "--no-render"] + out)
    assert code == 2 and "the endoscope draws the scene's needle" in err
