"""The estimator measured: its pose errors on held-out frames (:mod:`regrasp_mjx.vision.pose_errors`: the
needle's and each tool's, fixed per episode and per frame, along and across the optical axis, median and
95th percentile), its keypoints' pixel errors (seen and hidden), and the relative poses a policy
observes (the needle and the regrasping tool in the grasping tool's frame), written as strict JSON and
a markdown table, with every frame's errors beside them (what the camera-error model is fitted to:
:mod:`regrasp_mjx.vision.error_fit`); and its time per stereo pair on this machine's default device.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.vision import error_fit, pose_errors
from regrasp_mjx.vision.estimator_file import Estimator, EstimatorError, estimator_folder, load_estimator, predict
from regrasp_mjx.vision.network import decode, make_network
from regrasp_mjx.workflows.frame_dataset import FrameDataset, load_dataset
from regrasp_mjx.world.endoscope import OBJECTS, quat_matrix

REPORT = "estimator_errors"


def check_pairing(est: Estimator, data: FrameDataset) -> None:
    """Refuses frames the estimator cannot be measured on: another image size, keypoints or cameras."""
    size = (int(data.meta["width"]), int(data.meta["height"]))
    if size != (est.net.width, est.net.height):
        raise EstimatorError(
            f"the frames are {size[0]} x {size[1]}; this estimator takes {est.net.width} x {est.net.height}"
        )
    if tuple(data.meta["keypoints"]["names"]) != est.keypoints.names:
        raise EstimatorError("the frames' keypoints are not the estimator's (another layout)")
    if not np.allclose(data.intrinsics, est.fit.intrinsics):
        raise EstimatorError("the frames' camera intrinsics are not the estimator's")


def _relative(poses: np.ndarray) -> np.ndarray:
    """The needle and the regrasping tool ``[N, 2, 4, 4]`` in the grasping tool's frame, of camera-frame poses."""
    mats = np.zeros(poses.shape[:2] + (4, 4))
    mats[..., :3, :3], mats[..., :3, 3], mats[..., 3, 3] = quat_matrix(poses[..., 3:]), poses[..., :3], 1.0
    rot_t = np.swapaxes(mats[:, 1, :3, :3], -1, -2)
    inv = np.zeros_like(mats[:, 1])
    inv[:, :3, :3], inv[:, :3, 3], inv[:, 3, 3] = rot_t, -(rot_t @ mats[:, 1, :3, 3, None])[..., 0], 1.0
    return inv[:, None] @ mats[:, [0, 2]]


def _relative_errors(estimate: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    est, tru = _relative(estimate), _relative(truth)
    out = {}
    for i, name in enumerate(("needle_in_e_g", "regrasping_tool_in_e_g")):
        ok = np.all(np.isfinite(est[:, i]), axis=(-2, -1))
        pos = (est[ok, i, :3, 3] - tru[ok, i, :3, 3]) * 1e3
        rot = np.degrees(
            np.linalg.norm(pose_errors.rotvec(est[ok, i, :3, :3] @ np.swapaxes(tru[ok, i, :3, :3], -1, -2)), axis=-1)
        )
        norm = np.linalg.norm(pos, axis=-1)
        out[name] = {
            "position_mm": {"median": float(np.median(norm)), "p95": float(np.percentile(norm, 95))}
            if ok.any()
            else None,
            "orientation_deg": {"median": float(np.median(rot)), "p95": float(np.percentile(rot, 95))}
            if ok.any()
            else None,
        }
    return out


def _by_jaws(estimate: np.ndarray, truth: np.ndarray, jaw_deg: np.ndarray, layout_deg: float) -> dict[str, Any]:
    """The regrasping tool's errors in the frames that draw its jaws at the layout's opening and in those
    that draw them opened wider, failed and gross frames left out and counted as the main table does. Not
    a clean comparison of the openings: a dataset opens them in each episode's later frames, nearer the
    goal."""
    pos, rot = pose_errors.frame_errors(np.asarray(estimate, np.float64), truth)
    mm, deg = np.linalg.norm(pos[:, 2], axis=-1), np.linalg.norm(rot[:, 2], axis=-1)
    kept = np.isfinite(mm) & (mm <= pose_errors.GROSS_MM)
    out = {}
    for key, rows in (("at_layout", jaw_deg <= layout_deg + 0.5), ("opened", jaw_deg > layout_deg + 0.5)):
        out[key] = {
            "frames": int(rows.sum()),
            "left_out": int((rows & ~kept).sum()),
            "position_mm": pose_errors.stats(mm[rows & kept]),
            "orientation_deg": pose_errors.stats(deg[rows & kept]),
        }
    return out


def _keypoint_errors(est: Estimator, data: FrameDataset, pixels: np.ndarray) -> dict[str, Any]:
    err = np.linalg.norm(pixels - data.pixels, axis=-1)  # [N, 2, K]
    inside = (data.pixels[..., 0] >= -0.5) & (data.pixels[..., 0] < est.net.width - 0.5)
    inside &= (data.pixels[..., 1] >= -0.5) & (data.pixels[..., 1] < est.net.height - 0.5)
    out = {}
    for o, name in enumerate(OBJECTS):
        cols = est.keypoints.obj == o
        row = {}
        for key, mask in (("seen", data.visible), ("hidden", inside & ~data.visible)):
            e = err[:, :, cols][mask[:, :, cols]]
            row[key] = {"n": int(e.size)} | (
                {"median": float(np.median(e)), "p95": float(np.percentile(e, 95))} if e.size else {}
            )
        out[name] = row
    return out


def evaluate(estimator: str | Path, data_path: str | Path, out: str | Path | None, batch: int = 64, log=print) -> dict:
    """The estimator's errors on the frames of ``data_path``; ``OUT/estimator_errors.json`` and ``.md``
    written when ``out`` is given, and every frame's errors in ``OUT/estimator_errors_frames.npz``
    (:func:`regrasp_mjx.vision.error_fit.save_frame_errors`: what ``estimator fit`` reads).

    Raises:
      EstimatorError: an unreadable estimator, or frames it does not take.
      DatasetError: unreadable frames.
    """
    est, data = load_estimator(estimator), load_dataset(data_path)
    check_pairing(est, data)
    t0 = time.perf_counter()
    result = est.poses(
        data.rgb, batch=batch, jaw_deg=data.jaw_deg
    )  # the fit told the jaws' opening, as the loop tells it
    seconds = time.perf_counter() - t0
    truth = data.camera_poses(0)
    trained_on = est.contract.get("training", {}).get("data", {})
    held_out = trained_on.get("seed") != data.meta["seed"]
    if not held_out:
        log(f"warning: these frames have the training frames' seed ({data.meta['seed']}): not held out")
    rep = pose_errors.report(result["poses"], truth, data.episode)
    rep |= {
        "held_out": held_out,
        "keypoints_px": _keypoint_errors(est, data, result["pixels"]),
        "relative": _relative_errors(result["poses"], truth),
        "fit_rms_px": {n: float(np.nanmedian(result["rms_px"][:, o])) for o, n in enumerate(OBJECTS)},
        "regrasping_tool_by_jaws": _by_jaws(result["poses"], truth, data.jaw_deg, est.layout_jaw_deg),
        "estimator": str(estimator_folder(estimator)),
        "data": {
            "path": str(data_path),
            **{k: data.meta[k] for k in ("seed", "episodes", "frames", "width", "height")},
        },
        "seconds": seconds,
        "machine": machine(),
    }
    title = (
        f"Estimator errors on {Path(data_path).name} (seed {data.meta['seed']}{'' if held_out else ', NOT held out'})"
    )
    lines = pose_errors.markdown(rep, title)
    lines += ["", "Keypoints, pixels (median / p95; seen, hidden in the image):", ""]
    for name in OBJECTS:
        k = rep["keypoints_px"][name]
        cells = [
            f"{k[s]['median']:.2f} / {k[s]['p95']:.2f} ({k[s]['n']})" if k[s]["n"] else "-" for s in ("seen", "hidden")
        ]
        lines.append(f"- {name}: seen {cells[0]}, hidden {cells[1]}")
    lines += ["", "The regrasping tool by its jaws' opening (position mm, orientation deg; median / p95):", ""]
    for key, row in rep["regrasping_tool_by_jaws"].items():
        p, o = row["position_mm"], row["orientation_deg"]
        if row["frames"]:
            cells = "-" if p["median"] is None else f"{p['median']:.2f} / {p['p95']:.2f} mm, "
            cells += "" if o["median"] is None else f"{o['median']:.2f} / {o['p95']:.2f} deg"
            lines.append(f"- {key.replace('_', ' ')} ({row['frames']} frames, {row['left_out']} left out): {cells}")
    if out is not None:
        pos, rot = pose_errors.frame_errors(np.asarray(result["poses"], np.float64), truth)
        meta = {k: rep[k] for k in ("held_out", "estimator", "data", "machine")}
        frames = error_fit.FrameErrors(data.episode, data.frame, pos, rot, meta)
        error_fit.save_frame_errors(Path(out) / error_fit.FRAMES_FILE, frames)
        rep["frame_errors"] = error_fit.FRAMES_FILE
    write_results(out, REPORT, lines, rep)
    return rep


def headline(rep: dict[str, Any]) -> dict[str, Any]:
    """The few numbers of a report a command prints: each object's position (mm) and orientation (deg)
    error, median and 95th percentile, and its failed and gross rates."""
    out: dict[str, Any] = {k: rep[k] for k in ("frames", "episodes", "held_out")}
    for name in OBJECTS:
        row = rep[name]
        out[name] = {
            "position_mm": row["position_mm"]["total"]["norm"],
            "orientation_deg": row["orientation_deg"]["total"]["norm"],
            "failed": row["failed"],
            "gross": row["gross"],
        }
    return out


def bench(estimator: str | Path, repeats: int = 50, batch: int = 1) -> dict[str, Any]:
    """Milliseconds per call of the estimator (``batch`` stereo pairs) on this machine's default device:
    the network and decoding alone, and with the pose fit; medians of ``repeats`` calls after a warm-up."""
    est = load_estimator(estimator)
    rgb = jnp.asarray(np.random.default_rng(0).integers(0, 256, (batch, 2, est.net.height, est.net.width, 3), np.uint8))
    net_only = jax.jit(lambda p, x: decode(est.net, *make_network(est.net).apply(p, x.reshape((-1,) + x.shape[2:]))))
    whole = jax.jit(lambda p, x: predict(est.net, est.fit, p, x))
    out = {"batch": batch, "repeats": repeats, "machine": machine(), "image": [est.net.width, est.net.height]}
    for name, fn in (("network_ms", net_only), ("network_and_fit_ms", whole)):
        jax.block_until_ready(fn(est.params, rgb))
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn(est.params, rgb))
            times.append(1e3 * (time.perf_counter() - t))
        out[name] = float(np.median(times))
        out[name.replace("_ms", "_ms_per_pair")] = float(np.median(times)) / batch
    return out
