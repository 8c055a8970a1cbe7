"""Labelled stereo frames rendered in batches on the device, through MJX's MuJoCo Warp ray tracer
(``mjx.create_render_context``, ``mjx.refit_bvh``, ``mjx.render_with_segmentation``): the pictures and
labels of :mod:`regrasp_mjx.workflows.frames`, one world per episode state, without leaving the device.

Optional: it needs NVIDIA Warp (``pip install -e ".[render-gpu]"``; MJX carries its own copy of MuJoCo
Warp) and, to be fast, a CUDA GPU (Warp's CPU device works too, slowly: the tests run it there);
:class:`MjxFrameRenderer` raises :class:`RenderUnavailable` saying so where Warp is missing. Written
against mujoco 4.0.0's MJX Warp render tests (``mujoco/mjx/warp/render_test.py``): the render context
fixes the number of worlds when it is made (so does this renderer: ``nworld``), ``refit_bvh`` runs before
``render`` (mujoco#3435), and the context's arrays are not JAX arrays, so the program is one jitted
function of the whole batch, not vmapped over it.

Per call the program runs only the kinematics (``mjx.kinematics``): the poses are set, never simulated,
and the cameras and lights hang from the world body, so their places (``cam_xpos``, ``light_xpos``)
are computed once, on the host, when the renderer is made. The regrasping jaws' opening is per world:
their geoms' ``geom_pos`` and ``geom_quat`` are batched model fields, which MuJoCo Warp reads per world.

What differs from the OpenGL path, for now: one randomisation draw (``seed``) sets the lights, materials
and the cameras' pose for every world (MuJoCo Warp can vary most of them per world, but not the
headlight, which the render context bakes in; not wired here yet); the image's blur, gain and noise are
drawn per world from each state's seed, on the device. Warp's depth is planar (along the optical axis),
like the OpenGL path's; a pixel that shows nothing has depth 0 (OpenGL's: the far plane), which the
scene's tissue never leaves.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import mujoco.mjx.warp as mjxw  # imports without Warp too (then WARP_INSTALLED is False)
import numpy as np
from mujoco import mjx

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.workflows.frames import LabelledFrames, _openings, _poses, labelled
from regrasp_mjx.workflows.render import RenderUnavailable
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.endoscope_scene import CAMERAS, RENDER_GROUPS, endoscope_model
from regrasp_mjx.world.scene import Scene

INSTALL = 'pip install -e ".[render-gpu]"'


def require_warp() -> None:
    """Raises :class:`RenderUnavailable` unless MJX's Warp backend is installed."""
    if not mjxw.WARP_INSTALLED:
        raise RenderUnavailable(f"MJX's batched renderer needs NVIDIA Warp: {INSTALL}")


def _turned_jaws(
    geom_pos: jax.Array,
    geom_quat: jax.Array,
    jaw_geoms: jax.Array,
    jaw_sides: jax.Array,
    jaw_poses: jax.Array,
    turn: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """``geom_pos`` ``[N, ngeom, 3]`` and ``geom_quat`` ``[N, ngeom, 4]``: the model's, with each world's
    jaw geoms turned about the hinge (the end-effector's x axis) by ``turn`` ``[N]`` radians, away from
    each other, as :meth:`~regrasp_mjx.world.endoscope_scene.EndoscopeModel.open_jaws` turns them."""
    angle = -jaw_sides[None, :] * turn[:, None]  # [N, jaws]: about +x, the jaw on +y turns towards +y
    c, s = jnp.cos(angle), jnp.sin(angle)
    p, q = jaw_poses[None, :, :3], jaw_poses[None, :, 3:]
    pos = jnp.stack(
        [jnp.broadcast_to(p[..., 0], c.shape), c * p[..., 1] - s * p[..., 2], s * p[..., 1] + c * p[..., 2]], -1
    )
    h = angle / 2.0  # the turn's quaternion (cos h, sin h, 0, 0) times q
    ch, sh = jnp.cos(h), jnp.sin(h)
    quat = jnp.stack(
        [
            ch * q[..., 0] - sh * q[..., 1],
            ch * q[..., 1] + sh * q[..., 0],
            ch * q[..., 2] - sh * q[..., 3],
            ch * q[..., 3] + sh * q[..., 2],
        ],
        -1,
    )
    n = turn.shape[0]
    all_pos = jnp.broadcast_to(geom_pos, (n,) + geom_pos.shape).at[:, jaw_geoms].set(pos.astype(geom_pos.dtype))
    all_quat = jnp.broadcast_to(geom_quat, (n,) + geom_quat.shape).at[:, jaw_geoms].set(quat.astype(geom_quat.dtype))
    return all_pos, all_quat


def _pictures(rc, ncam: int, mx, d0, classes, jaws, turn, qpos, blur, noise, gain, keys):
    """``qpos`` ``[N, nq]`` and the jaws' turn ``[N]`` to RGB ``[N, C, H, W, 3]`` (degraded), depth
    ``[N, C, H, W]`` and classes ``[N, C, H, W]``: the kinematics, the BVH refit, one render of every
    world. ``rc`` (the render context's handle) and ``ncam`` are static; the rest are arrays."""
    geom_pos, geom_quat = _turned_jaws(mx.geom_pos, mx.geom_quat, *jaws, turn)
    per_world = jax.tree.map(lambda _: None, mx).tree_replace({"geom_pos": 0, "geom_quat": 0})
    d = jax.vmap(lambda q: d0.replace(qpos=q))(qpos)
    d = jax.vmap(mjx.kinematics, in_axes=(per_world, 0))(
        mx.tree_replace({"geom_pos": geom_pos, "geom_quat": geom_quat}), d
    )
    d = mjx.refit_bvh(mx, d, rc)
    rgb, depth, seg, _ = mjx.render_with_segmentation(mx, d, rc)
    cams = range(ncam)
    rgb = jnp.stack([mjx.get_rgb(rc, c, rgb) for c in cams], axis=1)
    rgb = jnp.round(rgb * 255.0).astype(jnp.uint8)
    depth = jnp.stack([mjx.get_depth(rc, c, depth, 1.0)[..., 0] for c in cams], axis=1)  # metres (< 1 m)
    seg = jnp.stack([mjx.get_segmentation(rc, c, seg) for c in cams], axis=1)  # geom ids, -1 nothing
    labels = classes[jnp.where(seg < 0, classes.shape[0] - 1, seg)]
    return dr.degrade(rgb, blur, noise, gain, keys), depth, labels


class MjxFrameRenderer:
    """Labelled stereo frames of ``nworld`` episode states at once, on the device.

    Args:
      nworld: the batch size, fixed when the render context is made.
      scene, rig: as :class:`~regrasp_mjx.workflows.frames.FrameRenderer`.
      seed: the randomisation draw of the lights, materials and the cameras' pose (every world).

    Raises:
      RenderUnavailable: Warp is not installed (:data:`INSTALL`).
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
        if np.any(m.cam_bodyid[list(self.endo.cameras)] != 0) or np.any(m.light_bodyid != 0):
            raise ValueError("the endoscope's cameras and lights must hang from the world body")
        # the cameras' and lights' places, once: the kinematics the program runs leaves them as they are
        host = mujoco.MjData(m)
        mujoco.mj_kinematics(m, host)
        mujoco.mj_camlight(m, host)
        self._mx = mjx.put_model(m, impl="warp")
        self._d0 = mjx.put_data(m, host, impl="warp", naconmax=0, njmax=0)
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
        self._classes = jnp.asarray(np.r_[self.endo.classes, 0], jnp.int8)  # a last entry for -1 (nothing)
        e = self.endo
        self._jaws = tuple(jnp.asarray(x) for x in (e.jaw_geoms, e.jaw_sides, e.jaw_poses))
        # one program for every call: the context's handle and the camera count are its only static inputs
        self._program = jax.jit(functools.partial(_pictures, self._ctx.pytree(), len(CAMERAS)))

    def pictures(self, qpos: Any, turn: Any, seeds: Any, frame: int = 0) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The device's part of :meth:`render`, its arrays left on the device (what a training step that
        reads frames where they are drawn takes): ``qpos`` ``[nworld, nq]`` (the endoscope model's), the
        jaws' turn ``[nworld]`` (rad, half the opening's change), a seed per world; RGB ``[N, 2, H, W, 3]``
        (degraded), depth ``[N, 2, H, W]`` and classes ``[N, 2, H, W]``."""
        # np.shape reads a device array's shape without copying it to the host
        if np.shape(qpos) != (self.nworld, self.endo.model.nq) or np.shape(turn) != (self.nworld,):
            raise ValueError(
                f"qpos {np.shape(qpos)} and turn {np.shape(turn)} are not accepted: [{self.nworld}, {self.endo.model.nq}] "
                f"and [{self.nworld}] (one per world)"
            )
        d = dr.draws(seeds)
        return self._program(
            self._mx,
            self._d0,
            self._classes,
            self._jaws,
            jnp.asarray(turn, jnp.float32),
            jnp.asarray(qpos, jnp.float32),
            d.blur_px,
            d.noise,
            d.gain,
            dr.noise_keys(seeds, frame),
        )

    def render(self, needle: Any, ee: Any, seeds: Any, frame: int = 0, jaw_deg: Any = None) -> LabelledFrames:
        """Labelled frames of exactly ``nworld`` states (``[nworld, 7]`` needle and end-effector poses,
        a seed per state for its image's blur, gain and noise, the jaws' opening per state or one for
        all, None the scene's); see :meth:`FrameRenderer.render`.

        Raises:
          ValueError: not ``nworld`` states, poses that are not finite 7-vectors with unit quaternions,
            or an opening that is not a number of degrees in (0, JAW_MAX_DEG].
        """
        needle, ee = _poses("needle", needle), _poses("ee", ee)
        if len(needle) != self.nworld or len(ee) != self.nworld:
            raise ValueError(f"this renderer draws exactly {self.nworld} states, got {len(needle)} and {len(ee)}")
        seeds = np.broadcast_to(np.atleast_1d(np.asarray(seeds)), (self.nworld,))
        jaws = None if jaw_deg is None else _openings(jaw_deg, self.nworld)
        turn = np.zeros(self.nworld) if jaws is None else np.radians(jaws - self.endo.base_jaw_deg) / 2.0
        d = dr.draws(seeds)
        qpos = np.stack([self.endo.qpos(n, e) for n, e in zip(needle, ee)])
        out = self.pictures(qpos, turn, seeds, frame)
        rgb, depth, seg = (np.asarray(x) for x in out)
        scene_draws = dr.draws(np.full(self.nworld, self.seed))  # the lights', materials' and cameras' one draw
        extrinsics = np.broadcast_to(self._extrinsics, (self.nworld, 2, 4, 4)).copy()
        draws = scene_draws.replace(blur_px=d.blur_px, noise=d.noise, gain=d.gain)
        return labelled(self.endo, self.keypoints, needle, ee, extrinsics, (rgb, depth, seg), seeds, draws, jaws)
