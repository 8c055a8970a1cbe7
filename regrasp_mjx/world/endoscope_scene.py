"""The scene as the endoscope sees it: a model for pictures only, built from the task's MJCF with the
stereo camera pair, the endoscope's light, materials and a tissue background added.

It is a model of its own, compiled from the same file with the same :class:`SceneConfig` applied
(through ``MjSpec``): the collision scene that the environment, the planners and the policies use
(:func:`regrasp_mjx.world.scene.load_scene`, identified in a policy file by its ``SceneConfig``) is
neither changed nor rebuilt. What is added is visual only: the tissue plane has
``contype = conaffinity = 0`` and geom group :data:`TISSUE_GROUP`, outside the collision geoms'
groups 0 and 3. The MJCF's own lights and its ``overview`` camera are left out, so the endoscope's
cameras are cameras 0 and 1. Offscreen multisampling is off: the segmentation pass encodes geom
ids as colours, which multisampling would blend at edges.

Segmentation classes (:data:`CLASSES`) are per geom: the needle, each tool (by body), the tissue;
pixels that show nothing are ``background``. Per-episode randomisation (:mod:`domain_randomisation`)
is written into the model's arrays by :meth:`EndoscopeModel.apply` before each episode's pictures.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.domain_randomisation import Draws, nominal
from regrasp_mjx.world.scene import (
    MJCF_PATH,
    NEEDLE_BODY,
    REGRASP_BODY,
    REGRASP_JAWS,
    Scene,
    _apply_config,
    load_scene,
)

CAMERAS = ("endoscope_left", "endoscope_right")
CLASSES = ("background", "tissue", "needle", "grasping_tool", "regrasping_tool")
OBJECT_CLASS = np.array([2, 3, 4])  # the class of each of endoscope.OBJECTS
GRASP_BODY = "grasp_tool"
TISSUE_GROUP = 1  # the MJCF's collision geoms are in groups 0 and 3, its visual meshes in 2
RENDER_GROUPS = (0, 1, 2)  # what the pictures show: not group 3 (the jaws' and needle's collision capsules)
NEAR_M, FAR_M = 0.002, 0.5  # clipping planes: nothing nearer the camera, the tissue well inside
TISSUE_HALF_M = 0.15
TEXTURE_SIZE, TEXTURE_SEED = 256, 0
# the materials of each visual geom (by name prefix); the MJCF's own colours mark objects for plots
MATERIALS = {"needle_visual": "endo_needle", "_jaw_": "endo_jaw", "_wrist": "endo_jaw", "_shaft": "endo_shaft"}


def _tissue_texture() -> np.ndarray:
    """A fixed 256 x 256 RGB texture: smooth blotches and fine grain, light (the material's colour,
    drawn per episode, tints it)."""
    rng = np.random.default_rng(TEXTURE_SEED)
    n = TEXTURE_SIZE
    f = np.fft.fftfreq(n)
    radius = np.hypot(f[:, None], f[None, :])
    field = np.zeros((n, n))
    for scale, weight in ((0.02, 1.0), (0.08, 0.35), (0.3, 0.12)):
        spectrum = np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-((radius / scale) ** 2))
        part = np.real(np.fft.ifft2(spectrum))
        field += weight * part / part.std()
    field = (field - field.min()) / (field.max() - field.min())
    rgb = np.stack([0.78 + 0.22 * field, 0.62 + 0.38 * field, 0.62 + 0.38 * field], axis=-1)
    return np.round(rgb * 255).astype(np.uint8)


@dataclasses.dataclass(frozen=True, eq=False)
class EndoscopeModel:
    """The picture model and the names in it, resolved once.

    Attributes:
      model: the ``MjModel`` (mutable: :meth:`apply` writes an episode's randomisation into it).
      scene: the collision scene it was built beside (its ``qpos`` layout is the same).
      rig: the stereo pair; the cameras' ``fovy`` matches its size.
      cameras: the two camera ids (left, right).
      classes: the segmentation class of each geom (an index into :data:`CLASSES`).
      jaw_geoms: the regrasping jaws' geoms (their meshes and capsules); jaw_sides ``[n]``: +1 jaw a
        (towards +y), -1 jaw b; jaw_poses ``[n, 7]``: their ``geom_pos`` and ``geom_quat`` at the
        scene's opening, what :meth:`open_jaws` turns about the hinge.
    """

    model: mujoco.MjModel
    scene: Scene
    rig: endoscope.Rig
    cameras: tuple[int, int]
    classes: np.ndarray
    jaw_geoms: np.ndarray
    jaw_sides: np.ndarray
    jaw_poses: np.ndarray

    @property
    def base_jaw_deg(self) -> float:
        """The scene's opening of the regrasping jaws [deg] (``SceneConfig.jaw_angle_deg``)."""
        return float(self.scene.config.jaw_angle_deg)

    def open_jaws(self, jaw_deg: float | None = None) -> None:
        """Draws the regrasping jaws at an opening of ``jaw_deg`` [deg] (None: the scene's): each jaw's
        geoms turned about the hinge (the end-effector's x axis) by half the change from the scene's
        opening, away from the other, as the environment turns their capsules; written into the model's
        ``geom_pos`` and ``geom_quat`` (the next kinematics places them)."""
        m = self.model
        pos, quat = self.jaw_poses[:, :3], self.jaw_poses[:, 3:]
        turn = 0.0 if jaw_deg is None else np.radians(float(jaw_deg) - self.base_jaw_deg) / 2.0
        if turn == 0.0:
            m.geom_pos[self.jaw_geoms], m.geom_quat[self.jaw_geoms] = pos, quat
            return
        for g, side, p, q in zip(self.jaw_geoms, self.jaw_sides, pos, quat):
            angle = -side * turn  # about +x: the jaw on +y turns towards +y
            c, s = np.cos(angle), np.sin(angle)
            m.geom_pos[g] = [p[0], c * p[1] - s * p[2], s * p[1] + c * p[2]]
            mujoco.mju_mulQuat(m.geom_quat[g], np.array([np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0]), q)

    def qpos(self, needle: np.ndarray, ee: np.ndarray) -> np.ndarray:
        """``qpos`` for a needle pose and a regrasping end-effector pose (7-vectors, e_g)."""
        return self.scene.qpos(needle[:3], needle[3:], ee[:3], ee[3:])

    def apply(self, d: Draws) -> np.ndarray:
        """Writes one episode's draws (one row, numpy) into the model: the cameras' poses, the lights,
        the materials and the tissue's place. Returns both cameras' poses ``[2, 4, 4]`` (camera to
        e_g, OpenCV axes) as the model now has them."""
        m, rig = self.model, self.rig
        poses = endoscope.camera_poses(rig, d.camera_shift, d.camera_rotvec)
        for cam, pose in zip(self.cameras, poses):
            m.cam_pos[cam] = pose[:3, 3]
            mujoco.mju_mat2Quat(m.cam_quat[cam], (pose[:3, :3] @ np.diag([1.0, -1.0, -1.0])).ravel())
        rot, centre = poses[0, :3, :3], poses[:, :3, 3].mean(axis=0)
        look_at = centre + rig.working_distance_m * rot[:, 2]  # where the jittered rig looks
        key, fill = m.light("endoscope_light").id, m.light("fill_light").id
        m.light_pos[key] = centre + rot[:, :2] @ d.light_offset
        m.light_dir[key] = endoscope.unit(look_at - m.light_pos[key])
        m.light_diffuse[key] = d.light_diffuse
        m.light_specular[key] = d.light_specular
        m.light_dir[fill] = -d.fill_dir
        m.light_pos[fill] = look_at + 0.1 * d.fill_dir
        m.light_diffuse[fill] = d.fill_diffuse
        m.vis.headlight.ambient[:] = d.ambient
        for name, rgb in (("endo_needle", d.needle_rgb), ("endo_jaw", d.jaw_rgb), ("endo_shaft", d.shaft_rgb)):
            m.mat_rgba[m.material(name).id, :3] = rgb
        m.mat_rgba[m.material("endo_tissue").id, :3] = d.tissue_rgb
        needle = m.material("endo_needle").id
        m.mat_specular[needle], m.mat_shininess[needle] = d.needle_specular, d.needle_shininess
        tissue = m.geom("tissue").id
        axis = endoscope.unit(np.asarray(rig.view_axis, np.float64))
        m.geom_pos[tissue] = np.asarray(rig.look_at_m) + d.tissue_behind * axis
        return poses


def _add(spec: mujoco.MjSpec, rig: endoscope.Rig) -> None:
    """The endoscope's additions to the scene's spec (see the module docstring)."""
    for light in list(spec.lights):
        spec.delete(light)
    for cam in list(spec.cameras):
        spec.delete(cam)
    world = spec.worldbody
    for name in CAMERAS:
        world.add_camera(name=name, fovy=rig.fovy_deg)
    world.add_light(name="endoscope_light", castshadow=False, attenuation=[1.0, 0.0, 0.0])
    world.add_light(name="fill_light", castshadow=False)
    spec.add_material(name="endo_needle", rgba=[0.8, 0.8, 0.82, 1.0], specular=0.9, shininess=0.8, reflectance=0.0)
    spec.add_material(name="endo_jaw", rgba=[0.6, 0.6, 0.62, 1.0], specular=0.6, shininess=0.5)
    spec.add_material(name="endo_shaft", rgba=[0.1, 0.1, 0.11, 1.0], specular=0.3, shininess=0.3)
    tex = _tissue_texture()
    texture = spec.add_texture(
        name="tissue", type=mujoco.mjtTexture.mjTEXTURE_2D, width=tex.shape[1], height=tex.shape[0], nchannel=3
    )
    texture.data = tex.tobytes()
    tissue = spec.add_material(name="endo_tissue", rgba=[0.85, 0.47, 0.45, 1.0], specular=0.15, shininess=0.2)
    tissue.texrepeat = [6.0, 6.0]
    roles = list(tissue.textures)
    roles[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "tissue"
    tissue.textures = roles
    axis = endoscope.unit(np.asarray(rig.view_axis, np.float64))
    quat = np.zeros(4)
    mujoco.mju_quatZ2Vec(quat, -axis)  # the plane's normal (its z) towards the camera
    world.add_geom(
        name="tissue",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[TISSUE_HALF_M, TISSUE_HALF_M, 0.001],
        quat=quat,
        material="endo_tissue",
        contype=0,
        conaffinity=0,
        group=TISSUE_GROUP,
    )
    for geom in spec.geoms:
        for part, material in MATERIALS.items():
            if part in geom.name and geom.group in RENDER_GROUPS:
                geom.material = material
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, rig.width)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, rig.height)
    spec.visual.quality.offsamples = 0


def endoscope_model(scene: Scene | SceneConfig | None = None, rig: endoscope.Rig | None = None) -> EndoscopeModel:
    """A new picture model of ``scene`` (a :class:`Scene`, its config, or None for the default) seen
    by ``rig`` (default :class:`~regrasp_mjx.world.endoscope.Rig`), at its nominal randomisation.

    Raises:
      ValueError: the compiled model's joints differ from the scene's (the ``qpos`` layout).
    """
    scene = scene if isinstance(scene, Scene) else load_scene(scene or SceneConfig())
    rig = rig or endoscope.Rig()
    spec = mujoco.MjSpec.from_file(str(MJCF_PATH))
    _apply_config(spec, scene.config)  # the scene's own geometry, exactly as load_scene applies it
    _add(spec, rig)
    model = spec.compile()
    if model.nq != scene.model.nq or any(
        model.joint(j).qposadr[0] != scene.model.joint(j).qposadr[0] for j in ("needle_pose", "regrasp_pose")
    ):
        raise ValueError("the endoscope's model must keep the scene's joints in the scene's qpos order")
    # clipping planes in metres whatever the model's extent (the MJCF's are relative to it, and its far
    # plane would cut the tissue off)
    model.vis.map.znear = NEAR_M / model.stat.extent
    model.vis.map.zfar = FAR_M / model.stat.extent
    body_class = {NEEDLE_BODY: 2, GRASP_BODY: 3, REGRASP_BODY: 4}
    classes = np.array([body_class.get(model.body(int(b)).name, 0) for b in model.geom_bodyid], np.int8)
    classes[model.geom("tissue").id] = 1
    jaws = [
        (model.geom(name + suffix).id, side)
        for name, side in zip(REGRASP_JAWS, (1.0, -1.0))  # as _apply_config opens them
        for suffix in ("", "_visual")
    ]
    ids = np.array([g for g, _ in jaws], np.int64)
    out = EndoscopeModel(
        model=model,
        scene=scene,
        rig=rig,
        cameras=(model.camera(CAMERAS[0]).id, model.camera(CAMERAS[1]).id),
        classes=classes,
        jaw_geoms=ids,
        jaw_sides=np.array([side for _, side in jaws]),
        jaw_poses=np.concatenate([model.geom_pos[ids], model.geom_quat[ids]], axis=1),
    )
    out.apply(nominal().row(0))
    return out
