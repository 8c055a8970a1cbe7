"""The camera-error model fitted to an estimator's measured errors (issue 68, step 4): the moments worked
by hand, the fit recovering exactly the sizes behind exact moments and, within stated tolerances, those
behind sampled sequences (a bias, an AR(1) drift, white noise, depth stretched along the optical axis,
rotations of known degrees per mm), the fit file read back as the ``rendered`` preset wherever a preset
name is taken, and bad files refused. Numpy only: seconds."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from regrasp_mjx import compare, evaluate
from regrasp_mjx import estimator as estimator_cli
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_errors import CameraErrors, Tracking
from regrasp_mjx.envs.camera_presets import PRESETS
from regrasp_mjx.inference import robustness, robustness_report
from regrasp_mjx.vision import error_fit, variogram
from regrasp_mjx.vision.error_fit import FitError, FrameErrors
from tests.cli_helper import run_main

# the sizes behind the sampled sequences: per object bias (mm, the shift's length), drift (mm per axis),
# its correlation time (the data's frames), white (mm per axis), degrees per mm; one depth factor
NEEDLE = (0.4, 0.2, 3.0, 0.15, 2.0)
TOOL = (0.3, 0.1, 5.0, 0.1, 3.0)
DEPTH = 2.0
E, F = 2000, 8


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _ar1(rng, sd, rho):
    x = np.zeros((E, F, 3))
    x[:, 0] = sd * rng.normal(size=(E, 3))
    for t in range(1, F):
        x[:, t] = rho * x[:, t - 1] + math.sqrt(1.0 - rho**2) * sd * rng.normal(size=(E, 3))
    return x


def sample(rng, bias, drift, tau, white, deg_per_mm, depth=DEPTH):
    """``E`` episodes of ``F`` frames of the model's errors (position mm, rotation vector deg; z the
    optical axis), small rotations summed as vectors."""
    rho = math.exp(-1.0 / tau)
    pos = bias * _unit(rng, E)[:, None] + _ar1(rng, drift, rho) + white * rng.normal(size=(E, F, 3))
    pos[..., 2] *= depth
    rot = deg_per_mm * bias * _unit(rng, E)[:, None] + _ar1(rng, deg_per_mm * drift / math.sqrt(3.0), rho)
    rot += deg_per_mm * white * rng.normal(size=(E, F, 1)) * _unit(rng, E * F).reshape(E, F, 3)
    return pos.reshape(-1, 3), rot.reshape(-1, 3)


@pytest.fixture(scope="module")
def errors():
    rng = np.random.default_rng(0)
    parts = [sample(rng, *NEEDLE), sample(rng, *TOOL), sample(rng, *TOOL)]
    meta = {"held_out": True, "estimator": "synthetic", "data": {"path": "synthetic", "seed": 2, "frames": F}}
    return FrameErrors(
        np.repeat(np.arange(E), F),
        np.tile(np.arange(F), E),
        np.stack([p for p, _ in parts], 1),
        np.stack([r for _, r in parts], 1),
        meta,
    )


def test_the_moments_worked_by_hand():
    # episode 0: frames 0, 1, 2 at 1, 3, 2; episode 7: frames 0, 1, 2 at 2, NaN (no pose), 4
    values = np.array([[1.0], [3.0], [2.0], [2.0], [np.nan], [4.0]])
    s0, gamma, pairs = variogram.moments(values, np.array([0, 0, 0, 7, 7, 7]), np.array([0, 1, 2] * 2), 2)
    assert s0 == pytest.approx((1 + 9 + 4 + 4 + 16) / 5)
    np.testing.assert_array_equal(pairs, [2, 2])  # lag 1: (1, 3), (3, 2); lag 2: (1, 2), (2, 4)
    np.testing.assert_allclose(gamma, [((3 - 1) ** 2 + (2 - 3) ** 2) / 4, ((2 - 1) ** 2 + (4 - 2) ** 2) / 4])


def test_exact_moments_give_back_exactly_their_sizes():
    """S0 = B + D + W and gamma(L) = W + D (1 - exp(-L / tau)) of known parts: the fit returns them."""
    lags = np.arange(1, 8)
    stats, truth = [], [(0.05, 0.04, 0.02), (0.2, 0.16, 0.08), (0.3, 0.1, 0.0)]  # (B, D, W); the last no white
    for b, d, w in truth:
        gamma = w + d * (1.0 - np.exp(-lags / 3.0))
        stats.append((b + d + w, gamma, np.full(7, 100)))
    out = variogram.fit_series(stats, (1.0, 3000.0))
    assert out["tau"] == pytest.approx(3.0, rel=1e-4) and not out["at_bound"]
    for (b, d, w), s in zip(truth, out["series"], strict=True):
        assert (s["bias"], s["drift"], s["white"]) == pytest.approx((b, d, w), abs=1e-6)
    # no drift at all: any tau; the bias and the white part are still exact
    flat = variogram.fit_series([(0.3, np.full(7, 0.1), np.full(7, 10))], (1.0, 3000.0))["series"][0]
    assert flat["white"] + flat["drift"] * (1.0 - math.exp(-1.0 / 3000.0)) == pytest.approx(0.1, abs=1e-6)


def test_sampled_sequences_give_back_their_sizes_within_tolerance(errors):
    """2000 episodes of 8 frames. Over 30 other seeds (sd / largest error): the needle's sizes 1.6-2.1 % /
    6 %, its correlation time 8 % / 24 %; a tool's drift 5 % / 15 % and its correlation time 21 % / 72 %
    (5 frames in episodes of 8, the drift no larger than the white part: the hardest to tell apart);
    depth and degrees per mm 1 % / 4 % (each part's own ratio 1-4 % / 9 %). The bounds below are about three
    standard deviations; the tools' fit pools both tools (twice the episodes)."""
    result = error_fit.fit(errors, motion_frames=F - 1)  # one loop frame per frame of the data
    json.dumps(result, allow_nan=False)  # strict JSON
    assert result["frames_per_episode"] == F and result["max_lag"] == F - 1
    for name, sizes, rel, rel_drift, rel_tau in (
        ("needle", NEEDLE, 0.07, 0.07, 0.25),
        ("tools", TOOL, 0.07, 0.12, 0.5),
        ("grasping_tool", TOOL, 0.07, 0.15, 0.65),
    ):
        bias, drift, tau, white, dpm = sizes
        t = result["objects"][name]["tracking"]
        got = (t["bias_mm"], t["white_mm"], t["deg_per_mm"])
        assert got == pytest.approx((bias, white, dpm), rel=rel), name
        assert t["drift_mm"] == pytest.approx(drift, rel=rel_drift), name
        assert t["drift_frames"] == pytest.approx(tau, rel=rel_tau), name
        assert result["objects"][name]["depth_factor"] == pytest.approx(DEPTH, rel=0.04), name
        for part in ("bias", "drift", "white"):
            assert result["objects"][name]["depth_factor_parts"][part] == pytest.approx(DEPTH, rel=0.15)
            assert result["objects"][name]["deg_per_mm_parts"][part] == pytest.approx(dpm, rel=0.15)
    preset = result["preset"]
    assert preset["depth_factor"] == pytest.approx(DEPTH, rel=0.05)
    assert preset["needle"] == {k: round(v, 6) for k, v in result["objects"]["needle"]["tracking"].items()}
    # the loop's frames: the same tau in the data's frames, twice the loop's frames per frame of the data
    slower = error_fit.fit_object(
        errors.position_mm[:, 0], errors.orientation_deg[:, 0], errors.episode, errors.frame, F, 2.0 * (F - 1)
    )
    tau = result["objects"]["needle"]["tracking"]["drift_frames"]
    assert slower["tracking"]["drift_frames"] == pytest.approx(2.0 * tau, rel=1e-3)


def test_lost_and_gross_frames_are_left_out_and_counted(errors):
    pos = errors.position_mm[: 40 * F, 0].copy()
    rot = errors.orientation_deg[: 40 * F, 0].copy()
    pos[3] = np.nan  # no pose
    pos[9] = [0.0, 0.0, 8.0]  # 8 mm off: gross
    row = error_fit.fit_object(pos, rot, errors.episode[: 40 * F], errors.frame[: 40 * F], F)
    assert row["failed_rate"] == pytest.approx(1 / (40 * F)) and row["gross_rate"] == pytest.approx(1 / (40 * F))
    assert row["frames_used"] == 40 * F - 2 and row["series"]["across"]["pairs"][0] == 40 * (F - 1) - 4
    big = errors.position_mm.copy()
    big[::10, 2] = [0.0, 0.0, 6.0]  # a tenth of the regrasping tool's frames gross
    result = error_fit.fit(dataclasses.replace(errors, position_mm=big))
    assert result["objects"]["regrasping_tool"]["gross_rate"] == pytest.approx(0.1)
    assert any(n.startswith("regrasping_tool: 10.0 % of the frames left out") for n in result["notes"])
    assert not any(n.startswith("needle: ") and "left out" in n for n in result["notes"])
    with pytest.raises(FitError, match="3 or more"):
        error_fit.fit_object(pos, rot, errors.episode[: 40 * F], errors.frame[: 40 * F] % 2, 2)


def test_the_command_writes_a_file_the_rendered_preset_reads(errors, tmp_path, monkeypatch):
    error_fit.save_frame_errors(tmp_path / "eval" / error_fit.FRAMES_FILE, errors)
    out = tmp_path / "camera_rendered.json"
    code, printed, err = run_main(
        estimator_cli.main, ["fit", "--errors", str(tmp_path / "eval"), "--out", str(out), "--bootstrap", "3"]
    )
    assert code == 0, err
    assert "| needle (preset) |" in printed and "90 % intervals over 3 resamples" in printed
    saved = json.loads(out.read_text(), parse_constant=pytest.fail)  # strict JSON: no NaN
    assert saved["format"] == camera_presets.FIT_FORMAT and saved["measured"]["estimator"] == "synthetic"
    lo, hi = saved["interval"]["needle.bias_mm"]
    assert lo <= hi and saved["interval"]["fitted"] == 3
    camera = camera_presets.fitted(out)
    assert camera.needle == Tracking(**saved["preset"]["needle"]) and camera.depth_factor == pytest.approx(
        2.0, rel=0.05
    )
    # the preset by name, wherever lab-good is taken
    monkeypatch.setitem(camera_presets.FITTED, "rendered", out)
    assert "rendered" in PRESETS and tuple(PRESETS)[-1] == "rendered"
    assert camera_presets.preset("rendered") == camera == PRESETS["rendered"]
    (condition,) = [c for c in robustness.NAMED_CONDITIONS if c.name == "camera: rendered"]
    assert condition not in robustness.ALL_CONDITIONS and condition.resolved_camera() == camera
    assert robustness.program_groups(("fused",), ("camera: rendered",)) == [("fused", ["camera: rendered"])]
    # the docs' camera table shows a fitted row only where a table holds it
    row = {"condition": "camera: rendered", "mode": "fused", "success_rate": 0.5, "collision_rate": 0.25}
    table = {"policy": "default", "policy_hash": "h", "problems": "paper300", "rows": [row | {"wrong_stop_rate": 0}]}
    assert robustness_report.camera_block([table])[-1] == "| rendered | 0.500 (0.250 / 0.000) |"


def test_a_missing_or_broken_fit_file_is_refused(tmp_path, monkeypatch):
    missing = tmp_path / "none.json"
    monkeypatch.setitem(camera_presets.FITTED, "rendered", missing)
    with pytest.raises(ConfigError, match=r"no fitted file yet .*estimator fit --errors EVAL --out"):
        camera_presets.preset("rendered")
    with pytest.raises(ConfigError, match="no fitted file yet"):
        PRESETS["rendered"]
    assert PRESETS["lab-good"] == camera_presets.LITERATURE["lab-good"]  # the others unaffected
    with pytest.raises(ConfigError, match="camera='lab-best' is not accepted: a CameraErrors or one of"):
        robustness.Condition("x", camera="lab-best")
    # the command lines refuse at once, with how to make the file
    code, _, err = run_main(compare.main, ["--robustness", "--conditions", "camera: rendered"])
    assert code == 2 and "no fitted file yet" in err
    code, _, err = run_main(evaluate.main, ["--closed-loop", "--camera", "rendered"])
    assert code == 2 and "--camera rendered: camera errors 'rendered': no fitted file yet" in err
    good = {
        "format": camera_presets.FIT_FORMAT,
        "version": camera_presets.FIT_VERSION,
        "preset": {
            "needle": dataclasses.asdict(Tracking(0.3, 0.1, 5.0, 0.1, 2.0)),
            "tools": dataclasses.asdict(Tracking(0.2)),
            "depth_factor": 2.0,
        },
    }
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(good))
    assert camera_presets.fitted(path) == CameraErrors(Tracking(0.3, 0.1, 5.0, 0.1, 2.0), Tracking(0.2), 2.0)
    needle = good["preset"]["needle"]
    for text, match in (
        ("{", "not strict JSON"),
        (json.dumps(good).replace("0.3", "NaN"), "NaN is not a number of strict JSON"),
        (json.dumps({**good, "format": "other"}), "its format is not"),
        (json.dumps({**good, "version": 9}), "version 9; this package reads version 1"),
        (json.dumps({**good, "preset": {"needle": needle}}), "its 'preset' is not"),
        (json.dumps({**good, "preset": {**good["preset"], "tools": {"bias_mm": 1}}}), "'tools' does not hold exactly"),
        (
            json.dumps({**good, "preset": {**good["preset"], "needle": {**needle, "white_mm": -1}}}),
            "its preset's needle: white_mm=-1 is not accepted",
        ),
        (json.dumps({**good, "preset": {**good["preset"], "depth_factor": 0.5}}), "depth_factor=0.5 is not accepted"),
    ):
        path.write_text(text)
        with pytest.raises(ConfigError, match=f"is not a camera-error fit .*{match}"):
            camera_presets.fitted(path)


def test_bad_per_frame_errors_are_refused(errors, tmp_path):
    with pytest.raises(FitError, match="no per-frame errors at .* must be run again"):
        error_fit.load_frame_errors(tmp_path)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FitError, match="is not a per-frame error file"):
        error_fit.load_frame_errors(tmp_path / "junk.npz")
    small = dataclasses.replace(errors, episode=errors.episode[:16], frame=errors.frame[:16])
    error_fit.save_frame_errors(tmp_path / "bad.npz", small)
    with pytest.raises(FitError, match=r"position_mm has shape \(16000, 3, 3\); accepted \(16, 3, 3\)"):
        error_fit.load_frame_errors(tmp_path / "bad.npz")
    with pytest.raises(FitError, match="not of held-out frames"):
        error_fit.fit(dataclasses.replace(errors, meta={**errors.meta, "held_out": False}))
    with pytest.raises(FitError, match="motion_frames=0 is not accepted"):
        error_fit.fit(errors, motion_frames=0)
    code, _, err = run_main(estimator_cli.main, ["fit", "--errors", str(tmp_path), "--out", str(tmp_path / "x.txt")])
    assert code == 2 and "ending in .json" in err
    code, _, err = run_main(estimator_cli.main, ["fit", "--errors", str(tmp_path), "--out", str(tmp_path / "x.json")])
    assert code == 2 and "no per-frame errors" in err and not (tmp_path / "x.json").exists()
