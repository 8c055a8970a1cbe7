"""Poses from keypoints seen by a rectified stereo pair: triangulation, a rigid fit of each object's known
points (the needle's arc from its radius, the tools' jaws and wrists) to the triangulated ones, then the
fit refined on the pixels themselves. Pure JAX functions of arrays, for one stereo pair (``vmap`` them
over a batch).

Frames: everything is in the left camera's frame (OpenCV: x right, y down, z along the optical axis),
the right camera ``right_from_left`` from it (a rectified pair: ``[I | (-B, 0, 0)]``). Poses are
7-vectors ``[x, y, z, qw, qx, qy, qz]`` (metres; ``qw >= 0``).

Why the fit is refined on the pixels. Triangulated points are ``Z / B`` = 10 times less certain along
the optical axis than across it (at 50 mm with a 5 mm baseline), so a least-squares fit in 3-D
(:func:`kabsch`, the start) weighs the worst axis as much as the best. Minimising the reprojection
error in both images (:func:`refine`, a few Levenberg-Marquardt steps on the pose) weighs each axis by
what the pixels say about it; a Cauchy loss (scale :data:`CAUCHY_PX`) keeps one keypoint found in the
wrong place (a tip taken for the tail) from dragging the pose, and each keypoint counts as much as the
network's confidence in it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from regrasp_mjx.core.geometry import canonical_quat
from regrasp_mjx.world.distances import turn_jaws

ITERATIONS = 8  # Levenberg-Marquardt steps of the refinement
CAUCHY_PX = 2.0  # the robust loss's scale: residuals beyond a few pixels count less and less
MIN_WEIGHT = 1e-6  # a keypoint's least weight, so that a fit of unseen points stays defined


def rectified(baseline_m: float) -> np.ndarray:
    """The right camera from the left one, ``[4, 4]``, for a rectified pair ``baseline_m`` apart
    (the right camera on the left one's +x)."""
    out = np.eye(4)
    out[0, 3] = -float(baseline_m)
    return out


def project(points: jax.Array, k: jax.Array, camera_from_left: jax.Array) -> jax.Array:
    """Pixels ``[..., 2]`` of points ``[..., 3]`` (left camera frame) in a camera ``camera_from_left``."""
    cam = points @ camera_from_left[:3, :3].T + camera_from_left[:3, 3]
    z = cam[..., 2]
    return jnp.stack([k[0, 0] * cam[..., 0] / z + k[0, 2], k[1, 1] * cam[..., 1] / z + k[1, 2]], axis=-1)


def triangulate(uv_left: jax.Array, uv_right: jax.Array, k: jax.Array, right_from_left: jax.Array) -> jax.Array:
    """The points ``[..., 3]`` (left camera frame, metres) seen at pixels ``uv_left`` and ``uv_right``
    ``[..., 2]``: the least-squares solution of the four linear equations the two cameras give
    (``(R_0 - x R_2) . X = x t_2 - t_0`` and its ``y`` twin per camera, ``x, y`` the normalised image
    coordinates), exact for pixels that are exact projections."""
    eye = jnp.eye(4, dtype=right_from_left.dtype)
    rows, rhs = [], []
    for uv, cam in ((uv_left, eye), (uv_right, right_from_left)):
        rot, t = cam[:3, :3], cam[:3, 3]
        x = (uv[..., 0] - k[0, 2]) / k[0, 0]
        y = (uv[..., 1] - k[1, 2]) / k[1, 1]
        rows += [rot[0] - x[..., None] * rot[2], rot[1] - y[..., None] * rot[2]]
        rhs += [x * t[2] - t[0], y * t[2] - t[1]]
    a, b = jnp.stack(rows, axis=-2), jnp.stack(rhs, axis=-1)  # [..., 4, 3], [..., 4]
    ata = jnp.einsum("...ki,...kj->...ij", a, a)
    atb = jnp.einsum("...ki,...k->...i", a, b)
    return jnp.linalg.solve(ata, atb[..., None])[..., 0]


def kabsch(model: jax.Array, observed: jax.Array, weights: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The rotation ``[3, 3]`` and translation ``[3]`` that carry ``model`` points ``[M, 3]`` onto
    ``observed`` ones (``observed ~ R model + t``) with the least weighted squared error (Kabsch;
    ``weights`` ``[M]``, a proper rotation)."""
    w = jnp.maximum(weights, MIN_WEIGHT)
    w = w / w.sum()
    mc, oc = w @ model, w @ observed
    h = (model - mc).T @ (w[:, None] * (observed - oc))
    u, _, vt = jnp.linalg.svd(h)
    d = jnp.sign(jnp.linalg.det(vt.T @ u.T))
    rot = vt.T @ jnp.diag(jnp.array([1.0, 1.0, 1.0]).at[2].set(d)) @ u.T
    return rot, oc - rot @ mc


def _residuals(delta, rot, t, model, uv, k, cams):
    """Reprojection residuals ``[2, M, 2]`` (pixels) of the pose turned by ``delta[:3]`` (radians, in
    the left camera's frame) and moved by ``delta[3:]`` (millimetres: both columns of the Jacobian of
    a similar size)."""
    turned = jaxlie.SO3.exp(delta[:3]).as_matrix() @ rot
    points = model @ turned.T + t + 1e-3 * delta[3:]
    return jnp.stack([project(points, k, cams[c]) - uv[c] for c in range(2)])


def refine(
    rot: jax.Array,
    t: jax.Array,
    model: jax.Array,
    uv: jax.Array,
    weights: jax.Array,
    k: jax.Array,
    right_from_left: jax.Array,
    iterations: int = ITERATIONS,
    scale_px: float = CAUCHY_PX,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The pose ``(rot, t)`` of ``model`` points ``[M, 3]`` refined to their pixels ``uv`` ``[2, M, 2]``
    (left, right) with per-pixel ``weights`` ``[2, M]``: Levenberg-Marquardt on the weighted Cauchy
    loss of the reprojection errors, a step kept only where it lowers the loss.

    Returns:
      ``(rot, t, rms_px)``: the refined pose and the weighted RMS reprojection error (pixels).
    """
    cams = jnp.stack([jnp.eye(4, dtype=right_from_left.dtype), right_from_left])
    w = jnp.maximum(weights, MIN_WEIGHT)
    c2 = scale_px**2

    def cost(r):
        return (w * c2 * jnp.log1p((r**2).sum(-1) / c2)).sum()

    def step(_, state):
        rot, t, lam = state
        zero = jnp.zeros(6, rot.dtype)
        r = _residuals(zero, rot, t, model, uv, k, cams)
        jac = jax.jacfwd(_residuals)(zero, rot, t, model, uv, k, cams).reshape(-1, 6)
        # iteratively reweighted: the Cauchy loss's weight at each pixel's current residual
        irls = jnp.repeat((w / (1.0 + (r**2).sum(-1) / c2)).reshape(-1), 2)
        hess = jac.T @ (irls[:, None] * jac)
        grad = jac.T @ (irls * r.reshape(-1))
        damped = hess + lam * jnp.diag(jnp.diag(hess)) + 1e-9 * jnp.eye(6)
        delta = -jnp.linalg.solve(damped, grad)
        rot_new = jaxlie.SO3.exp(delta[:3]).as_matrix() @ rot
        t_new = t + 1e-3 * delta[3:]
        better = cost(_residuals(zero, rot_new, t_new, model, uv, k, cams)) < cost(r)
        better = better & jnp.all(jnp.isfinite(delta))
        return (
            jnp.where(better, rot_new, rot),
            jnp.where(better, t_new, t),
            jnp.where(better, lam / 3.0, lam * 4.0),
        )

    rot, t, _ = jax.lax.fori_loop(0, iterations, step, (rot, t, jnp.asarray(1e-3, rot.dtype)))
    r = _residuals(jnp.zeros(6, rot.dtype), rot, t, model, uv, k, cams)
    rms = jnp.sqrt((w * (r**2).sum(-1)).sum() / w.sum())
    return rot, t, rms


def pose_vector(rot: jax.Array, t: jax.Array) -> jax.Array:
    """``[x, y, z, qw, qx, qy, qz]`` of a rotation matrix and a translation (``qw >= 0``)."""
    return jnp.concatenate([t, canonical_quat(jaxlie.SO3.from_matrix(rot).wxyz)])


@dataclasses.dataclass(frozen=True)
class PoseFit:
    """Each object's pose from its keypoints in a stereo pair.

    Attributes:
      local: every keypoint in its object's frame ``[K, 3]`` (m), in the network's order.
      rows: each object's keypoint indices (:func:`regrasp_mjx.vision.layout.object_rows`).
      intrinsics: both cameras' ``K`` ``[3, 3]``.
      right_from_left: the right camera from the left one ``[4, 4]`` (:func:`rectified`).
      iterations, scale_px: the refinement's steps and its Cauchy scale.
      tips: the keypoints fixed on the regrasping jaws (their tips), which turn about the hinge as
        the jaws open (:func:`regrasp_mjx.world.endoscope.turn_open`); ``local`` has them at the
        opening the layout was made at.
    """

    local: np.ndarray
    rows: tuple[tuple[int, ...], ...]
    intrinsics: np.ndarray
    right_from_left: np.ndarray
    iterations: int = ITERATIONS
    scale_px: float = CAUCHY_PX
    tips: tuple[int, ...] = ()

    def __call__(
        self, pixels: jax.Array, confidence: jax.Array, jaw_turn: jax.Array | float = 0.0
    ) -> tuple[jax.Array, jax.Array]:
        """One stereo pair's keypoints ``[2, K, 2]`` (left, right) and confidences ``[2, K]`` to each
        object's pose ``[O, 7]`` in the left camera's frame and its RMS reprojection error ``[O]`` (px).
        Keypoints that do not determine a pose (all on one pixel, no disparity) give NaN. ``jaw_turn``
        (rad, traced: one program for every opening): how far each regrasping jaw is turned open beyond
        the layout's opening (half the opening's change), what the robot commanded: the jaw tips'
        model points turned with it, so an opened jaw is not fitted as a turned tool.

        The objects are fitted as one batch (``vmap``; one compiled fit): each object's keypoints padded
        to the most any object has by repeating its first one with no weight."""
        most = max(len(r) for r in self.rows)
        idx = np.array([list(r) + [r[0]] * (most - len(r)) for r in self.rows])  # [O, M]
        real = np.array([[1.0] * len(r) + [0.0] * (most - len(r)) for r in self.rows])
        k = jnp.asarray(self.intrinsics, pixels.dtype)
        cams = jnp.asarray(self.right_from_left, pixels.dtype)
        local = jnp.asarray(self.local, pixels.dtype)
        if self.tips:  # each tip turns with its own jaw: +y jaw a, -y jaw b (as the environment's capsules)
            tips = np.asarray(self.tips)
            sides = jnp.asarray(np.sign(self.local[tips, 1]), pixels.dtype)
            local = local.at[tips].set(turn_jaws(local[tips], sides, jnp.asarray(jaw_turn, pixels.dtype)))
        model = local[idx]  # [O, M, 3]
        uv = jnp.moveaxis(pixels[:, idx], 0, 1)  # [O, 2, M, 2]
        w = jnp.moveaxis(confidence[:, idx], 0, 1) * jnp.asarray(real, pixels.dtype)[:, None]  # [O, 2, M]

        def one(model, uv, w):
            points = triangulate(uv[0], uv[1], k, cams)
            rot, t = kabsch(model, points, jnp.minimum(w[0], w[1]))
            rot, t, err = refine(rot, t, model, uv, w, k, cams, self.iterations, self.scale_px)
            return pose_vector(rot, t), err

        return jax.vmap(one)(model, uv, w)
