"""Estimator files: plain arrays (``estimator.npz``, the network's parameters under their flax paths) plus a
JSON contract (``estimator.json``: the network's shape, the keypoints, the stereo camera, the fit, what
it was trained on), like a policy file; and :class:`Estimator`, a loaded one, whose :meth:`~Estimator.
poses` turns stereo pairs into the needle's and the tools' poses in the left camera's frame.

No pickle: the npz is read with ``allow_pickle=False`` and every array is checked against the network
the contract describes (names, shapes, finite values); :class:`EstimatorError` says what is wrong.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from regrasp_mjx.core.atomic import atomic_write, write_json
from regrasp_mjx.core.config import JAW_MAX_DEG
from regrasp_mjx.vision import layout as kp_layout
from regrasp_mjx.vision.network import STRIDE, NetConfig, decode, init_params, make_network
from regrasp_mjx.vision.stereo import CAUCHY_PX, ITERATIONS, PoseFit
from regrasp_mjx.world.endoscope import OBJECTS, Keypoints
from regrasp_mjx.world.testsets import versions

ESTIMATOR_FORMAT = "regrasp_mjx.estimator"
ESTIMATOR_VERSION = 1
OUTPUTS = (
    "poses [B, 3, 7]: the needle (its circle's centre, the needle frame n), the grasping and the regrasping "
    "tool (their jaw pivots, frames e_g and e_r) in the left camera's frame (OpenCV: x right, y down, z along "
    "the optical axis), [x, y, z (m), qw, qx, qy, qz], qw >= 0; rms_px [B, 3]: each fit's RMS reprojection "
    "error; pixels [B, 2, K, 2] (u, v) and confidence [B, 2, K] of the keypoints, camera 0 the left"
)
# Files written before the jaws could open (no "jaws" in the contract) were made and trained at the scene's
# opening of that time, the only one they were rendered with.
OLD_JAWS = {"layout_deg": kp_layout.JAW_DEG_BEFORE_OPENING, "trained_deg": [kp_layout.JAW_DEG_BEFORE_OPENING] * 2}


class EstimatorError(ValueError):
    """An estimator file that is missing, corrupt, from another version, or not for these images."""


def save_estimator(
    out_dir: str | os.PathLike,
    params: Any,
    net: NetConfig,
    keypoints: Keypoints,
    intrinsics: np.ndarray,
    baseline_m: float,
    extra: dict[str, Any] | None = None,
    jaws: dict[str, Any] | None = None,
) -> Path:
    """Writes ``estimator.npz`` and ``estimator.json`` into ``out_dir``, each atomically (the npz first:
    a contract never names arrays that are not there). ``jaws``: ``layout_deg``, the regrasping jaws'
    opening the keypoints' model points have, and ``trained_deg``, the least and most opening the
    training frames drew (degrees); None: both the default scene's opening."""
    jaws = OLD_JAWS if jaws is None else jaws
    out = Path(out_dir)
    flat = {
        "/".join(k): np.asarray(v, np.float32) for k, v in traverse_util.flatten_dict(jax.device_get(params)).items()
    }
    contract = {
        "format": ESTIMATOR_FORMAT,
        "version": ESTIMATOR_VERSION,
        "network": {
            "keypoints": net.keypoints,
            "width": net.width,
            "height": net.height,
            "widths": list(net.widths),
            "stride": STRIDE,
            "input": "RGB uint8 [H, W, 3], rows top down, one image at a time (both of a pair through the same weights)",
        },
        "keypoints": kp_layout.to_json(keypoints),
        "camera": {
            "intrinsics": np.asarray(intrinsics, np.float64).tolist(),
            "baseline_m": float(baseline_m),
            "conventions": "a rectified pair; OpenCV axes; pixel centres at integer (u, v); the right camera on +x",
        },
        "fit": {"iterations": ITERATIONS, "cauchy_px": CAUCHY_PX},
        "jaws": {
            "layout_deg": float(jaws["layout_deg"]),
            "trained_deg": [float(d) for d in jaws["trained_deg"]],
            "meaning": "the regrasping jaws' opening of the keypoints' model points, and the least and most "
            "opening the training frames drew; poses(jaw_deg=) turns the jaw tips' model points to the commanded "
            "opening",
        },
        "outputs": OUTPUTS,
        "arrays": sorted(flat),
        "versions": versions(),
        **(extra or {}),
    }
    atomic_write(out / "estimator.npz", lambda f: np.savez(f, **flat))
    write_json(out / "estimator.json", contract)
    return out


@dataclasses.dataclass(frozen=True)
class Estimator:
    """A loaded estimator: the network's shape and parameters, its keypoints and the pose fit."""

    net: NetConfig
    params: Any
    keypoints: Keypoints
    fit: PoseFit
    contract: dict[str, Any]
    _program: Any = dataclasses.field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        net, fit = self.net, self.fit  # one jitted program per loaded estimator
        object.__setattr__(self, "_program", jax.jit(lambda params, rgb, turn: predict(net, fit, params, rgb, turn)))

    def check_images(self, rgb: Any) -> np.ndarray:
        """``rgb`` as ``[B, 2, H, W, 3]`` uint8, or a :class:`EstimatorError` saying what it is instead."""
        rgb = np.asarray(rgb)
        if rgb.ndim == 4:
            rgb = rgb[None]
        want = (2, self.net.height, self.net.width, 3)
        if rgb.ndim != 5 or rgb.shape[1:] != want or rgb.dtype != np.uint8:
            raise EstimatorError(
                f"images of shape {rgb.shape} ({rgb.dtype}) are not accepted: stereo pairs [B, {', '.join(map(str, want))}]"
                f" uint8 (this estimator was trained at {self.net.width} x {self.net.height})"
            )
        return rgb

    @property
    def layout_jaw_deg(self) -> float:
        """The regrasping jaws' opening the keypoints' model points have [deg]."""
        return float(self.contract.get("jaws", OLD_JAWS)["layout_deg"])

    @property
    def trained_jaw_deg(self) -> tuple[float, float]:
        """The least and the most opening of the regrasping jaws its training frames drew [deg]."""
        lo, hi = self.contract.get("jaws", OLD_JAWS)["trained_deg"]
        return float(lo), float(hi)

    def jaw_turns(self, jaw_deg: Any, n: int) -> np.ndarray:
        """``[n]`` turns (rad) of the jaw tips' model points for openings ``jaw_deg`` (None: the layout's;
        one number or ``[n]``, degrees in (0, JAW_MAX_DEG]); an :class:`EstimatorError` for others."""
        try:
            return kp_layout.jaw_turns(jaw_deg, n, self.layout_jaw_deg).astype(np.float32)
        except ValueError as err:
            raise EstimatorError(str(err)) from None

    def poses(self, rgb: Any, batch: int = 64, jaw_deg: Any = None) -> dict[str, np.ndarray]:
        """The poses of stereo pairs ``rgb`` ``[B, 2, H, W, 3]`` (uint8, left then right; one pair
        ``[2, H, W, 3]``): see :data:`OUTPUTS`. ``jaw_deg``: the regrasping jaws' opening in each pair
        (one number or ``[B]`` degrees; None: the layout's, :attr:`layout_jaw_deg`), what the robot
        commanded: the fit turns the jaw tips' model points there. Runs ``batch`` pairs at a time (the
        last batch padded: one compiled program for any ``B`` above it)."""
        rgb = self.check_images(rgb)
        if batch < 1:
            raise EstimatorError(f"batch={batch} is not accepted: a positive number of stereo pairs")
        turns = self.jaw_turns(jaw_deg, len(rgb))
        parts = []
        for i in range(0, len(rgb), batch):
            chunk, turn = rgb[i : i + batch], turns[i : i + batch]
            n = len(chunk)
            if n < batch and len(rgb) > batch:
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], batch - n, axis=0)])
                turn = np.concatenate([turn, np.repeat(turn[-1:], batch - n)])
            out = self._program(self.params, jnp.asarray(chunk), jnp.asarray(turn))
            parts.append({k: np.asarray(v)[:n] for k, v in out.items()})
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def predict(
    net: NetConfig, fit: PoseFit, params: Any, rgb: jax.Array, jaw_turn: jax.Array | None = None
) -> dict[str, jax.Array]:
    """The device path, a pure function: stereo pairs ``[B, 2, H, W, 3]`` through the network (both
    images in one batch), decoded to keypoints, then each pair's poses (:class:`PoseFit`), its jaw tips
    turned by ``jaw_turn`` ``[B]`` (rad; None: none)."""
    b = rgb.shape[0]
    logits, offsets = make_network(net).apply(params, rgb.reshape((2 * b,) + rgb.shape[2:]))
    pixels, confidence = decode(net, logits, offsets)
    pixels, confidence = pixels.reshape(b, 2, net.keypoints, 2), confidence.reshape(b, 2, net.keypoints)
    turn = jnp.zeros(b, pixels.dtype) if jaw_turn is None else jaw_turn
    poses, rms = jax.vmap(fit)(pixels, confidence, turn)
    return {"poses": poses, "rms_px": rms, "pixels": pixels, "confidence": confidence}


def estimator_folder(path: str | os.PathLike) -> Path:
    """The folder of an estimator: ``path`` itself, or the folder of its ``estimator.json``/``.npz``."""
    path = Path(path)
    return path.parent if path.name in ("estimator.json", "estimator.npz") else path


def load_estimator(path: str | os.PathLike) -> Estimator:
    """Reads an estimator folder (or its ``estimator.json``/``estimator.npz``) and checks it against its
    contract; an :class:`EstimatorError` says what is wrong."""
    folder = estimator_folder(path)
    js, npz = folder / "estimator.json", folder / "estimator.npz"
    if not folder.is_dir():
        raise EstimatorError(f"estimator folder not found: {path}; accepted: a folder holding estimator.json and .npz")
    for f in (js, npz):
        if not f.is_file():
            raise EstimatorError(f"estimator file not found: {f}")
    try:
        contract = json.loads(js.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise EstimatorError(f"{js} is not valid JSON: {err}") from err
    if not isinstance(contract, dict) or (contract.get("format"), contract.get("version")) != (
        ESTIMATOR_FORMAT,
        ESTIMATOR_VERSION,
    ):
        got = (contract.get("format"), contract.get("version")) if isinstance(contract, dict) else contract
        raise EstimatorError(f"{js}: {got!r}; this package reads {ESTIMATOR_FORMAT!r} version {ESTIMATOR_VERSION}")
    try:
        n = contract["network"]
        net = NetConfig(int(n["keypoints"]), int(n["width"]), int(n["height"]), tuple(int(w) for w in n["widths"]))
        if int(n["stride"]) != STRIDE:
            raise ValueError(f"stride {n['stride']}, this package's network has {STRIDE}")
        keypoints = kp_layout.from_json(contract["keypoints"])
        cam = contract["camera"]
        intrinsics = np.asarray(cam["intrinsics"], np.float64)
        baseline = float(cam["baseline_m"])
        fit_cfg = contract["fit"]
        iterations, cauchy = int(fit_cfg["iterations"]), float(fit_cfg["cauchy_px"])
        jaws = contract.get("jaws", OLD_JAWS)
        lo, hi = (float(d) for d in jaws["trained_deg"])
        layout_deg = float(jaws["layout_deg"])
        if not (0 < layout_deg <= JAW_MAX_DEG and 0 < lo <= hi <= JAW_MAX_DEG):
            raise ValueError(f"jaws: openings in (0, {JAW_MAX_DEG:g}] degrees, least before most, got {jaws!r}")
    except (KeyError, TypeError, ValueError) as err:
        raise EstimatorError(f"{js}: incomplete or invalid contract ({err})") from err
    if len(keypoints.names) != net.keypoints:
        raise EstimatorError(f"{js}: {len(keypoints.names)} keypoints named, the network has {net.keypoints}")
    good_k = intrinsics.shape == (3, 3) and np.all(np.isfinite(intrinsics)) and intrinsics[0, 0] > 0
    if not (good_k and intrinsics[1, 1] > 0 and 0 < baseline <= 0.05):
        raise EstimatorError(
            f"{js}: camera needs a finite 3 x 3 K with positive focal lengths and a baseline in (0, 0.05] m"
        )
    if not (1 <= iterations <= 100 and cauchy > 0):
        raise EstimatorError(f"{js}: fit needs 1-100 iterations and a positive cauchy_px")
    try:
        with np.load(npz, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as err:  # a truncated or foreign file: zipfile, OSError, ValueError
        raise EstimatorError(f"{npz} is not a readable estimator array file: {err}") from err
    expected = traverse_util.flatten_dict(init_params(net, jax.random.PRNGKey(0)))
    names = {"/".join(k) for k in expected}
    if set(arrays) != names or set(contract.get("arrays", [])) != names:
        missing, extra = sorted(names - set(arrays)), sorted(set(arrays) - names)
        raise EstimatorError(
            f"{npz}: arrays differ from the contract's network (missing {missing}, not expected {extra})"
        )
    params = {}
    for k, v in expected.items():
        name = "/".join(k)
        if arrays[name].shape != v.shape or arrays[name].dtype.kind != "f":
            raise EstimatorError(
                f"{npz}: {name} has shape {arrays[name].shape}, the contract's network needs {v.shape}"
            )
        if not np.all(np.isfinite(arrays[name])):
            raise EstimatorError(f"{npz}: {name} holds NaN or inf; accepted: finite weights")
        params[k] = jnp.asarray(arrays[name], jnp.float32)
    fit = kp_layout.pose_fit(keypoints, intrinsics, baseline, iterations, cauchy)
    return Estimator(net, traverse_util.unflatten_dict(params), keypoints, fit, contract)


__all__ = ["OBJECTS", "Estimator", "EstimatorError", "load_estimator", "predict", "save_estimator"]
