"""Labelled stereo frames rendered in batches on the device, through MJX's MuJoCo Warp ray tracer
(``mjx.create_render_context``, ``mjx.refit_bvh``, ``mjx.render_with_segmentation``): the pictures and
labels of :mod:`regrasp_mjx.workflows.frames`, one world per episode state, without leaving the device.

Optional: it needs ``warp-lang`` and ``mujoco-warp`` (``pip install warp-lang mujoco-warp``) and, to be
fast, a CUDA GPU; :class:`MjxFrameRenderer` raises :class:`RenderUnavailable` saying so where they are
missing. Written against mujoco 4.0.0's MJX Warp render tests (``mujoco/mjx/warp/render_test.py``):
the render context fixes the number of worlds when it is made (so does this renderer: ``nworld``),
``refit_bvh`` runs before ``render`` (mujoco#3435), and the context's arrays are not JAX arrays, so the
program is one jitted function of the batch, not vmapped over it.

What differs from the OpenGL path, for now: one randomisation draw (``seed``) sets the lights, materials
and the cameras' pose for every world (MuJoCo Warp can vary them per world; not wired here yet); the
image's blur, gain and noise are drawn per world from each state's seed, on the device. Warp's depth is
planar (along the optical axis), like the OpenGL path's.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import mujoco.mjx.warp as mjxw  # imports without Warp too (then WARP_INSTALLED is False)
import numpy as np
from mujoco import mjx

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.workflows.frames import LabelledFrames, _poses, labelled
from regrasp_mjx.workflows.render import RenderUnavailable
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.endoscope_scene import CAMERAS, RENDER_GROUPS, endoscope_model
from regrasp_mjx.world.scene import Scene

INSTALL = "pip install warp-lang mujoco-warp"


def require_warp() -> None:
    """Raises :class:`RenderUnavailable` unless MJX's Warp backend is installed."""
    if not mjxw.WARP_INSTALLED:
        raise RenderUnavailable(f"MJX's batched renderer needs NVIDIA Warp and MuJoCo Warp: {INSTALL}")


class MjxFrameRenderer:
    """Labelled stereo frames of ``nworld`` episode states at once, on the device.

    Args:
      nworld: the batch size, fixed when the render context is made.
      scene, rig: as :class:`~regrasp_mjx.workflows.frames.FrameRenderer`.
      seed: the randomisation draw of the lights, materials and the cameras' pose (every world).

    Raises:
      RenderUnavailable: Warp or MuJoCo Warp is not installed (:data:`INSTALL`).
    """

    def __init__(
        self,
        nworld: int,
        scene: Scene | SceneConfig | None = None,
        rig: endoscope.Rig | None = None,
        seed: int = 0,
    ):
        require_warp()
        if nworld < 1:
            raise ValueError(f"nworld must be >= 1, got {nworld}")
        self.nworld = int(nworld)
        self.endo = endoscope_model(scene, rig)
        self.rig, self.keypoints = self.endo.rig, endoscope.keypoints(self.endo.scene)
        self.seed = int(seed)
        self._extrinsics = endoscope.invert(self.endo.apply(dr.draws(self.seed).row(0)))
        m = self.endo.model
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)  # poses are set, never simulated: no contacts
        self._mx = mjx.put_model(m, impl="warp")
        self._ctx = mjx.create_render_context(
            mjm=m,
            nworld=self.nworld,
            cam_res=(self.rig.width, self.rig.height),
            render_rgb=True,
            render_depth=True,
            render_seg=True,
            use_textures=True,
            use_shadows=False,
            enabled_geom_groups=list(RENDER_GROUPS),
            cam_active=list(CAMERAS),
        )
        self._data = jax.vmap(lambda _: mjx.make_data(m, impl="warp"))(jnp.arange(self.nworld))
        self._classes = jnp.asarray(np.r_[self.endo.classes, 0], jnp.int8)  # a last entry for -1 (nothing)
        self._program = jax.jit(self._pictures)

    def _pictures(self, qpos: jax.Array, blur, noise, gain, keys):
        """``qpos`` ``[N, nq]`` to RGB ``[N, 2, H, W, 3]`` (degraded), depth ``[N, 2, H, W]`` and
        classes ``[N, 2, H, W]``: forward kinematics, the BVH refit, one render of every world."""
        d = jax.vmap(lambda dd, q: dd.replace(qpos=q))(self._data, qpos)
        d = jax.vmap(mjx.forward, in_axes=(None, 0))(self._mx, d)
        rc = self._ctx.pytree()
        d = mjx.refit_bvh(self._mx, d, rc)
        rgb, depth, seg, d = mjx.render_with_segmentation(self._mx, d, rc)
        cams = range(len(CAMERAS))
        rgb = jnp.stack([mjx.get_rgb(rc, c, rgb) for c in cams], axis=1)
        rgb = jnp.round(rgb * 255.0).astype(jnp.uint8)
        depth = jnp.stack([mjx.get_depth(rc, c, depth, 1.0)[..., 0] for c in cams], axis=1)  # metres (< 1 m)
        seg = jnp.stack([mjx.get_segmentation(rc, c, seg) for c in cams], axis=1)
        classes = self._classes[jnp.where(seg < 0, -1, seg)]
        return dr.degrade(rgb, blur, noise, gain, keys), depth, classes

    def render(self, needle: Any, ee: Any, seeds: Any, frame: int = 0) -> LabelledFrames:
        """Labelled frames of exactly ``nworld`` states (``[nworld, 7]`` needle and end-effector poses,
        a seed per state for its image's blur, gain and noise); see :meth:`FrameRenderer.render`."""
        needle, ee = _poses("needle", needle), _poses("ee", ee)
        if len(needle) != self.nworld or len(ee) != self.nworld:
            raise ValueError(f"this renderer draws exactly {self.nworld} states, got {len(needle)} and {len(ee)}")
        seeds = np.broadcast_to(np.atleast_1d(np.asarray(seeds)), (self.nworld,))
        d = dr.draws(seeds)
        qpos = np.stack([self.endo.qpos(n, e) for n, e in zip(needle, ee)]).astype(np.float32)
        out = self._program(jnp.asarray(qpos), d.blur_px, d.noise, d.gain, dr.noise_keys(seeds, frame))
        rgb, depth, seg = (np.asarray(x) for x in out)
        scene_draws = dr.draws(np.full(self.nworld, self.seed))  # the lights', materials' and cameras' one draw
        extrinsics = np.broadcast_to(self._extrinsics, (self.nworld, 2, 4, 4)).copy()
        draws = scene_draws.replace(blur_px=d.blur_px, noise=d.noise, gain=d.gain)
        return labelled(self.endo, self.keypoints, needle, ee, extrinsics, (rgb, depth, seg), seeds, draws)
