"""Training the estimator: the host loop over epochs of :mod:`regrasp_mjx.vision.training`'s jitted program,
validated each epoch on held-out frames (another seed), a progress line per epoch (losses, pixel and
pose errors, pairs per second, ETA), an atomic checkpoint after each epoch (a killed run resumes from
it: the same command again), and the epoch best on validation exported as an estimator file
(``OUT/estimator``), its rows in ``OUT/log.jsonl``.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import MutableMapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.atomic import dumps, write_text
from regrasp_mjx.core.host_loop import eta, folder_lock
from regrasp_mjx.vision import layout as kp_layout
from regrasp_mjx.vision import pose_errors
from regrasp_mjx.vision.estimator_file import save_estimator
from regrasp_mjx.vision.network import WIDTHS, NetConfig
from regrasp_mjx.vision.training import (
    CheckpointError,
    init_state,
    keypoints_in_batches,
    load_checkpoint,
    make_epoch,
    make_keypoints,
    optimizer,
    save_checkpoint,
    targets,
)
from regrasp_mjx.workflows.frame_dataset import DatasetError, FrameDataset, load_dataset

EVAL_BATCH = 32  # stereo pairs per call when validating
DETERMINISTIC = "--xla_gpu_deterministic_ops=true"  # a GPU's convolutions' gradients without atomics


def deterministic_gpu(environ: MutableMapping[str, str] = os.environ) -> str:
    """Adds :data:`DETERMINISTIC` to ``XLA_FLAGS`` unless it names that flag already, so that on a GPU a
    seed gives the same numbers run after run (cuDNN's fastest gradient kernels may add in any order);
    it applies only where JAX has not started its backend yet (a command line's first work). Returns
    ``XLA_FLAGS``."""
    current = environ.get("XLA_FLAGS", "")
    if DETERMINISTIC.split("=")[0] not in {w.split("=", 1)[0] for w in current.split()}:
        environ["XLA_FLAGS"] = f"{current} {DETERMINISTIC}".strip()
    return environ["XLA_FLAGS"]


@dataclasses.dataclass(frozen=True)
class Settings:
    """A training run's settings (a resumed run must have the same).

    Attributes:
      epochs: passes over the training frames.
      batch: stereo pairs per update (two images each).
      learning_rate, weight_decay: AdamW's (warm-up then cosine decay, :func:`~regrasp_mjx.vision.training.optimizer`).
      widths: the network's channels at strides 2, 4, 8, 16.
      seed: the initial weights and every epoch's order.
    """

    epochs: int = 30
    batch: int = 16
    learning_rate: float = 2e-3
    weight_decay: float = 1e-4
    widths: tuple[int, ...] = WIDTHS
    seed: int = 0

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch < 1:
            raise ValueError(f"epochs {self.epochs}, batch {self.batch}: accepted 1 or more of each")
        if not (0.0 < self.learning_rate < 1.0 and 0.0 <= self.weight_decay < 1.0):
            raise ValueError(
                f"learning_rate {self.learning_rate}, weight_decay {self.weight_decay}: accepted in (0, 1) and [0, 1)"
            )


def _pair_up(data: FrameDataset, val: FrameDataset) -> None:
    """Refuses validation frames that are not held out, or not of the training frames' images and keypoints."""
    if val.meta["seed"] == data.meta["seed"]:
        raise DatasetError(
            f"the validation frames have the training frames' seed ({data.meta['seed']}); accepted: frames of "
            "another seed (held out: other problems, other randomisation draws)"
        )
    for key in ("width", "height", "task"):
        if val.meta[key] != data.meta[key]:
            raise DatasetError(
                f"validation frames' {key} {val.meta[key]!r} differs from the training frames' {data.meta[key]!r}"
            )
    if val.meta["keypoints"] != data.meta["keypoints"] or not np.allclose(val.intrinsics, data.intrinsics):
        raise DatasetError("the validation frames' keypoints or cameras differ from the training frames'")


def validate(run, fit, params: Any, val: FrameDataset, net: NetConfig) -> dict[str, float]:
    """Median and 95th percentile pixel errors of the validation keypoints that count (in their
    image), and the median needle and tool position (mm) and orientation (deg) errors of their poses."""
    pixels, conf = keypoints_in_batches(run, params, val.rgb, EVAL_BATCH)
    counted = targets(net, val.pixels) > 0
    err = np.linalg.norm(pixels - val.pixels, axis=-1)[counted]
    turns = jaw_turns(val)
    poses = np.concatenate(
        [np.asarray(fit(jnp.asarray(p), jnp.asarray(c), jnp.asarray(t))[0]) for p, c, t in _chunks(pixels, conf, turns)]
    )
    pos, rot = pose_errors.errors(poses, val.camera_poses(0))
    pos_mm, rot_deg = np.linalg.norm(pos, axis=-1) * 1e3, np.degrees(np.linalg.norm(rot, axis=-1))
    return {
        "val_px_median": float(np.median(err)),
        "val_px_p95": float(np.percentile(err, 95)),
        "val_needle_mm": float(np.nanmedian(pos_mm[:, 0])),
        "val_needle_deg": float(np.nanmedian(rot_deg[:, 0])),
        "val_tool_mm": float(np.nanmedian(pos_mm[:, 1:])),
        "val_tool_deg": float(np.nanmedian(rot_deg[:, 1:])),
    }


def _chunks(*arrays: np.ndarray, size: int = 256):
    for i in range(0, len(arrays[0]), size):
        yield tuple(a[i : i + size] for a in arrays)


def base_jaw_deg(data: FrameDataset) -> float:
    """The regrasping jaws' opening the frames' keypoint model has [deg]."""
    return float(data.meta.get("jaws", {}).get("base_deg", kp_layout.JAW_DEG_BEFORE_OPENING))


def jaw_turns(data: FrameDataset) -> np.ndarray:
    """Each row's jaw-tip turn for the pose fit ``[N]`` (rad): half its opening beyond the model's."""
    return kp_layout.jaw_turns(data.jaw_deg, len(data.jaw_deg), base_jaw_deg(data)).astype(np.float32)


def progress_line(row: dict[str, Any], epochs: int, eta_text: str) -> str:
    return (
        f"epoch {row['epoch']}/{epochs}  loss {row['loss']:.4f} (heatmap {row['heatmap']:.3f}, offset "
        f"{row['offset']:.4f})  train {row['train_px']:.2f} px  val {row['val_px_median']:.2f} / "
        f"{row['val_px_p95']:.2f} px (median / p95)  needle {row['val_needle_mm']:.2f} mm {row['val_needle_deg']:.1f} deg  "
        f"tools {row['val_tool_mm']:.2f} mm {row['val_tool_deg']:.1f} deg  {row['pairs_per_s']:,.0f} pairs/s  {eta_text}"
    )


def _data_id(d: FrameDataset) -> dict[str, Any]:
    return {k: d.meta.get(k) for k in ("seed", "episodes", "frames", "width", "height", "task", "jaw_open")}


def train(
    data_path: str | Path, val_path: str | Path, out: str | Path, settings: Settings, log=print
) -> dict[str, Any]:
    """Trains on the frames of ``data_path``, validates on ``val_path``'s, into ``out`` (resuming from
    its checkpoint when there is one of the same settings and data).

    Returns:
      ``{"estimator": folder, "best": its epoch's row, "epochs": ...}``.

    Raises:
      DatasetError: unreadable, mismatched or not held-out frames, or too few for one batch.
      CheckpointError: ``out`` holds a checkpoint of other settings or data.
    """
    out = Path(out)
    data, val = load_dataset(data_path), load_dataset(val_path)
    _pair_up(data, val)
    keypoints = data.keypoints
    net = NetConfig(len(keypoints.names), int(data.meta["width"]), int(data.meta["height"]), tuple(settings.widths))
    steps = len(data.rgb) // settings.batch
    if steps < 1:
        raise DatasetError(f"{len(data.rgb)} training pairs are fewer than one batch of {settings.batch}")
    tx = optimizer(settings.learning_rate, steps * settings.epochs, settings.weight_decay)
    init_key, order_key = jax.random.split(jax.random.PRNGKey(settings.seed))
    state = init_state(net, tx, init_key)
    header = {"settings": dataclasses.asdict(settings) | {"widths": list(settings.widths)}, "data": _data_id(data)}
    baseline = float(data.meta["rig"]["baseline_m"])
    fit = kp_layout.pose_fit(keypoints, data.intrinsics, baseline)
    fit_batch = jax.jit(jax.vmap(fit))
    with folder_lock(out):
        history: list[dict[str, Any]] = []
        best: dict[str, Any] | None = None
        loaded = load_checkpoint(out, state)
        if loaded is not None:
            state, meta = loaded
            saved = {"settings": meta.get("settings"), "data": meta.get("data")}
            if dumps(saved, sort_keys=True) != dumps(header, sort_keys=True):
                raise CheckpointError(
                    f"{out} holds a checkpoint of other settings or data ({dumps(saved)}); accepted: the same "
                    f"options and frames to resume it ({dumps(header)}), or another --out"
                )
            history, best = meta["history"], meta["best"]
            log(f"resuming {out} after epoch {meta['epoch']}/{settings.epochs}")
        start = len(history)
        rgb, pixels = jnp.asarray(data.rgb), jnp.asarray(data.pixels, jnp.float32)
        weight = jnp.asarray(targets(net, data.pixels))
        epoch_fn, run = make_epoch(net, tx, settings.batch, steps), make_keypoints(net)
        log(
            f"train on {len(data.rgb)} pairs ({steps} updates of {settings.batch} an epoch), validate on {len(val.rgb)} "
            f"(seed {val.meta['seed']}); {jax.default_backend()}: {jax.devices()[0].device_kind}"
        )
        t_run = time.perf_counter()
        for epoch in range(start + 1, settings.epochs + 1):
            t0 = time.perf_counter()
            state, metrics = epoch_fn(state, rgb, pixels, weight, jax.random.fold_in(order_key, epoch))
            metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
            seconds = time.perf_counter() - t0
            row = {"epoch": epoch, **metrics, **validate(run, fit_batch, state.params, val, net)}
            row |= {"seconds": seconds, "pairs_per_s": steps * settings.batch / seconds}
            history.append(row)
            if best is None or row["val_px_median"] < best["val_px_median"]:
                best = row
                training = {"settings": header["settings"], "data": header["data"], "validation": _data_id(val)}
                save_estimator(
                    out / "estimator",
                    state.params,
                    net,
                    keypoints,
                    data.intrinsics,
                    baseline,
                    extra={"training": training | {"epoch": epoch, "of_epochs": settings.epochs, "row": row}},
                    jaws={"layout_deg": base_jaw_deg(data), "trained_deg": [data.jaw_deg.min(), data.jaw_deg.max()]},
                )
            save_checkpoint(out, state, {"epoch": epoch, **header, "history": history, "best": best})
            write_text(out / "log.jsonl", "".join(dumps(r) + "\n" for r in history))
            done = epoch - start
            log(progress_line(row, settings.epochs, eta(done, settings.epochs - start, time.perf_counter() - t_run)))
    return {"estimator": str(out / "estimator"), "best": best, "epochs": settings.epochs}
