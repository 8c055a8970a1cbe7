"""The oracle estimator: the learned estimator's keypoints taken from the true poses instead of a network
(projected into both cameras, :func:`regrasp_mjx.world.endoscope.project`), then the same triangulation
and pose fit (:class:`regrasp_mjx.vision.stereo.PoseFit`). A reference for the loop from pixels and for
tests: with no error added it returns the true poses (to the fit's float32 rounding); with a bias or
noise on the pixels it shows what a keypoint error of that size does to the poses, through the same
geometry as the learned estimator.

    oracle = OracleEstimator.of(rig)  # or OracleEstimator.of(rig, bias_px=b, noise_px=0.3, seed=0)
    out = oracle.estimate(poses, extrinsics)  # poses [B, 3, 7] in e_g, extrinsics [B, 2, 4, 4] world to camera
    out["poses"]  # [B, 3, 7] in the left camera's frame, as Estimator.poses gives them

Every keypoint counts fully (confidence 1), seen or hidden: the oracle knows where each one is.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.vision import layout as kp_layout
from regrasp_mjx.vision.stereo import PoseFit
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.endoscope import OBJECTS, Keypoints, Rig
from regrasp_mjx.world.scene import Scene, load_scene

_PROGRAMS: dict = {}  # (rig, keypoint names, their local points) -> (PoseFit, its jitted batch)


class OracleError(ValueError):
    """Bad settings or inputs of an :class:`OracleEstimator`."""


def _bias(bias_px: Any, k: int) -> np.ndarray:
    try:
        bias = np.broadcast_to(np.asarray(0.0 if bias_px is None else bias_px, np.float64), (2, k, 2)).copy()
    except ValueError:
        raise OracleError(
            f"bias_px of shape {np.shape(bias_px)} is not accepted: pixels broadcastable to [2, {k}, 2] "
            "(camera, keypoint, u/v)"
        ) from None
    if not np.all(np.isfinite(bias)) or np.abs(bias).max(initial=0.0) > 100.0:
        raise OracleError("bias_px is not accepted: finite pixels, at most 100 in size")
    return bias


@dataclasses.dataclass(frozen=True, eq=False)
class OracleEstimator:
    """Keypoints from the true poses, the learned estimator's fit (see the module docstring).

    Attributes:
      keypoints: the estimator's keypoints (:func:`regrasp_mjx.vision.layout.layout`).
      rig: the stereo pair (its intrinsics and baseline; the image size bounds nothing here).
      bias_px: ``[2, K, 2]``, added to every frame's pixels (camera, keypoint, u/v): a fixed error.
      noise_px: the standard deviation of Gaussian noise added to each pixel coordinate of each frame.
      seed: the noise's seed (each call draws the next frames' noise from it).
      layout_jaw_deg: the regrasping jaws' opening the keypoints were made at [deg].
    """

    keypoints: Keypoints
    rig: Rig
    bias_px: np.ndarray
    noise_px: float = 0.0
    seed: int = 0
    layout_jaw_deg: float = SceneConfig().jaw_angle_deg
    fit: PoseFit = dataclasses.field(init=False, repr=False)
    _program: Any = dataclasses.field(init=False, repr=False)
    _calls: list = dataclasses.field(init=False, repr=False)

    def __post_init__(self) -> None:
        key = (self.rig, self.keypoints.names, self.keypoints.local.tobytes())
        if key not in _PROGRAMS:  # one jitted fit for every oracle of one rig and layout
            fit = kp_layout.pose_fit(self.keypoints, self.rig.intrinsics(), self.rig.baseline_m)
            _PROGRAMS[key] = (fit, jax.jit(jax.vmap(fit)))
        object.__setattr__(self, "fit", _PROGRAMS[key][0])
        object.__setattr__(self, "_program", _PROGRAMS[key][1])
        object.__setattr__(self, "_calls", [0])

    @classmethod
    def of(
        cls,
        rig: Rig | None = None,
        scene: Scene | None = None,
        bias_px: Any = None,
        noise_px: float = 0.0,
        seed: int = 0,
    ) -> OracleEstimator:
        """The oracle of ``scene``'s keypoints (default: the default scene) seen by ``rig`` (default
        :class:`~regrasp_mjx.world.endoscope.Rig`); ``bias_px`` broadcastable to ``[2, K, 2]`` (None:
        none). Raises :class:`OracleError` on bad settings."""
        scene = scene if scene is not None else load_scene()
        kp = kp_layout.layout(scene)
        if not (np.isfinite(noise_px) and 0.0 <= noise_px <= 100.0):
            raise OracleError(f"noise_px={noise_px!r} is not accepted: pixels in [0, 100]")
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool):
            raise OracleError(f"seed={seed!r} is not accepted: an integer")
        bias = _bias(bias_px, len(kp.names))
        return cls(kp, rig or Rig(), bias, float(noise_px), int(seed), float(scene.config.jaw_angle_deg))

    def rows(self, name: str) -> np.ndarray:
        """The keypoints of object ``name`` (one of :data:`~regrasp_mjx.world.endoscope.OBJECTS`), a
        ``[K]`` mask (to build a ``bias_px`` for one object)."""
        if name not in OBJECTS:
            raise OracleError(f"object {name!r} is not accepted: one of {OBJECTS}")
        return self.keypoints.obj == OBJECTS.index(name)

    def jaw_turns(self, jaw_deg: Any, n: int) -> np.ndarray:
        """``[n]`` turns (rad) of the jaw tips beyond the layout's for openings ``jaw_deg`` (None: the
        layout's; one number or ``[n]`` degrees in (0, JAW_MAX_DEG])."""
        try:
            return kp_layout.jaw_turns(jaw_deg, n, self.layout_jaw_deg)
        except ValueError as err:
            raise OracleError(str(err)) from None

    def pixels(self, poses: Any, extrinsics: Any, jaw_deg: Any = None) -> np.ndarray:
        """The keypoints' true pixels ``[B, 2, K, 2]`` of objects at ``poses`` ``[B, 3, 7]`` (the needle,
        the grasping tool, the regrasping tool in e_g; the grasping tool must be e_g itself) seen by
        cameras ``extrinsics`` ``[B, 2, 4, 4]`` (world to camera), the regrasping jaws opened to
        ``jaw_deg`` (None: the layout's opening)."""
        poses, extrinsics = np.asarray(poses, np.float64), np.asarray(extrinsics, np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (3, 7) or extrinsics.shape != (len(poses), 2, 4, 4):
            raise OracleError(
                f"poses {poses.shape} and extrinsics {extrinsics.shape} are not accepted: [B, 3, 7] and [B, 2, 4, 4]"
            )
        if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(extrinsics))):
            raise OracleError("poses and extrinsics must be finite")
        if not np.allclose(poses[:, 1], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], atol=1e-9):
            raise OracleError("the grasping tool's pose must be e_g itself (the identity): poses are in e_g")
        turn = None if jaw_deg is None else self.jaw_turns(jaw_deg, len(poses))
        world = self.keypoints.world(poses[:, 0], poses[:, 2], turn)
        uv, _ = endoscope.project(world[:, None], extrinsics, self.rig.intrinsics())
        return uv

    def estimate(self, poses: Any, extrinsics: Any, keys: Any = None, jaw_deg: Any = None) -> dict[str, np.ndarray]:
        """The objects' poses as the oracle sees them: the true pixels (:meth:`pixels`) plus ``bias_px``
        and noise, triangulated and fitted. ``keys`` ``[B, 2]`` integers (an episode's seed and the
        frame's number, say) key each row's noise with :attr:`seed`, so a frame's noise does not depend
        on the rows beside it (None: each call draws the next noise of :attr:`seed`). Returns what
        :meth:`regrasp_mjx.vision.estimator_file.Estimator.poses` returns: ``poses`` ``[B, 3, 7]`` in
        the left camera's frame, ``rms_px`` ``[B, 3]``, ``pixels`` ``[B, 2, K, 2]``, ``confidence``
        ``[B, 2, K]`` (ones). ``jaw_deg``: the regrasping jaws' opening (one or ``[B]`` degrees; None:
        the layout's), where the keypoints are and what the fit is told, as the learned estimator is."""
        uv = self.pixels(poses, extrinsics, jaw_deg) + self.bias_px
        if self.noise_px and keys is None:
            uv = uv + np.random.default_rng([self.seed, self._calls[0]]).normal(0.0, self.noise_px, uv.shape)
            self._calls[0] += 1
        elif self.noise_px:
            keys = np.asarray(keys)
            if keys.shape != (len(uv), 2) or keys.dtype.kind not in "iu" or (keys < 0).any():
                raise OracleError(f"keys of shape {keys.shape} are not accepted: [{len(uv)}, 2] integers >= 0")
            for i, (a, b) in enumerate(keys):
                uv[i] += np.random.default_rng([self.seed, int(a), int(b)]).normal(0.0, self.noise_px, uv.shape[1:])
        conf = np.ones(uv.shape[:-1], np.float32)
        turn = jnp.asarray(self.jaw_turns(jaw_deg, len(uv)), jnp.float32)
        out, rms = self._program(jnp.asarray(uv, jnp.float32), jnp.asarray(conf), turn)
        return {"poses": np.asarray(out, np.float64), "rms_px": np.asarray(rms), "pixels": uv, "confidence": conf}
