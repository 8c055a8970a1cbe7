"""The keypoint network's loss: each keypoint's heatmap against a Gaussian around its true pixel (a
cross-entropy over the cells), and the offsets of the 3 x 3 cells around it against where it lies
from each one's centre (L1, in cells); and the pixel error of decoded keypoints.

Which keypoints count: every one whose true pixel lies inside the image, seen or hidden. A hidden
keypoint (a jaw tip behind the other tool, an arc point under the grasping jaws) still has a place
the rest of the picture implies, and the pose fit needs most of them; the confidence that
:func:`regrasp_mjx.vision.network.decode` reports is what lets the fit trust a guess less.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from regrasp_mjx.vision.network import STRIDE, NetConfig, cell_centres

SIGMA_CELLS = 0.75  # the target heatmap's Gaussian, in cells
OFFSET_WEIGHT = 1.0  # the offsets' L1 (cells) beside the heatmap's cross-entropy


def inside(config: NetConfig, pixels: jax.Array) -> jax.Array:
    """``[..., K]``: whether each pixel ``[..., K, 2]`` lies in the image (pixel centres at integers)."""
    u, v = pixels[..., 0], pixels[..., 1]
    return (u >= -0.5) & (u < config.width - 0.5) & (v >= -0.5) & (v < config.height - 0.5)


def loss(
    config: NetConfig, logits: jax.Array, offsets: jax.Array, pixels: jax.Array, weight: jax.Array
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The mean loss over the images' keypoints and its parts.

    Args:
      config: the network's shape.
      logits, offsets: the network's outputs for ``N`` images, ``[N, Gh, Gw, K]`` and ``[N, Gh, Gw, K, 2]``.
      pixels: the true ``(u, v)`` ``[N, K, 2]``.
      weight: ``[N, K]``, 1 for a keypoint that counts (in the image), 0 for one that does not.

    Returns:
      ``(loss, {"heatmap": ..., "offset": ...})``.
    """
    n, gh, gw, k = logits.shape
    us, vs = cell_centres(config)
    # the target: a Gaussian over the cells around the true pixel, normalised over the grid
    du = (us[None, None, :, None] - pixels[:, None, None, :, 0]) / STRIDE  # [N, 1, Gw, K]
    dv = (vs[None, :, None, None] - pixels[:, None, None, :, 1]) / STRIDE  # [N, Gh, 1, K]
    target = jnp.exp(-0.5 * (du**2 + dv**2) / SIGMA_CELLS**2)
    target = target / jnp.maximum(target.sum(axis=(1, 2), keepdims=True), 1e-12)
    logp = jax.nn.log_softmax(logits.reshape(n, gh * gw, k), axis=1).reshape(n, gh, gw, k)
    heatmap = -(target * logp).sum(axis=(1, 2))  # [N, K]
    # the offsets of the 3 x 3 cells around the true one: each says where the keypoint is from its centre
    near = (jnp.abs(du) <= 1.5) & (jnp.abs(dv) <= 1.5)  # [N, Gh, Gw, K]
    err = jnp.abs(offsets[..., 0] + du) + jnp.abs(offsets[..., 1] + dv)
    offset = (near * err).sum(axis=(1, 2)) / jnp.maximum(near.sum(axis=(1, 2)), 1)
    total = jnp.maximum(weight.sum(), 1.0)
    parts = {"heatmap": (weight * heatmap).sum() / total, "offset": (weight * offset).sum() / total}
    return parts["heatmap"] + OFFSET_WEIGHT * parts["offset"], parts


def pixel_error(predicted: jax.Array, pixels: jax.Array) -> jax.Array:
    """The distance ``[..., K]`` in pixels between decoded and true keypoints ``[..., K, 2]``."""
    return jnp.linalg.norm(predicted - pixels, axis=-1)
