"""The keypoint network's training program: its state, the optimiser, one jitted epoch (a shuffled pass over
stereo pairs held on the device, ``lax.scan`` over minibatches; on the CPU a host loop of jitted updates), the keypoints of a batch of pairs, and
checkpoints (one npz of the state's leaves and a JSON header, written atomically; read back into the
state's own structure, checked leaf by leaf).

Both images of a pair are in the same minibatch (``2 B`` images through the network). An epoch's order
is a pure function of the run's seed and the epoch's number, so a run killed and resumed from its last
checkpoint takes the same steps as one that was not.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from regrasp_mjx.core.atomic import atomic_write, dumps
from regrasp_mjx.vision.losses import inside, loss, pixel_error
from regrasp_mjx.vision.network import NetConfig, decode, init_params, make_network

CHECKPOINT = "checkpoint.npz"
CHECKPOINT_FORMAT = "regrasp_mjx.estimator_checkpoint"


@struct.dataclass
class TrainState:
    """The network's parameters, the optimiser's state and the number of updates made."""

    step: jax.Array
    params: Any
    opt_state: Any


def optimizer(learning_rate: float, total_steps: int, weight_decay: float = 1e-4) -> optax.GradientTransformation:
    """AdamW with a linear warm-up over the first 5 % of the steps and a cosine decay to 1 % after,
    gradients clipped to norm 1."""
    warmup = max(1, total_steps // 20)
    schedule = optax.warmup_cosine_decay_schedule(
        0.0, learning_rate, warmup, max(total_steps, warmup + 1), end_value=0.01 * learning_rate
    )
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=weight_decay))


def init_state(net: NetConfig, tx: optax.GradientTransformation, key: jax.Array) -> TrainState:
    params = init_params(net, key)
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params))


def targets(net: NetConfig, pixels: np.ndarray) -> np.ndarray:
    """Which keypoints count in the loss ``[N, 2, K]`` (float32): those whose true pixel lies in its image."""
    return np.asarray(inside(net, jnp.asarray(pixels)), np.float32)


def make_epoch(net: NetConfig, tx: optax.GradientTransformation, batch: int, steps: int, scan: bool | None = None):
    """The epoch ``(state, rgb, pixels, weight, key) -> (state, metrics)``: ``steps`` updates of
    ``batch`` stereo pairs drawn without replacement from ``rgb`` ``[N, 2, H, W, 3]`` (uint8) with
    their keypoints ``pixels`` ``[N, 2, K, 2]`` and loss weights ``weight`` ``[N, 2, K]``; ``metrics``
    are the epoch's means (loss, its parts, the keypoints' mean pixel error where they count).

    ``scan`` (default: on any backend but the CPU) makes the epoch one jitted ``lax.scan``; without it
    each update is its own jitted call from a host loop, in the same order. Why not on the CPU: XLA:CPU
    runs convolutions inside a loop without its fast library kernels (measured: four updates of this
    network 1.3 s in a scan, 0.05 s unrolled)."""
    model = make_network(net)
    scan = jax.default_backend() != "cpu" if scan is None else scan

    def update(state: TrainState, rgb, pixels, weight):
        images = rgb.reshape((-1,) + rgb.shape[2:])
        px, w = pixels.reshape((-1,) + pixels.shape[2:]), weight.reshape((-1,) + weight.shape[2:])

        def objective(params):
            logits, offsets = model.apply(params, images)
            value, parts = loss(net, logits, offsets, px, w)
            return value, (parts, logits, offsets)

        (value, (parts, logits, offsets)), grads = jax.value_and_grad(objective, has_aux=True)(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        decoded, _ = decode(net, jax.lax.stop_gradient(logits), jax.lax.stop_gradient(offsets))
        err = (w * pixel_error(decoded, px)).sum() / jnp.maximum(w.sum(), 1.0)
        metrics = {"loss": value, "heatmap": parts["heatmap"], "offset": parts["offset"], "train_px": err}
        return TrainState(step=state.step + 1, params=params, opt_state=opt_state), metrics

    def order(key, n):
        return jax.random.permutation(key, n)[: steps * batch].reshape(steps, batch)

    def step(state, rgb, pixels, weight, idx):
        return update(state, rgb[idx], pixels[idx], weight[idx])

    def epoch(state: TrainState, rgb, pixels, weight, key):
        state, metrics = jax.lax.scan(lambda s, idx: step(s, rgb, pixels, weight, idx), state, order(key, rgb.shape[0]))
        return state, jax.tree.map(jnp.mean, metrics)

    if scan:
        return jax.jit(epoch, donate_argnums=0)
    order_jit, step_jit = jax.jit(order, static_argnums=1), jax.jit(step, donate_argnums=0)

    def host_epoch(state: TrainState, rgb, pixels, weight, key):
        rows = []
        for idx in order_jit(key, rgb.shape[0]):
            state, metrics = step_jit(state, rgb, pixels, weight, idx)
            rows.append(metrics)
        return state, jax.tree.map(lambda *xs: jnp.mean(jnp.stack(xs)), *rows)

    return host_epoch


def make_keypoints(net: NetConfig):
    """The jitted ``(params, rgb [B, 2, H, W, 3]) -> (pixels [B, 2, K, 2], confidence [B, 2, K])``."""
    model = make_network(net)

    def run(params, rgb):
        b = rgb.shape[0]
        pixels, conf = decode(net, *model.apply(params, rgb.reshape((2 * b,) + rgb.shape[2:])))
        return pixels.reshape(b, 2, net.keypoints, 2), conf.reshape(b, 2, net.keypoints)

    return jax.jit(run)


def keypoints_in_batches(run, params: Any, rgb: np.ndarray, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`make_keypoints`' program over ``rgb`` ``[N, ...]`` in batches (the last one padded)."""
    pix, conf = [], []
    for i in range(0, len(rgb), batch):
        chunk = rgb[i : i + batch]
        n = len(chunk)
        if n < batch and len(rgb) > batch:
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], batch - n, axis=0)])
        p, c = run(params, jnp.asarray(chunk))
        pix.append(np.asarray(p)[:n])
        conf.append(np.asarray(c)[:n])
    return np.concatenate(pix), np.concatenate(conf)


def save_checkpoint(folder: Path, state: TrainState, meta: dict[str, Any]) -> None:
    """``folder/checkpoint.npz``: the state's leaves and ``meta`` (JSON) in one file, written atomically."""
    leaves = jax.tree_util.tree_leaves(jax.device_get(state))
    arrays = {f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)}
    header = {"format": CHECKPOINT_FORMAT, "leaves": len(leaves), **meta}
    atomic_write(folder / CHECKPOINT, lambda f: np.savez(f, meta=np.array(dumps(header)), **arrays))


class CheckpointError(ValueError):
    """A checkpoint that cannot be read, or not of this run's network and optimiser."""


def load_checkpoint(folder: Path, template: TrainState) -> tuple[TrainState, dict[str, Any]] | None:
    """The state and meta of ``folder/checkpoint.npz`` in ``template``'s structure; None where there is
    none; a :class:`CheckpointError` for one that is unreadable or of another structure."""
    path = folder / CHECKPOINT
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta"]))
            arrays = [f[f"leaf_{i:05d}"] for i in range(int(meta["leaves"]))]
    except Exception as err:  # truncated, foreign or without its leaves
        raise CheckpointError(
            f"{path} is not a readable checkpoint ({err}); accepted: move it away to start over"
        ) from err
    leaves, treedef = jax.tree_util.tree_flatten(template)
    if meta.get("format") != CHECKPOINT_FORMAT or len(arrays) != len(leaves):
        raise CheckpointError(f"{path}: {len(arrays)} arrays, this run's state has {len(leaves)}")
    for i, (saved, want) in enumerate(zip(arrays, leaves, strict=True)):
        if saved.shape != np.shape(want) or saved.dtype != np.asarray(want).dtype:
            raise CheckpointError(f"{path}: leaf {i} is {saved.dtype}{saved.shape}, this run needs {np.shape(want)}")
    return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(a) for a in arrays]), meta
