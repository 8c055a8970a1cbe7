"""The camera-error model (:mod:`regrasp_mjx.envs.camera_errors`) fitted to an estimator's measured errors:
each frame's position and orientation error of the needle and each tool on held-out rendered frames
(``estimator evaluate`` writes them, :func:`save_frame_errors`), turned into the model's sizes, a fit file
that the ``rendered`` preset reads (:func:`regrasp_mjx.envs.camera_presets.fitted`).

The model's error of one object is, per axis, a bias fixed for the episode, an AR(1) drift and white noise;
:mod:`~regrasp_mjx.vision.variogram` fits their variances ``B, D, W`` and the drift's correlation time to
the second moment of the errors about zero (not about their mean: a constant offset of the estimator is
an error the model can only hold as bias; the file states the mean beside it) and to their
within-episode semivariogram at lags ``1 .. k``, from which the bias cancels: one correlation time for an
object's three series, its position across the optical axis (``x, y`` of the left camera's frame), along
it (``z``), and its orientation (the rotation vector's three components).

The sizes (the model's: :class:`~regrasp_mjx.envs.camera_errors.Tracking`): the position's parts across
the axis give ``bias_mm = sqrt(3 B)`` (the model's bias is a shift of that length in a random
direction), ``drift_mm = sqrt(D)``, ``white_mm = sqrt(W)``; the depth factor is the ratio of the
position's standard deviation along the axis to across it (each part's, and one over all parts and
objects for the preset: the model has one); ``deg_per_mm`` the one ratio of rotation to position that
gives the orientation's measured variance (each part's ratio is in the file); ``drift_frames``, the
correlation time, in the loop's frames: the rendered episodes' ``F`` frames span the regrasping tool's
motion from start to goal, which the closed loop covers in about ``motion_frames`` frames (one a step:
:data:`MOTION_FRAMES`), so ``tau`` in the data's frames times ``motion_frames / (F - 1)``. The tools'
sizes (the model has one set for both) are fitted to both tools' episodes together.

What the model cannot hold is in the file's notes (:func:`fit`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from regrasp_mjx.core.atomic import atomic_write, dumps, machine
from regrasp_mjx.envs.camera_errors import MAX_DEPTH_FACTOR, MAX_DRIFT_FRAMES, MAX_MM, CameraErrors, Tracking
from regrasp_mjx.envs.camera_presets import FIT_FORMAT, FIT_VERSION
from regrasp_mjx.vision import variogram
from regrasp_mjx.vision.pose_errors import GROSS_MM
from regrasp_mjx.world.endoscope import OBJECTS

FRAMES_FORMAT = "regrasp_mjx.estimator_errors_frames"
FRAMES_VERSION = 1
FRAMES_FILE = "estimator_errors_frames.npz"
# the shipped default's median steps from start to goal on paper300 in the closed loop from pixels (the
# oracle, experiments/results/pixel_loop/oracle_px0: 7 steps, one frame each), over which the rendered
# episodes move the regrasping tool from start to goal
MOTION_FRAMES = 7.0
MAX_DEG_PER_MM = 30.0
SERIES = ("across", "along", "rotation")  # position x, y; position z; rotation vector x, y, z
BOOTSTRAP = 100  # the command's resamples of the episodes for the sizes' intervals
LOST_NOTED = 0.05  # a share of frames left out (failed, gross) that the file's notes name


class FitError(ValueError):
    """Per-frame errors that are missing, malformed, or too few to fit."""


# ---- the per-frame errors, as evaluate writes them ------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FrameErrors:
    """Every frame's errors: ``episode`` and ``frame`` ``[N]``, ``position_mm`` and ``orientation_deg``
    ``[N, O, 3]`` (objects :data:`~regrasp_mjx.world.endoscope.OBJECTS`; the left camera's frame, z the
    optical axis; orientation as the rotation vector of ``R_est R_true^T`` in degrees; NaN where the fit
    gave no pose) and ``meta`` (what was measured: the estimator, the frames, whether held out)."""

    episode: np.ndarray
    frame: np.ndarray
    position_mm: np.ndarray
    orientation_deg: np.ndarray
    meta: dict[str, Any]


def save_frame_errors(path: str | Path, errors: FrameErrors) -> None:
    """``errors`` to an npz (atomically): the arrays and a strict-JSON ``meta`` with its format."""
    meta = {"format": FRAMES_FORMAT, "version": FRAMES_VERSION, "objects": list(OBJECTS), **errors.meta}
    arrays = {
        "episode": np.asarray(errors.episode, np.int64),
        "frame": np.asarray(errors.frame, np.int64),
        "position_mm": np.asarray(errors.position_mm, np.float64),
        "orientation_deg": np.asarray(errors.orientation_deg, np.float64),
        "meta": np.asarray(dumps(meta)),
    }
    atomic_write(path, lambda f: np.savez(f, **arrays))


def load_frame_errors(path: str | Path) -> FrameErrors:
    """The per-frame errors of ``path``: an npz of :func:`save_frame_errors`, or the folder of
    ``estimator evaluate --out`` that holds one. Raises :class:`FitError` saying what is wrong."""
    path = Path(path)
    if path.is_dir():
        path = path / FRAMES_FILE
    if not path.is_file():
        raise FitError(
            f"no per-frame errors at {path}: `python -m regrasp_mjx.estimator evaluate --estimator EST --data "
            f"HELDOUT.npz --out DIR` writes DIR/{FRAMES_FILE} (an evaluation made before it did must be run again)"
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.pop("meta")))
    except (OSError, ValueError, KeyError) as err:  # not a zip, no meta, meta not JSON
        raise FitError(f"{path} is not a per-frame error file ({type(err).__name__}: {err})") from None
    if not isinstance(meta, dict) or meta.get("format") != FRAMES_FORMAT or meta.get("version") != FRAMES_VERSION:
        raise FitError(f"{path} is not a per-frame error file of format {FRAMES_FORMAT!r} version {FRAMES_VERSION}")
    if tuple(meta.get("objects", ())) != OBJECTS:
        raise FitError(f"{path}: its objects {meta.get('objects')} are not {list(OBJECTS)}")
    missing = {"episode", "frame", "position_mm", "orientation_deg"} - set(arrays)
    if missing:
        raise FitError(f"{path} lacks the arrays {sorted(missing)}")
    n = len(arrays["episode"])
    shapes = {"episode": (n,), "frame": (n,), "position_mm": (n, len(OBJECTS), 3)}
    shapes["orientation_deg"] = shapes["position_mm"]
    for k, shape in shapes.items():
        if arrays[k].shape != shape:
            raise FitError(f"{path}: {k} has shape {arrays[k].shape}; accepted {shape}")
    if n == 0 or arrays["frame"].min() < 0:
        raise FitError(f"{path}: no frames, or negative frame numbers")
    return FrameErrors(arrays["episode"], arrays["frame"], arrays["position_mm"], arrays["orientation_deg"], meta)


# ---- one object ---------------------------------------------------------------------------------------


def _ratio(num: float, den: float) -> float | None:
    return math.sqrt(num / den) if den > 0 else None


def fit_object(
    position_mm: np.ndarray,
    orientation_deg: np.ndarray,
    episode: np.ndarray,
    frame: np.ndarray,
    frames_per_episode: int,
    motion_frames: float = MOTION_FRAMES,
    max_lag: int | None = None,
) -> dict[str, Any]:
    """The model fitted to one object's errors ``[N, 3]`` (position in mm, orientation as a rotation vector
    in degrees, the left camera's frame; NaN rows: no pose; rows off by more than
    :data:`~regrasp_mjx.vision.pose_errors.GROSS_MM` are gross): see the module docstring. Returns the
    :class:`~regrasp_mjx.envs.camera_errors.Tracking` sizes (``tracking``, unclamped), the object's depth
    factor, and every part of the fit (per-axis variances, the variograms measured and fitted, the
    rates left out)."""
    if frames_per_episode < 3:
        raise FitError(f"{frames_per_episode} frames an episode: the fit needs 3 or more (render --frames 8)")
    finite = np.all(np.isfinite(position_mm), -1) & np.all(np.isfinite(orientation_deg), -1)
    gross = finite & (np.linalg.norm(np.where(finite[:, None], position_mm, 0.0), axis=-1) > GROSS_MM)
    keep = finite & ~gross
    k = max_lag or frames_per_episode - 1
    pos = np.where(keep[:, None], position_mm, np.nan)
    rot = np.where(keep[:, None], orientation_deg, np.nan)
    stats = [variogram.moments(v, episode, frame, k) for v in (pos[:, :2], pos[:, 2:], rot)]
    if any(s[2][:2].min() == 0 for s in stats) or not all(np.isfinite(s[0]) for s in stats):
        raise FitError("too few frames kept: the fit needs pairs of frames one and two apart in some episode")
    scale = motion_frames / (frames_per_episode - 1)  # the loop's frames per frame of the data
    fit = variogram.fit_series(stats, (1.0 / scale, MAX_DRIFT_FRAMES / scale))
    across, along, rotation = fit["series"]
    tracking = {
        "bias_mm": math.sqrt(3.0 * across["bias"]),
        "drift_mm": math.sqrt(across["drift"]),
        "drift_frames": fit["tau"] * scale,
        "white_mm": math.sqrt(across["white"]),
    }
    msq = 3.0 * across["bias"] + across["drift"] + across["white"]  # the model's b^2 + drift^2 + white^2
    rot_total = rotation["bias"] + rotation["drift"] + rotation["white"]
    tracking["deg_per_mm"] = math.sqrt(3.0 * rot_total / msq) if msq > 0 else (0.0 if rot_total == 0 else math.inf)
    series = {}
    for name, unit, (s0, gamma, pairs), part in zip(SERIES, ("mm", "mm", "deg"), stats, fit["series"]):
        series[name] = {
            "unit": f"{unit}^2 per axis",
            "second_moment": s0,
            **{p: part[p] for p in ("bias", "drift", "white")},
            "variogram": gamma.tolist(),
            "variogram_fitted": part["fitted"].tolist(),
            "pairs": pairs.tolist(),
        }
    return {
        "frames": int(len(keep)),
        "frames_used": int(keep.sum()),
        "episodes": int(len(np.unique(episode[keep]))),
        "failed_rate": float(np.mean(~finite)),
        "gross_rate": float(np.mean(gross)),
        "mean_mm": np.nanmean(pos, axis=0).tolist(),
        "mean_deg": np.nanmean(rot, axis=0).tolist(),
        "drift_frames_data": fit["tau"],
        "drift_frames_at_bound": fit["at_bound"],
        "tracking": tracking,
        "depth_factor": _ratio(*(sum(x[p] for p in ("bias", "drift", "white")) for x in (along, across))),
        "depth_factor_parts": {p: _ratio(along[p], across[p]) for p in ("bias", "drift", "white")},
        "rotation_rms_deg": {p: math.sqrt(3.0 * rotation[p]) for p in ("bias", "drift", "white")},
        "deg_per_mm_parts": {
            "bias": _ratio(rotation["bias"], across["bias"]),
            "drift": _ratio(3.0 * rotation["drift"], across["drift"]),
            "white": _ratio(3.0 * rotation["white"], across["white"]),
        },
        "series": series,
    }


# ---- the whole fit ------------------------------------------------------------------------------------


def _clamped(name: str, value: float, lo: float, hi: float, notes: list[str], where: str) -> float:
    if value is None or not math.isfinite(value):
        notes.append(f"{where}: {name} undefined (no position error to scale by): set to {hi:g}")
        return hi
    if lo <= value <= hi:
        return round(value, 6)
    notes.append(f"{where}: {name} {value:.4g} is outside the model's [{lo:g}, {hi:g}]: clamped")
    return round(min(max(value, lo), hi), 6)


def _tracking(fitted: dict[str, float], where: str, notes: list[str]) -> Tracking:
    return Tracking(
        bias_mm=_clamped("bias_mm", fitted["bias_mm"], 0.0, MAX_MM, notes, where),
        drift_mm=_clamped("drift_mm", fitted["drift_mm"], 0.0, MAX_MM, notes, where),
        drift_frames=_clamped("drift_frames", fitted["drift_frames"], 1.0, MAX_DRIFT_FRAMES, notes, where),
        white_mm=_clamped("white_mm", fitted["white_mm"], 0.0, MAX_MM, notes, where),
        deg_per_mm=_clamped("deg_per_mm", fitted["deg_per_mm"], 0.0, MAX_DEG_PER_MM, notes, where),
    )


def _fit_all(
    position_mm: np.ndarray, orientation_deg: np.ndarray, episode: np.ndarray, frame: np.ndarray, args: tuple
) -> tuple[dict[str, Any], float | None]:
    """Every object's :func:`fit_object`, the tools' together (one set of sizes for both, fitted to both
    tools' episodes as episodes of their own), and the depth factor of all three objects together (the
    position's variance along the axis over across)."""
    objects = {
        name: fit_object(position_mm[:, o], orientation_deg[:, o], episode, frame, *args)
        for o, name in enumerate(OBJECTS)
    }
    _, ep = np.unique(episode, return_inverse=True)
    both = np.concatenate([ep, ep + ep.max() + 1])
    tools = [OBJECTS.index("grasping_tool"), OBJECTS.index("regrasping_tool")]
    pos = np.concatenate([position_mm[:, t] for t in tools])
    rot = np.concatenate([orientation_deg[:, t] for t in tools])
    objects["tools"] = fit_object(pos, rot, both, np.concatenate([frame] * 2), *args)
    along = sum(objects[n]["series"]["along"][p] for n in OBJECTS for p in ("bias", "drift", "white"))
    across = sum(objects[n]["series"]["across"][p] for n in OBJECTS for p in ("bias", "drift", "white"))
    return objects, _ratio(along, across)


def _bootstrap(errors: FrameErrors, args: tuple, n: int, seed: int) -> dict[str, Any]:
    """The 5th and 95th percentiles of the preset's sizes (needle, tools; unclamped) and of the depth
    factor over ``n`` refits to the episodes resampled with replacement."""
    rng = np.random.default_rng(seed)
    ids, ep = np.unique(errors.episode, return_inverse=True)
    rows = [np.flatnonzero(ep == i) for i in range(len(ids))]
    draws: dict[str, list[float]] = {}
    for _ in range(n):
        pick = rng.integers(0, len(ids), len(ids))
        idx = np.concatenate([rows[i] for i in pick])
        new_ep = np.repeat(np.arange(len(pick)), [len(rows[i]) for i in pick])
        try:
            objects, depth = _fit_all(
                errors.position_mm[idx], errors.orientation_deg[idx], new_ep, errors.frame[idx], args
            )
        except FitError:  # a resample without the pairs a fit needs
            continue
        for name in ("needle", "tools"):
            for key, value in objects[name]["tracking"].items():
                draws.setdefault(f"{name}.{key}", []).append(value)
        draws.setdefault("depth_factor", []).append(math.nan if depth is None else depth)
    out: dict[str, Any] = {"resamples": n, "fitted": len(draws.get("depth_factor", [])), "seed": seed}
    for key, values in draws.items():
        v = np.asarray(values, np.float64)
        v = v[np.isfinite(v)]
        out[key] = [float(np.percentile(v, 5)), float(np.percentile(v, 95))] if v.size else None
    return out


def fit(
    errors: FrameErrors,
    motion_frames: float = MOTION_FRAMES,
    max_lag: int | None = None,
    bootstrap: int = 0,
    source: str | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """The fit file's content (strict JSON once written): ``preset`` (the model's sizes:
    :func:`~regrasp_mjx.envs.camera_presets.fitted` reads them), each object's :func:`fit_object` and the
    tools' together, with ``bootstrap`` resamples of the episodes the preset's sizes' 90 % intervals
    (``interval``), the notes on what was clamped and what the model leaves out, and what was measured.

    Raises:
      FitError: errors not of held-out frames, too few frames, or a motion_frames that is no positive number.
    """
    if not (isinstance(motion_frames, (int, float)) and math.isfinite(motion_frames) and motion_frames > 0):
        raise FitError(f"motion_frames={motion_frames!r} is not accepted: a positive number of the loop's frames")
    if errors.meta.get("held_out") is not True:
        raise FitError("these errors are not of held-out frames (the training frames' seed): not fitted")
    frames_per_episode = int(errors.meta.get("data", {}).get("frames") or errors.frame.max() + 1)
    args = (frames_per_episode, motion_frames, max_lag)
    objects, depth_ratio = _fit_all(errors.position_mm, errors.orientation_deg, errors.episode, errors.frame, args)
    interval = _bootstrap(errors, args, bootstrap, seed) if bootstrap else None
    notes: list[str] = []
    needle = _tracking(objects["needle"]["tracking"], "needle", notes)
    tool = _tracking(objects["tools"]["tracking"], "tools", notes)
    depth = _clamped("depth_factor", depth_ratio, 1.0, MAX_DEPTH_FACTOR, notes, "all objects")
    camera = CameraErrors(needle, tool, depth)
    for name, row in objects.items():
        lost = row["failed_rate"] + row["gross_rate"]
        if lost > LOST_NOTED:
            notes.append(
                f"{name}: {100 * lost:.1f} % of the frames left out (no pose, or over {GROSS_MM:g} mm off): the fit "
                "describes the rest, smaller errors than the estimator's whole"
            )
        if row["drift_frames_at_bound"]:
            notes.append(
                f"{name}: the correlation time is at its bound ({row['tracking']['drift_frames']:.4g} of the loop's "
                f"frames): a drift this slow or fast is not told apart from the bias or the white part by "
                f"{frames_per_episode} frames an episode"
            )
    notes += [
        "each object is fitted alone: errors correlated between the objects (one picture shows them all) are "
        "drawn independently by the model",
        "the drift here follows the pose along the tool's motion; the model's fades with time even while the "
        "tool holds still (warm-up, looking)",
        f"failed fits and errors over {GROSS_MM:g} mm are left out (their rates per object above); the model has none",
        "one deg_per_mm and one depth factor hold every part (each part's own ratio is in the object's row), and "
        "the orientation error is isotropic in the model",
    ]
    return {
        "format": FIT_FORMAT,
        "version": FIT_VERSION,
        "preset": {
            "needle": dataclasses.asdict(camera.needle),
            "tools": dataclasses.asdict(camera.tools),
            "depth_factor": camera.depth_factor,
        },
        "interval": interval,
        "objects": objects,
        "notes": notes,
        "method": (
            "per axis: second moment about zero S0 = B + D + W, within-episode semivariogram "
            "gamma(L) = W + D (1 - exp(-L / tau)) at lags 1..k, weighted least squares, one tau per object "
            "(position across, along, orientation); B = S0 - D - W (regrasp_mjx.vision.error_fit)"
        ),
        "motion_frames": motion_frames,
        "frames_per_episode": frames_per_episode,
        "max_lag": max_lag or frames_per_episode - 1,
        "measured": {k: v for k, v in errors.meta.items() if k not in ("format", "version", "objects")},
        "source": source,
        "fitted": {"date": time.strftime("%Y-%m-%d"), "machine": machine(devices=False)},
    }


def markdown(result: dict[str, Any]) -> list[str]:
    """The fit as a table: each object's sizes (the preset's rows marked) and its parts."""
    m = result["measured"]
    data = m.get("data", {})
    lines = [
        f"Camera-error model fitted to {m.get('estimator', '?')} on {data.get('path', '?')} (seed "
        f"{data.get('seed', '?')}, {data.get('episodes', '?')} episodes x {result['frames_per_episode']} frames); "
        f"drift_frames in the loop's frames ({result['motion_frames']:g} from start to goal). Preset: depth factor "
        f"{result['preset']['depth_factor']:g}.",
        "",
        "| object | bias mm | drift mm | drift frames | white mm | deg per mm | depth factor | rotation RMS deg "
        "(bias / drift / white) | failed / gross |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]

    def num(x):
        return "-" if x is None else f"{x:.3g}"

    for name, row in result["objects"].items():
        t, r = row["tracking"], row["rotation_rms_deg"]
        mark = " (preset)" if name in ("needle", "tools") else ""
        lines.append(
            f"| {name}{mark} | {t['bias_mm']:.3f} | {t['drift_mm']:.3f} | {t['drift_frames']:.3g} | "
            f"{t['white_mm']:.3f} | {num(t['deg_per_mm'])} | {num(row['depth_factor'])} | "
            f"{r['bias']:.2f} / {r['drift']:.2f} / {r['white']:.2f} | "
            f"{row['failed_rate']:.3f} / {row['gross_rate']:.3f} |"
        )
    interval = result.get("interval")
    if interval:
        cells = [f"{key} {v[0]:.3g}-{v[1]:.3g}" for key, v in interval.items() if isinstance(v, list)]
        lines += ["", f"90 % intervals over {interval['fitted']} resamples of the episodes: " + ", ".join(cells) + "."]
    return lines + [""] + [f"- {n}" for n in result["notes"]]
