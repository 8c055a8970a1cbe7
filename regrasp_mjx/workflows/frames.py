"""Labelled stereo frames of the endoscope: left and right RGB, depth and segmentation of a batch of episode
states, with the true poses, each camera's intrinsics and extrinsics, and the task's keypoints projected
into both images with their visibility.

:class:`FrameRenderer` draws with MuJoCo's own OpenGL renderer, headless, on the CPU or a GPU, one
picture at a time: the context comes from :mod:`regrasp_mjx.workflows.render` (EGL by default, or
``MUJOCO_GL``), which raises :class:`~regrasp_mjx.workflows.render.RenderUnavailable` where none can be
made. Each camera is drawn twice, as ``mujoco.Renderer`` does: once lit (the RGB image) and once with
geom ids as colours (segmentation), whose depth buffer gives the depth. Depth is linear, metres along
each camera's optical axis (OpenCV's camera z). The batched GPU path through MuJoCo Warp is
:mod:`regrasp_mjx.workflows.frames_mjx`.

Each episode's picture is randomised by its seed (:mod:`regrasp_mjx.world.domain_randomisation`):
the same seed gives the same pictures and labels, bit for bit, on one machine.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import mujoco
import numpy as np

from regrasp_mjx.core.config import JAW_MAX_DEG, SceneConfig
from regrasp_mjx.workflows.render import Offscreen, _gl_context  # the package's one way to make a headless GL context
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.endoscope_scene import CLASSES, OBJECT_CLASS, RENDER_GROUPS, EndoscopeModel, endoscope_model
from regrasp_mjx.world.scene import Scene


@dataclasses.dataclass(frozen=True)
class LabelledFrames:
    """A batch of labelled stereo frames: ``B`` episode states, camera 0 the left, 1 the right.

    Attributes:
      rgb: ``[B, 2, H, W, 3]`` uint8, blurred, gained and noised as each episode's draws say.
      depth: ``[B, 2, H, W]`` float32, metres along each camera's optical axis.
      segmentation: ``[B, 2, H, W]`` int8, an index into :data:`CLASSES` per pixel.
      intrinsics: ``[3, 3]``, both cameras' matrix K (OpenCV: pixel centres at integers).
      extrinsics: ``[B, 2, 4, 4]``, world (e_g) to camera, OpenCV axes (x right, y down, z forward).
      poses: ``[B, 3, 7]``: the needle, the grasping tool and the regrasping tool in e_g.
      keypoints: ``[B, K, 3]`` in e_g, named by ``names``.
      pixels: ``[B, 2, K, 2]`` (u, v) in each image; keypoint_depth ``[B, 2, K]`` their camera z (m).
      visible: ``[B, 2, K]`` bool (:func:`regrasp_mjx.world.endoscope.visible`).
      names: the keypoints' names; seeds ``[B]``: each episode's randomisation seed; draws: its draws.
    """

    rgb: np.ndarray
    depth: np.ndarray
    segmentation: np.ndarray
    intrinsics: np.ndarray
    extrinsics: np.ndarray
    poses: np.ndarray
    keypoints: np.ndarray
    pixels: np.ndarray
    keypoint_depth: np.ndarray
    visible: np.ndarray
    names: tuple[str, ...]
    seeds: np.ndarray
    draws: dr.Draws

    def camera_poses(self, camera: int = 0) -> np.ndarray:
        """The three objects' poses ``[B, 3, 4, 4]`` in one camera's frame (OpenCV axes)."""
        rot = endoscope.quat_matrix(self.poses[..., 3:])
        obj = np.zeros(self.poses.shape[:2] + (4, 4))
        obj[..., :3, :3], obj[..., :3, 3], obj[..., 3, 3] = rot, self.poses[..., :3], 1.0
        return self.extrinsics[:, camera, None] @ obj


def _poses(name: str, poses: Any) -> np.ndarray:
    p = np.atleast_2d(np.asarray(poses, np.float64))
    if p.ndim != 2 or p.shape[1] != 7 or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite poses [B, 7] ([x, y, z, qw, qx, qy, qz]), got shape {p.shape}")
    if not np.allclose(np.linalg.norm(p[:, 3:], axis=1), 1.0, atol=1e-6):
        raise ValueError(f"{name}'s quaternions must have unit norm")
    return p


def label(
    endo: EndoscopeModel,
    kp: endoscope.Keypoints,
    needle: np.ndarray,
    ee: np.ndarray,
    extrinsics: np.ndarray,
    depth: np.ndarray,
    segmentation: np.ndarray,
    jaw_deg: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The keypoints' labels for rendered depth and segmentation ``[B, 2, H, W]``: their places in
    e_g ``[B, K, 3]``, pixels ``[B, 2, K, 2]``, depths ``[B, 2, K]`` and visibility ``[B, 2, K]``; the
    regrasping jaws' tips where jaws opened to ``jaw_deg`` ``[B]`` put them (None: the scene's opening)."""
    turn = None if jaw_deg is None else np.radians(np.asarray(jaw_deg, np.float64) - endo.base_jaw_deg) / 2.0
    world = kp.world(needle, ee, turn)
    pixels, z = endoscope.project(world[:, None], extrinsics, endo.rig.intrinsics())
    want = OBJECT_CLASS[kp.obj]
    seen = endoscope.visible(pixels, z, depth, segmentation, want, kp.depth_slack)
    return world, pixels, z, seen


def labelled(
    endo: EndoscopeModel,
    kp: endoscope.Keypoints,
    needle: np.ndarray,
    ee: np.ndarray,
    extrinsics: np.ndarray,
    pictures: tuple[np.ndarray, np.ndarray, np.ndarray],
    seeds: Any,
    draws: Any,
    jaw_deg: np.ndarray | None = None,
) -> LabelledFrames:
    """:class:`LabelledFrames` of rendered ``pictures`` (RGB, depth, segmentation) with their labels
    (:func:`label`), whichever renderer made them."""
    rgb, depth, seg = pictures
    world, pixels, z, seen = label(endo, kp, needle, ee, extrinsics, depth, seg, jaw_deg)
    return LabelledFrames(
        rgb=rgb,
        depth=depth,
        segmentation=seg,
        intrinsics=endo.rig.intrinsics(),
        extrinsics=extrinsics,
        poses=endoscope.object_poses(needle, ee),
        keypoints=world,
        pixels=pixels,
        keypoint_depth=z,
        visible=seen,
        names=kp.names,
        seeds=np.asarray(seeds).copy(),
        draws=jax.tree.map(np.asarray, draws),
    )


class FrameRenderer(Offscreen):
    """Labelled stereo frames of one scene through MuJoCo's OpenGL renderer; a context manager (or
    call :meth:`close`).

    Args:
      scene: a loaded :class:`Scene`, a :class:`SceneConfig` or None (the default scene).
      rig: the stereo pair and image size (default :class:`~regrasp_mjx.world.endoscope.Rig`).

    Raises:
      RenderUnavailable: no OpenGL context can be made here.
    """

    def __init__(self, scene: Scene | SceneConfig | None = None, rig: endoscope.Rig | None = None):
        self.endo = endoscope_model(scene, rig)
        self.model, self.rig = self.endo.model, self.endo.rig
        self.keypoints = endoscope.keypoints(self.endo.scene)
        w, h = self.rig.width, self.rig.height
        self._ctx, self._con = _gl_context(self.model, w, h)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scn = mujoco.MjvScene(self.model, maxgeom=500)
        self._opt = mujoco.MjvOption()
        self._opt.geomgroup[:] = [int(g in RENDER_GROUPS) for g in range(len(self._opt.geomgroup))]
        self._opt.sitegroup[:] = 0
        self._data = mujoco.MjData(self.model)
        self._rect = mujoco.MjrRect(0, 0, w, h)
        self._pert = mujoco.MjvPerturb()
        self._cams = []
        for cam_id in self.endo.cameras:
            cam = mujoco.MjvCamera()
            cam.type, cam.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, cam_id
            self._cams.append(cam)

    def _shoot(self, cam: mujoco.MjvCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One camera's RGB ``[H, W, 3]``, depth ``[H, W]`` (m) and classes ``[H, W]``, rows top down."""
        m, scn, h, w = self.model, self._scn, self.rig.height, self.rig.width
        mujoco.mjv_updateScene(m, self._data, self._opt, self._pert, cam, int(mujoco.mjtCatBit.mjCAT_ALL), scn)
        rgb = np.empty((h, w, 3), np.uint8)
        mujoco.mjr_render(self._rect, scn, self._con)
        mujoco.mjr_readPixels(rgb, None, self._rect, self._con)
        scn.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = scn.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        try:
            ids = np.empty((h, w, 3), np.uint8)
            buf = np.empty((h, w), np.float32)
            mujoco.mjr_render(self._rect, scn, self._con)
            mujoco.mjr_readPixels(ids, buf, self._rect, self._con)
        finally:
            scn.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = scn.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = False
        # segment ids (1 + the scene geom's index; 0 nothing) to geom classes
        seg = ids[..., 0].astype(np.int64) + (ids[..., 1].astype(np.int64) << 8) + (ids[..., 2].astype(np.int64) << 16)
        lookup = np.zeros(scn.ngeom + 1, np.int8)
        for g in scn.geoms[: scn.ngeom]:
            if g.segid >= 0 and g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lookup[g.segid + 1] = self.endo.classes[g.objid]
        classes = lookup[np.clip(seg, 0, scn.ngeom)]
        return rgb[::-1], _linear_depth(buf, m)[::-1], classes[::-1]  # OpenGL's rows run bottom-up

    def render(
        self, needle: Any, ee: Any, seeds: Any, frame: int = 0, degrade: bool = True, jaw_deg: Any = None
    ) -> LabelledFrames:
        """Labelled frames of ``B`` episode states.

        Args:
          needle, ee: the needle and the regrasping end-effector, ``[B, 7]`` (or one ``[7]``) in e_g.
          seeds: one randomisation seed per state (``[B]`` ints, or one int for all): the camera's
            jitter, the light, the materials and the image's blur, gain and noise.
          frame: which frame of its episode each picture is (a new noise draw per frame; the rest is
            the episode's).
          degrade: False leaves out the blur, gain and noise (the rendered pixels as they are).
          jaw_deg: the regrasping jaws' opening each state draws, degrees (``[B]``, or one number for
            all; None: the scene's, ``SceneConfig.jaw_angle_deg``): the jaws turned about their hinge
            as the environment opens them, their tips' labels with them.

        Raises:
          ValueError: poses that are not finite 7-vectors with unit quaternions, bad seeds, or an
            opening that is not a number of degrees in (0, JAW_MAX_DEG].
          RuntimeError: the renderer is closed.
        """
        if self._ctx is None:
            raise RuntimeError("this FrameRenderer is closed")
        needle, ee = _poses("needle", needle), _poses("ee", ee)
        if needle.shape != ee.shape:
            raise ValueError(f"needle and ee must have the same number of poses, got {len(needle)} and {len(ee)}")
        seeds = np.broadcast_to(np.atleast_1d(np.asarray(seeds)), (len(needle),))
        jaws = None if jaw_deg is None else _openings(jaw_deg, len(needle))
        draws = dr.draws(seeds)
        b, h, w = len(needle), self.rig.height, self.rig.width
        rgb = np.empty((b, 2, h, w, 3), np.uint8)
        depth = np.empty((b, 2, h, w), np.float32)
        seg = np.empty((b, 2, h, w), np.int8)
        extrinsics = np.empty((b, 2, 4, 4))
        self._ctx.make_current()
        for i in range(b):
            extrinsics[i] = endoscope.invert(self.endo.apply(draws.row(i)))
            self._data.qpos[:] = self.endo.qpos(needle[i], ee[i])
            self.endo.open_jaws(None if jaws is None else jaws[i])
            mujoco.mj_kinematics(self.model, self._data)
            mujoco.mj_camlight(self.model, self._data)
            for c, cam in enumerate(self._cams):
                rgb[i, c], depth[i, c], seg[i, c] = self._shoot(cam)
        if degrade:
            d = draws
            rgb = np.asarray(dr.degrade(rgb, d.blur_px, d.noise, d.gain, dr.noise_keys(seeds, frame)))
        return labelled(self.endo, self.keypoints, needle, ee, extrinsics, (rgb, depth, seg), seeds, draws, jaws)


def _openings(jaw_deg: Any, n: int) -> np.ndarray:
    """``jaw_deg`` (one number or ``[n]``) as ``[n]`` float64 degrees; raises ValueError unless each is in
    (0, JAW_MAX_DEG]."""
    try:
        jaws = np.broadcast_to(np.atleast_1d(np.asarray(jaw_deg, np.float64)), (n,))
    except (TypeError, ValueError):
        raise ValueError(f"jaw_deg must be one opening or one per state ({n}) in degrees, got {jaw_deg!r}") from None
    if not np.all((jaws > 0.0) & (jaws <= JAW_MAX_DEG)):
        raise ValueError(f"jaw_deg must be in (0, {JAW_MAX_DEG:g}] degrees (the jaw's range), got {jaw_deg!r}")
    return jaws.copy()


def _linear_depth(buf: np.ndarray, model: mujoco.MjModel) -> np.ndarray:
    """Metric depth from a reversed-Z depth buffer (``mjDEPTH_ZEROFAR``), as ``mujoco.Renderer`` computes
    it: the perspective matrix's terms in float32 (as glFrustum has them), the division in float64."""
    extent = model.stat.extent
    near, far = np.float32(model.vis.map.znear * extent), np.float32(model.vis.map.zfar * extent)
    c = -(far + near) / (far - near)
    d = -(np.float32(2) * far * near) / (far - near)
    c, d = np.float32(-0.5) * c - np.float32(0.5), np.float32(-0.5) * d
    return (d / (buf.astype(np.float64) + c)).astype(np.float32)


__all__ = ["CLASSES", "FrameRenderer", "LabelledFrames", "label"]
