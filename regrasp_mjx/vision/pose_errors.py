"""The estimator's errors as the issue asks for them: for the needle and each tool, the position and the
orientation error in the left camera's frame, each split into the part fixed per episode (its mean over
the episode's frames) and the part that changes per frame (what is left), along the camera's optical
axis and across it, with medians and 95th percentiles; and as a markdown table.

Position errors are ``p_est - p_true``; orientation errors the rotation vector of ``R_est R_true^T``,
both in the camera's frame: "along" is its z component (for a rotation: about the optical axis),
"across" the norm of its x and y components. A pose the fit could not make (not finite) is counted
as failed and left out of the statistics; so is a gross error (position off by more than
:data:`GROSS_MM`), counted as such, so that a few lost frames show as a rate rather than as tails.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from regrasp_mjx.world.endoscope import OBJECTS, quat_matrix

GROSS_MM = 5.0


def rotvec(rot: np.ndarray) -> np.ndarray:
    """Rotation vectors ``[..., 3]`` (radians) of rotation matrices ``[..., 3, 3]``."""
    cos = np.clip((np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    axis = np.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]], -1
    )
    sin = np.sin(angle)
    small = sin < 1e-6
    scale = np.where(small, 0.5, angle / (2.0 * np.where(small, 1.0, sin)))
    out = scale[..., None] * axis
    # near 180 degrees the antisymmetric part vanishes: the axis from the symmetric part
    flip = angle > np.pi - 1e-3
    if np.any(flip):
        sym = (rot[flip] + np.eye(3)) / 2.0
        col = np.argmax(np.diagonal(sym, axis1=-2, axis2=-1), axis=-1)
        ax = sym[np.arange(len(col)), :, col]
        out[flip] = angle[flip, None] * ax / np.linalg.norm(ax, axis=-1, keepdims=True)
    return out


def errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position errors ``[..., 3]`` (m) and orientation errors ``[..., 3]`` (rotation vectors, rad) of
    poses ``[..., 7]`` (both in the same frame)."""
    pos = estimate[..., :3] - truth[..., :3]
    rel = quat_matrix(estimate[..., 3:]) @ np.swapaxes(quat_matrix(truth[..., 3:]), -1, -2)
    return pos, rotvec(rel)


def frame_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every frame's position errors (mm) and orientation errors (rotation vectors, degrees) ``[N, O, 3]`` of
    poses ``[N, O, 7]`` (both in the same frame), NaN where the estimate is not finite (no pose)."""
    finite = np.all(np.isfinite(estimate), axis=-1)
    pos, rot = np.full(estimate.shape[:-1] + (3,), np.nan), np.full(estimate.shape[:-1] + (3,), np.nan)
    p, r = errors(estimate[finite], truth[finite])
    pos[finite], rot[finite] = p * 1e3, np.degrees(r)
    return pos, rot


def stats(values: np.ndarray) -> dict[str, float | None]:
    """Median and 95th percentile of the finite ``values`` (None for both where there are none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"median": None, "p95": None}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95))}


def summary(err: np.ndarray, scale: float) -> dict[str, dict[str, float | None]]:
    """Median and 95th percentile of the norm, the along-axis part (``|z|``) and the across-axis part
    (``|(x, y)|``) of errors ``[N, 3]``, times ``scale``."""
    e = np.asarray(err, np.float64) * scale
    return {
        "norm": stats(np.linalg.norm(e, axis=-1)),
        "along": stats(np.abs(e[:, 2])),
        "across": stats(np.linalg.norm(e[:, :2], axis=-1)),
    }


def split(err: np.ndarray, episode: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Errors ``[N, 3]`` of frames of ``episode`` ``[N]``: each episode's mean ``[E, 3]`` (the part
    fixed per episode) and each frame's error less its episode's mean ``[N, 3]``."""
    ids, inverse = np.unique(episode, return_inverse=True)
    counts = np.bincount(inverse, minlength=len(ids)).astype(np.float64)
    means = np.stack([np.bincount(inverse, weights=err[:, i], minlength=len(ids)) for i in range(3)], -1)
    means /= counts[:, None]
    return means, err - means[inverse]


def report(estimate: np.ndarray, truth: np.ndarray, episode: np.ndarray) -> dict[str, Any]:
    """Every object's errors: ``estimate`` and ``truth`` ``[N, O, 7]`` in the camera's frame, the frames'
    episodes ``[N]``. Per object: ``failed`` and ``gross`` rates, then ``position_mm`` and
    ``orientation_deg``, each ``total``, ``per_episode`` (the fixed part, one value per episode with
    two frames or more) and ``per_frame`` (the rest), each :func:`summary`."""
    out: dict[str, Any] = {"frames": int(len(episode)), "episodes": int(len(np.unique(episode)))}
    for o, name in enumerate(OBJECTS):
        pos, rot = errors(estimate[:, o], truth[:, o])
        finite = np.all(np.isfinite(estimate[:, o]), axis=-1)
        gross = finite & (np.linalg.norm(np.where(finite[:, None], pos, 0.0), axis=-1) * 1e3 > GROSS_MM)
        keep = finite & ~gross
        row: dict[str, Any] = {"failed": float(np.mean(~finite)), "gross": float(np.mean(gross))}
        ep = episode[keep]
        _, where, counts = np.unique(ep, return_inverse=True, return_counts=True)
        several = counts[where] >= 2
        for key, err, scale in (("position_mm", pos, 1e3), ("orientation_deg", rot, 180.0 / np.pi)):
            e = err[keep]
            fixed, per_frame = split(e[several], ep[several]) if several.any() else (np.zeros((0, 3)),) * 2
            row[key] = {
                "total": summary(e, scale),
                "per_episode": summary(fixed, scale),
                "per_frame": summary(per_frame, scale),
            }
        out[name] = row
    return out


def _cell(s: dict[str, float | None]) -> str:
    return "-" if s["median"] is None else f"{s['median']:.2f} / {s['p95']:.2f}"


def markdown(rep: dict[str, Any], title: str) -> list[str]:
    """A table of :func:`report`: one row per object and quantity, median / p95 per column."""
    lines = [
        f"# {title}",
        "",
        f"{rep['frames']} frames of {rep['episodes']} episodes; errors in the left camera's frame, median / 95th "
        f"percentile; along: the optical axis (for a rotation: about it), across: perpendicular to it; "
        f"failed: no pose; gross: off by more than {GROSS_MM:g} mm (left out of the statistics).",
        "",
        "| object | error | total | along | across | fixed per episode | along | across | per frame | along "
        "| across | failed | gross |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name in OBJECTS:
        row = rep[name]
        for key, unit in (("position_mm", "position (mm)"), ("orientation_deg", "orientation (deg)")):
            parts = [
                row[key][part][axis]
                for part in ("total", "per_episode", "per_frame")
                for axis in ("norm", "along", "across")
            ]
            rates = f"{row['failed']:.3f} | {row['gross']:.3f}"
            lines.append(f"| {name} | {unit} | " + " | ".join(_cell(p) for p in parts) + f" | {rates} |")
    return lines
