"""Domain randomisation of the endoscope's pictures: one draw per episode of the camera's pose jitter, the
light, the materials and the image's blur, gain and noise, a pure function of the episode's seed, and
the image degradation as a JAX function of those draws.

The ranges are ours (:data:`RANGES`) but the camera's jitter, which is the calibration size of SPEC
"Errors of a lab" (:data:`regrasp_mjx.world.endoscope.CALIBRATION_MM` and ``CALIBRATION_DEG``). The
light is the endoscope's own (a light guide beside the lenses, moved a little in the image plane) and
a weak fill from a random side; the needle is polished steel, the jaws and the wrist brushed steel,
the shafts dark, the tissue pinkish red (a fixed texture, its colour drawn). :func:`nominal` is the
middle of every range without jitter, blur or noise: a reference.

Draws are made with ``jax.random`` (``draws(seeds)``: one row per seed, the same seed the same row on
every machine), so the same function serves the CPU renderer and, on the device, the batched one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from regrasp_mjx.world.endoscope import CALIBRATION_DEG, CALIBRATION_MM, VIEW_AXIS

# (low, high) of each drawn number (ours but the camera's jitter); colours are RGB in [0, 1]
RANGES: dict[str, tuple] = {
    "camera_shift_mm": (0.0, CALIBRATION_MM),  # magnitude, in a uniformly random direction
    "camera_turn_deg": (0.0, CALIBRATION_DEG),  # angle, about a uniformly random axis
    "light_offset_mm": (-10.0, 10.0),  # the endoscope's light, per image axis, from the rig's centre
    "light_diffuse": (0.5, 1.0),
    "light_specular": (0.2, 0.6),
    "fill_diffuse": (0.0, 0.3),  # a second light from a random direction on the camera's side
    "ambient": (0.05, 0.25),
    "needle_grey": (0.6, 0.9),
    "jaw_grey": (0.45, 0.75),
    "shaft_grey": (0.03, 0.2),
    "tint": (-0.04, 0.04),  # per channel, added to each metal's grey
    "needle_specular": (0.6, 1.0),
    "needle_shininess": (0.5, 1.0),
    "tissue_rgb": ((0.75, 0.35, 0.35), (0.95, 0.6, 0.55)),
    "tissue_behind_mm": (25.0, 45.0),  # the tissue plane behind the look-at point, along the optical axis
    "blur_px": (0.0, 1.0),  # Gaussian blur, standard deviation in pixels
    "noise": (0.0, 0.02),  # Gaussian noise, standard deviation as a fraction of full scale
    "gain": (0.9, 1.1),  # per channel (white balance)
}
BLUR_RADIUS = 3  # taps each side of the blur kernel: 3 sigma of the widest blur


@struct.dataclass
class Draws:
    """One episode's randomisation per row (``[B, ...]``), in SI units and RGB in [0, 1].

    Attributes:
      camera_shift: the rig's shift [m] (3); camera_rotvec: its turn about its centre [rad] (3).
      light_offset: the endoscope light's offset in the rig's x and y [m] (2); light_diffuse,
        light_specular: its brightness; fill_dir: the fill light's direction in e_g (3, unit);
        fill_diffuse: its brightness; ambient: the headlight's ambient term.
      needle_rgb, jaw_rgb, shaft_rgb, tissue_rgb: colours (3 each); needle_specular,
        needle_shininess: the needle's shine; tissue_behind: the tissue plane's distance behind
        the look-at point [m].
      blur_px, noise, gain: the image's blur (px), noise (fraction of full scale) and per-channel gain (3).
    """

    camera_shift: jax.Array
    camera_rotvec: jax.Array
    light_offset: jax.Array
    light_diffuse: jax.Array
    light_specular: jax.Array
    fill_dir: jax.Array
    fill_diffuse: jax.Array
    ambient: jax.Array
    needle_rgb: jax.Array
    jaw_rgb: jax.Array
    shaft_rgb: jax.Array
    tissue_rgb: jax.Array
    needle_specular: jax.Array
    needle_shininess: jax.Array
    tissue_behind: jax.Array
    blur_px: jax.Array
    noise: jax.Array
    gain: jax.Array

    def row(self, i) -> Draws:
        """Row ``i`` (an index, slice or mask) of a batch, as numpy arrays."""
        return jax.tree.map(lambda x: np.asarray(x)[i], self)


def _sphere(key: jax.Array) -> jax.Array:
    v = jax.random.normal(key, (3,))
    return v / jnp.linalg.norm(v)


def draw(key: jax.Array, view_axis=None) -> Draws:
    """One episode's draws from ``key`` (see :data:`RANGES`); ``view_axis`` (3, e_g) keeps the fill
    light on the camera's side (default, and what :func:`draws` uses: the default rig's
    :data:`~regrasp_mjx.world.endoscope.VIEW_AXIS`)."""
    axis = jnp.asarray(VIEW_AXIS if view_axis is None else view_axis, jnp.float32)
    axis = axis / jnp.linalg.norm(axis)
    keys = iter(jax.random.split(key, 32))  # 23 used, in this order

    def uniform(name, shape=()):
        lo, hi = RANGES[name]
        return jax.random.uniform(next(keys), shape, minval=jnp.asarray(lo), maxval=jnp.asarray(hi))

    def grey(name):
        return jnp.clip(uniform(name) + uniform("tint", (3,)), 0.0, 1.0)

    fill = _sphere(next(keys))
    fill = jnp.where(
        fill @ axis < 0, fill - 2 * (fill @ axis) * axis, fill
    )  # along the view: lit from the camera's side
    return Draws(
        camera_shift=_sphere(next(keys)) * uniform("camera_shift_mm") * 1e-3,
        camera_rotvec=_sphere(next(keys)) * jnp.radians(uniform("camera_turn_deg")),
        light_offset=uniform("light_offset_mm", (2,)) * 1e-3,
        light_diffuse=uniform("light_diffuse"),
        light_specular=uniform("light_specular"),
        fill_dir=fill,
        fill_diffuse=uniform("fill_diffuse"),
        ambient=uniform("ambient"),
        needle_rgb=grey("needle_grey"),
        jaw_rgb=grey("jaw_grey"),
        shaft_rgb=grey("shaft_grey"),
        tissue_rgb=uniform("tissue_rgb", (3,)),
        needle_specular=uniform("needle_specular"),
        needle_shininess=uniform("needle_shininess"),
        tissue_behind=uniform("tissue_behind_mm") * 1e-3,
        blur_px=uniform("blur_px"),
        noise=uniform("noise"),
        gain=uniform("gain", (3,)),
    )


@jax.jit
def _draws(seeds: jax.Array) -> Draws:
    return jax.vmap(lambda s: draw(jax.random.key(s)))(seeds)


def draws(seeds) -> Draws:
    """One row of draws per seed (``[B]`` non-negative integers, or one integer): a pure function of
    each seed alone (a row does not depend on the others)."""
    seeds = np.atleast_1d(np.asarray(seeds))
    if seeds.ndim != 1 or seeds.dtype.kind not in "iu" or np.any(seeds < 0) or np.any(seeds >= 2**31):
        raise ValueError(f"seeds must be integers in [0, 2**31), one per episode, got {seeds!r}")
    return _draws(jnp.asarray(seeds, jnp.int32))


def nominal(n: int = 1) -> Draws:
    """``n`` rows of the middle of every range, without jitter, blur or noise, unit gain and the
    fill light off: the reference picture."""

    def mid(name):
        lo, hi = RANGES[name]
        return (np.asarray(lo, np.float32) + np.asarray(hi, np.float32)) / 2

    def grey(name):
        return np.full(3, mid(name), np.float32)

    one = Draws(
        camera_shift=np.zeros(3, np.float32),
        camera_rotvec=np.zeros(3, np.float32),
        light_offset=np.zeros(2, np.float32),
        light_diffuse=mid("light_diffuse"),
        light_specular=mid("light_specular"),
        fill_dir=np.asarray([0.0, 0.0, 1.0], np.float32),
        fill_diffuse=np.float32(0.0),
        ambient=mid("ambient"),
        needle_rgb=grey("needle_grey"),
        jaw_rgb=grey("jaw_grey"),
        shaft_rgb=grey("shaft_grey"),
        tissue_rgb=mid("tissue_rgb"),
        needle_specular=mid("needle_specular"),
        needle_shininess=mid("needle_shininess"),
        tissue_behind=mid("tissue_behind_mm") * 1e-3,
        blur_px=np.float32(0.0),
        noise=np.float32(0.0),
        gain=np.ones(3, np.float32),
    )
    return jax.tree.map(lambda x: np.repeat(np.asarray(x, np.float32)[None], n, axis=0), one)


def _blur(image: jax.Array, sigma: jax.Array) -> jax.Array:
    """A separable Gaussian blur of ``image`` ``[H, W, C]`` (edges repeated); sigma 0 is none."""
    taps = jnp.arange(-BLUR_RADIUS, BLUR_RADIUS + 1, dtype=image.dtype)
    w = jnp.exp(-0.5 * (taps / jnp.maximum(sigma, 1e-3)) ** 2)
    w = w / w.sum()
    h, wd = image.shape[:2]
    r = BLUR_RADIUS
    padded = jnp.pad(image, ((r, r), (0, 0), (0, 0)), mode="edge")
    image = sum(w[i] * padded[i : i + h] for i in range(2 * r + 1))
    padded = jnp.pad(image, ((0, 0), (r, r), (0, 0)), mode="edge")
    return sum(w[i] * padded[:, i : i + wd] for i in range(2 * r + 1))


@jax.jit
def degrade(images: jax.Array, blur_px: jax.Array, noise: jax.Array, gain: jax.Array, keys: jax.Array) -> jax.Array:
    """What the endoscope's optics and sensor do to rendered images ``[B, C, H, W, 3]`` (uint8; the
    C cameras of one episode per row): a Gaussian blur of ``blur_px`` ``[B]`` pixels, a gain per
    channel ``[B, 3]``, Gaussian noise of ``noise`` ``[B]`` (fraction of full scale) drawn from each
    row's key ``keys`` ``[B]`` (:func:`noise_key`: a row's noise is its episode's alone), split per
    camera; returns uint8 of the same shape."""
    c = images.shape[1]
    x = images.astype(jnp.float32) / 255.0
    x = jax.vmap(jax.vmap(_blur, in_axes=(0, None)))(x, blur_px)
    x = x * gain[:, None, None, None, :]
    eps = jax.vmap(lambda k: jax.vmap(lambda kk: jax.random.normal(kk, images.shape[2:]))(jax.random.split(k, c)))(keys)
    x = x + noise[:, None, None, None, None] * eps
    return jnp.clip(jnp.round(x * 255.0), 0, 255).astype(jnp.uint8)


def noise_keys(seeds, frame: int = 0) -> jax.Array:
    """The keys ``[B]`` of the episodes' ``frame``-th pictures' noise: each a pure function of its
    episode's seed and the frame (a stream apart from :func:`draws`')."""
    seeds = jnp.asarray(np.atleast_1d(seeds), jnp.int32)
    return jax.vmap(lambda s: jax.random.fold_in(jax.random.fold_in(jax.random.key(s), 0x5EED), frame))(seeds)


def turn_deg(d: Draws) -> np.ndarray:
    """The camera turn's angle in degrees per row (for reports and tests)."""
    return np.degrees(np.linalg.norm(np.asarray(d.camera_rotvec), axis=-1))
