"""The keypoint network: a small convolutional net from one endoscope image to a heatmap and a sub-cell
offset per keypoint, and the decoding of its outputs into pixels and confidences.

Why heatmaps and offsets, not direct regression of the coordinates. Stereo turns pixels into depth at
``Z^2 / (f B)`` per pixel of disparity: 2.2 mm per pixel at the 50 mm working distance and 320 x 180
(f = 228 px, B = 5 mm), so a needle position within 0.5 mm needs keypoints to a fraction of a pixel.
A net that regresses coordinates from pooled features has to carry position through its pooling and
is known to be less precise than a dense prediction; a heatmap keeps each keypoint where it is seen
(translation equivariant), tolerates a keypoint that appears twice (the tip and the tail look alike:
the argmax picks one peak where an average would land between them) and gives a confidence for free
(the probability mass at the peak), which the pose fit uses as a weight. The heatmap is coarse (one
cell per ``stride`` x ``stride`` pixels, 4 by default) and each cell also regresses where inside it
the keypoint lies (CenterNet's offsets), so the resolution is not the cell's: the decoded pixel is
the probability-weighted mean of the 3 x 3 cells' own predictions around the peak.

Size. An encoder of 3 x 3 convolutions (``widths`` channels at strides 2, 4, 8 and 16: a stride-2
convolution into each, and a second at the same stride beyond the first), a top-down path back to stride 4 (FPN: a 1 x 1 lateral added to the upsampled coarser map, then a 3 x 3
convolution), and a 1 x 1 head of ``3 K`` channels: 0.73 GFLOP per 320 x 180 image with the default
widths (:func:`flops`; 0.33 M parameters), so that a stereo pair (two images, one batch) fits the
issue's 20 ms on one CPU core (measured 12.7 ms with the pose fit, one pinned core of a busy 2-core VM;
(16, 32, 48, 64) 12.1 ms and (32, 64, 96, 128) 15.0 ms on the same busy core) and, to be measured, 2 ms
on a GPU (``python -m regrasp_mjx.estimator bench``). Both images of
a pair go through the same weights: the network sees one image at a time, stereo enters in the fit.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

WIDTHS = (24, 48, 64, 96)
STRIDE = 4  # the heatmap's cell, in pixels (two stride-2 convolutions)


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """The network's shape: what an estimator file records and a loaded one is rebuilt from.

    Attributes:
      keypoints: K, the heatmaps (one per keypoint).
      width, height: the image size it takes (pixels).
      widths: channels at strides 2, 4, 8 and 16.
    """

    keypoints: int
    width: int
    height: int
    widths: tuple[int, ...] = WIDTHS

    def __post_init__(self) -> None:
        if self.keypoints < 1:
            raise ValueError(f"keypoints must be >= 1, got {self.keypoints}")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ValueError(f"width and height must be within [16, 4096] pixels, got {self.width} x {self.height}")
        if len(self.widths) != 4 or any(int(w) < 1 for w in self.widths):
            raise ValueError(f"widths must be 4 positive channel counts (strides 2, 4, 8, 16), got {self.widths}")

    @property
    def grid(self) -> tuple[int, int]:
        """The heatmap's rows and columns: the image's size over :data:`STRIDE`, rounded up."""
        return -(-self.height // STRIDE), -(-self.width // STRIDE)


def _conv(x: jax.Array, features: int, kernel: int = 3, stride: int = 1) -> jax.Array:
    return nn.Conv(features, (kernel, kernel), strides=(stride, stride), padding="SAME")(x)


class KeypointNet(nn.Module):
    """Images ``[N, H, W, 3]`` (uint8 or floats in [0, 255]) to heatmap logits ``[N, Gh, Gw, K]`` and
    offsets ``[N, Gh, Gw, K, 2]`` (u, v, in cells, from each cell's centre)."""

    keypoints: int
    widths: Sequence[int] = WIDTHS

    @nn.compact
    def __call__(self, images: jax.Array) -> tuple[jax.Array, jax.Array]:
        c2, c4, c8, c16 = self.widths
        x = images.astype(jnp.float32) / 255.0 - 0.5
        x = nn.relu(_conv(x, c2, stride=2))  # stride 2
        f4 = nn.relu(_conv(nn.relu(_conv(x, c4, stride=2)), c4))  # stride 4
        f8 = nn.relu(_conv(nn.relu(_conv(f4, c8, stride=2)), c8))  # stride 8
        f16 = nn.relu(_conv(nn.relu(_conv(f8, c16, stride=2)), c16))  # stride 16: the context (tip or tail)
        up = _upsample(f16, f8.shape) + _conv(f8, c16, kernel=1)
        up = nn.relu(_conv(up, c8))
        up = _upsample(_conv(up, c4, kernel=1), f4.shape) + _conv(f4, c4, kernel=1)
        up = nn.relu(_conv(up, c4))
        out = _conv(up, 3 * self.keypoints, kernel=1)
        logits = out[..., : self.keypoints]
        offsets = out[..., self.keypoints :].reshape(out.shape[:-1] + (self.keypoints, 2))
        return logits, offsets


def _upsample(x: jax.Array, like: tuple[int, ...]) -> jax.Array:
    """``x`` resized (nearest) to the rows and columns of a map of shape ``like``."""
    return jax.image.resize(x, x.shape[:1] + tuple(like[1:3]) + x.shape[3:], method="nearest")


def make_network(config: NetConfig) -> KeypointNet:
    return KeypointNet(keypoints=config.keypoints, widths=tuple(int(w) for w in config.widths))


def init_params(config: NetConfig, key: jax.Array) -> dict:
    """The network's initial parameters for images of ``config``'s size."""
    return make_network(config).init(key, jnp.zeros((1, config.height, config.width, 3), jnp.uint8))


def cell_centres(config: NetConfig) -> tuple[jax.Array, jax.Array]:
    """Each heatmap cell's centre in pixels: columns' ``u`` ``[Gw]`` and rows' ``v`` ``[Gh]`` (a cell
    covers the pixels ``STRIDE * j`` to ``STRIDE * j + STRIDE - 1``)."""
    gh, gw = config.grid
    return STRIDE * jnp.arange(gw) + (STRIDE - 1) / 2.0, STRIDE * jnp.arange(gh) + (STRIDE - 1) / 2.0


def decode(config: NetConfig, logits: jax.Array, offsets: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Pixels ``[N, K, 2]`` (u, v) and confidences ``[N, K]`` of the network's outputs.

    The peak cell of each keypoint's heatmap (softmax over the cells), then the mean of the 3 x 3 cells
    around it, each its own centre plus its offset, weighted by their probabilities; the confidence is
    the probability mass of those 9 cells (near 1 for one sharp peak, low for a keypoint the net does
    not find, or finds in two places)."""
    n, gh, gw, k = logits.shape
    prob = jax.nn.softmax(logits.reshape(n, gh * gw, k), axis=1).reshape(n, gh, gw, k)
    peak = jnp.argmax(logits.reshape(n, gh * gw, k), axis=1)  # [N, K]
    row, col = peak // gw, peak % gw
    du, dv = jnp.meshgrid(jnp.arange(-1, 2), jnp.arange(-1, 2))
    rows = jnp.clip(row[..., None] + dv.ravel(), 0, gh - 1)  # [N, K, 9]
    cols = jnp.clip(col[..., None] + du.ravel(), 0, gw - 1)
    inside = (row[..., None] + dv.ravel() == rows) & (col[..., None] + du.ravel() == cols)
    image, kp = jnp.arange(n)[:, None, None], jnp.arange(k)[None, :, None]
    p = jnp.where(inside, prob[image, rows, cols, kp], 0.0)
    off = offsets[image, rows, cols, kp]  # [N, K, 9, 2]
    us, vs = cell_centres(config)
    u = us[cols] + STRIDE * off[..., 0]
    v = vs[rows] + STRIDE * off[..., 1]
    mass = p.sum(-1)
    weight = p / jnp.maximum(mass[..., None], 1e-12)
    return jnp.stack([(weight * u).sum(-1), (weight * v).sum(-1)], axis=-1), mass


def flops(config: NetConfig) -> float:
    """Multiply-adds times two of one image through the network (convolutions only)."""
    c2, c4, c8, c16 = config.widths
    k = config.keypoints
    size = lambda s: -(-config.height // s) * -(-config.width // s)  # noqa: E731
    macs = size(2) * 27 * c2
    macs += size(4) * (9 * c2 * c4 + 9 * c4 * c4 + c4 * c4 + 9 * c4 * c4 + c4 * 3 * k)
    macs += size(8) * (9 * c4 * c8 + 9 * c8 * c8 + c8 * c16 + 9 * c16 * c8 + c8 * c4)
    macs += size(16) * (9 * c8 * c16 + 9 * c16 * c16)
    return 2.0 * macs
