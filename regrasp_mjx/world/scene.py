"""The regrasp scene: the MJCF loaded once, names resolved once, the counted collision pairs (their
distances as JAX functions: :mod:`regrasp_mjx.world.distances`).

``regrasp_mjx/models/regrasp_scene.xml`` (package data; ``models/mjcf`` in the repository links to it) is
the single source of truth for geometry. :func:`load_scene`
applies a :class:`~regrasp_mjx.core.config.SceneConfig` (jaw angle, needle and wire radii) with MuJoCo's
``MjSpec`` and compiles two models from it: ``render_model`` (with the visual meshes) and
``model`` (collision capsules only), which goes to MJX and to the host (CPU) checker alike. Keeping
the meshes out of MJX matters: MJX has no broad phase and prepares every mesh for collision.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.world import distances

MJCF_PATH = Path(__file__).resolve().parents[1] / "models" / "regrasp_scene.xml"  # package data

NEEDLE_JOINT = "needle_pose"
REGRASP_JOINT = "regrasp_pose"
NEEDLE_BODY, REGRASP_BODY = "needle", "regrasp_tool"
REGRASP_JAWS = ("regrasp_jaw_a", "regrasp_jaw_b")
_DEFAULT_JAW_HALF_ANGLE = math.radians(10.0)  # what the MJCF file holds
_DEFAULT_NEEDLE_RADIUS = 0.0054
_DEFAULT_WIRE_RADIUS_MM = 0.25  # the wire of the MJCF's needle mesh (models/meshes/needle_tube.stl)


@dataclasses.dataclass(frozen=True)
class CapsuleInfo:
    """A collision capsule in its body frame: axis end points (m) and radius (m)."""

    name: str
    geom_id: int
    p0: np.ndarray
    p1: np.ndarray
    radius: float


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Everything resolved once from the MJCF.

    Attributes:
      config: the geometry applied.
      model: collision-only ``MjModel`` (capsules), shared by MJX and the host checker.
      render_model: the same scene with the render meshes, for images and videos.
      needle_qpos: address of the needle's free joint in ``qpos`` (pos 3, quat 4).
      regrasp_qpos: address of the regrasping tool's free joint in ``qpos``.
      regrasp_capsules, needle_capsules, grasp_capsules: the collision capsules of each object.
      pairs: the counted geom pairs ``(regrasp geom id, needle or grasping-tool geom id)``.
    """

    config: SceneConfig
    model: mujoco.MjModel
    render_model: mujoco.MjModel
    needle_qpos: int
    regrasp_qpos: int
    regrasp_capsules: tuple[CapsuleInfo, ...]
    needle_capsules: tuple[CapsuleInfo, ...]
    grasp_capsules: tuple[CapsuleInfo, ...]
    pairs: tuple[tuple[int, int], ...]

    @functools.cached_property
    def mjx_model(self) -> mjx.Model:
        # this process's first device: MJX's default, jax.devices()[0], is process 0's in a distributed run
        return mjx.put_model(self.model, device=jax.local_devices()[0])

    @functools.cached_property
    def body_model(self) -> mujoco.MjModel:
        """The scene's two free bodies without their geoms, their joints in the scene's ``qpos``
        order: what ``mjx.kinematics`` needs to pose them (:attr:`mjx_body_model`). The counted
        capsules are then placed from their bodies' frames (:attr:`capsule_frames`), only those,
        instead of every geom of the scene."""
        spec = mujoco.MjSpec()
        order = [NEEDLE_BODY, REGRASP_BODY] if self.needle_qpos < self.regrasp_qpos else [REGRASP_BODY, NEEDLE_BODY]
        for name in order:
            body = spec.worldbody.add_body(name=name)
            body.add_freejoint()
            body.explicitinertial, body.mass, body.inertia = True, 1.0, [1e-6] * 3  # a moving body needs mass
        return spec.compile()

    @functools.cached_property
    def mjx_body_model(self) -> mjx.Model:
        """:attr:`body_model` on this process's first device."""
        return mjx.put_model(self.body_model, device=jax.local_devices()[0])

    @functools.cached_property
    def body_ids(self) -> tuple[int, int]:
        """The needle's and the regrasping tool's body ids in :attr:`body_model`."""
        return self.body_model.body(NEEDLE_BODY).id, self.body_model.body(REGRASP_BODY).id

    def qpos(self, needle_pos, needle_quat, ee_pos, ee_quat) -> np.ndarray | jax.Array:
        """The model's ``qpos`` for a needle pose and a regrasping end-effector pose (world = e_g)."""
        arrays = (needle_pos, needle_quat, ee_pos, ee_quat)
        xp = jnp if any(isinstance(a, jax.Array) for a in arrays) else np
        needle = xp.concatenate([needle_pos, needle_quat], -1)
        ee = xp.concatenate([ee_pos, ee_quat], -1)
        return xp.concatenate([needle, ee] if self.needle_qpos < self.regrasp_qpos else [ee, needle], -1)

    @property
    def needle_inflation(self) -> float:
        """How much the needle chords' capsule radius exceeds the wire's [m] (see :func:`chord_placement`):
        ``e = R tan^2(h/2)`` for chords of half-angle h with ``SceneConfig.conservative_needle``, else 0."""
        wire = self.config.wire_radius_mm * 1e-3
        return max(c.radius for c in self.needle_capsules) - wire

    @property
    def needle_error_bound(self) -> float:
        """The most the model's clearance to the needle lies below the true one [m]: ``2e`` with
        ``SceneConfig.conservative_needle`` (it is never above it), 2.12 um for R = 5.4 mm and 4.72 um
        for 12 mm with the 56 chords of the MJCF (measured in tests/test_clearance.py). Without it,
        the model over-reports clearance by up to the sagitta instead."""
        return 2.0 * self.needle_inflation

    @functools.cached_property
    def capsule_frames(self) -> CapsuleFrames:
        """The counted pairs' capsules as :class:`CapsuleFrames`: axis ends in their bodies' frames,
        read off CPU MuJoCo with both free bodies at the identity (world = e_g), and radii."""
        data = mujoco.MjData(self.model)
        zero, unit = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
        data.qpos[:] = self.qpos(zero, unit, zero, unit)
        mujoco.mj_kinematics(self.model, data)

        def ends(g: int) -> np.ndarray:
            axis = data.geom_xmat[g].reshape(3, 3)[:, 2] * self.model.geom_size[g, 1]
            return np.stack([data.geom_xpos[g] - axis, data.geom_xpos[g] + axis])

        tools = sorted({int(p[0]) for p in self.pairs})
        others = sorted({int(p[1]) for p in self.pairs})
        if [(t, o) for t in tools for o in others] != list(self.pairs):
            raise ValueError("every regrasping capsule must be paired with every counted one, tool by tool")
        needle_ids = [c.geom_id for c in self.needle_capsules]  # in the file's order: along the arc
        on_needle = np.isin(others, needle_ids)
        wire = self.config.wire_radius_mm * 1e-3
        jaws = {int(self.model.geom(name).id) for name in REGRASP_JAWS}
        return CapsuleFrames(
            tool_ids=tuple(tools),
            other_ids=tuple(others),
            tool_ends=np.stack([ends(g) for g in tools]),
            other_ends=np.stack([ends(g) for g in others]),
            on_needle=on_needle,
            tool_radii=self.model.geom_size[tools, 0].copy(),
            other_radii=self.model.geom_size[others, 0].copy(),
            inflation=np.where(on_needle, self.model.geom_size[others, 0] - wire, 0.0),
            chords=np.searchsorted(others, needle_ids),
            jaw_sides=np.array([_jaw_side(ends(g)) if g in jaws else 0.0 for g in tools]),
        )

    def distance_fn(self) -> distances.DistanceFn:
        """A pure JAX function ``(needle_pos, needle_quat, ee_pos, ee_quat[, radius, wire]) ->
        distances[npairs]``, the counted pairs' signed distances around the scene's needle or
        another (:func:`regrasp_mjx.world.distances.distance_fn`)."""
        return distances.distance_fn(self)

    def motion_distance_fn(self) -> tuple[Callable, Callable, Callable]:
        """:meth:`distance_fn` cut in parts for the many poses of one motion (the continuous test):
        ``(others, gaps, interval)`` (:func:`regrasp_mjx.world.distances.motion_distance_fn`)."""
        return distances.motion_distance_fn(self)


@dataclasses.dataclass(frozen=True)
class CapsuleFrames:
    """The counted pairs' capsules in their bodies' frames (:attr:`Scene.capsule_frames`): the
    regrasping tool's ``tool_ends`` ``[T, 2, 3]`` (frame e_r) and the counted ones' ``other_ends``
    ``[O, 2, 3]`` (the needle's in frame n, the grasping tool's in the world e_g), sorted by geom id
    as :attr:`Scene.pairs` pairs them (every tool capsule with every counted one); their radii [m];
    ``on_needle`` ``[O]``; ``inflation`` ``[O]``, how much a needle chord's radius exceeds the wire's;
    ``chords``, the needle chords' indices into ``other_ends`` along the arc; ``tool_ids`` and
    ``other_ids``, their geom ids; ``jaw_sides`` ``[T]``, which way each tool capsule turns about
    the hinge (the end-effector's x axis) as the jaws open: +1 or -1 for the two jaws (the one on +y
    towards +y), 0 for the rest."""

    tool_ids: tuple[int, ...]
    other_ids: tuple[int, ...]
    tool_ends: np.ndarray
    other_ends: np.ndarray
    on_needle: np.ndarray
    tool_radii: np.ndarray
    other_radii: np.ndarray
    inflation: np.ndarray
    chords: np.ndarray
    jaw_sides: np.ndarray


def _jaw_side(ends: np.ndarray) -> float:
    """The way a jaw capsule (``[2, 3]`` in e_r, the hinge its x axis) turns as the jaws open."""
    return float(np.sign(ends[:, 1].sum()))


def chord_placement(radius: float, half_angle: float, conservative: bool = True) -> tuple[float, float]:
    """Where a capsule chord of half-angle h standing for an arc of ``radius`` puts its ends, as a
    factor k of the radius, and how much its capsule's radius exceeds the wire's [m].

    Conservative: k = 2 / (1 + cos h) puts the arc's middle and its ends equally far, e = R tan^2(h/2),
    from the chord (the middle outside it, the ends inside), the least that any straight chord with
    its ends on the arc's rays can be; a capsule of radius w + e then holds the whole wire, and its
    distance to any point is at most 2e less than the wire's (within e of the chord, which is within
    e of the arc). Not conservative: the ends on the arc and the wire's radius (``k = 1, e = 0``),
    which under-reports contact by up to the sagitta ``R (1 - cos h)``.
    """
    if not conservative:
        return 1.0, 0.0
    grow = 2.0 / (1.0 + math.cos(half_angle))
    return grow, radius * (grow - 1.0)


def _capsules(model: mujoco.MjModel, names: list[str]) -> tuple[CapsuleInfo, ...]:
    out = []
    for name in names:
        g = model.geom(name)
        if g.type[0] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            raise ValueError(f"collision geom {name!r} must be a capsule (MJX is fast with them)")
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, g.quat)
        axis = rot.reshape(3, 3)[:, 2] * g.size[1]
        out.append(CapsuleInfo(name, int(g.id), g.pos - axis, g.pos + axis, float(g.size[0])))
    return tuple(out)


def _apply_config(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    half = math.radians(config.jaw_angle_deg) / 2.0
    for name, sign in zip(REGRASP_JAWS, (1.0, -1.0)):
        geom = spec.geom(name)
        tip = np.asarray(geom.fromto[3:])
        length = float(np.linalg.norm(tip))
        geom.fromto = [0.0, 0.0, 0.0, 0.0, sign * length * math.sin(half), length * math.cos(half)]
        visual = spec.geom(name + "_visual")
        # The jaw mesh points along +z; a rotation of -sign*half about x opens it to this jaw. The MJCF
        # gives its orientation as euler angles, which the compiler would take over the quaternion: the
        # quaternion is made the orientation used (else the meshes stay at the file's opening).
        visual.quat = [math.cos(-sign * half / 2), math.sin(-sign * half / 2), 0.0, 0.0]
        visual.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    radius = config.needle_radius_mm * 1e-3
    scale = radius / _DEFAULT_NEEDLE_RADIUS
    for geom in spec.geoms:
        if geom.name.startswith("needle_seg"):
            # the file's chord ends lie on the arc; only their directions from the centre are used
            ends = np.reshape(geom.fromto, (2, 3))
            ends = ends / np.linalg.norm(ends, axis=1, keepdims=True)
            half = 0.5 * math.acos(float(np.clip(ends[0] @ ends[1], -1.0, 1.0)))
            grow, inflation = chord_placement(radius, half, config.conservative_needle)
            geom.fromto = list((ends * radius * grow).ravel())
            geom.size = [config.wire_radius_mm * 1e-3 + inflation, 0.0, 0.0]
    if abs(scale - 1.0) > 1e-12 or abs(config.wire_radius_mm - _DEFAULT_WIRE_RADIUS_MM) > 1e-12:
        # the render mesh of this needle (the file holds the default one): the arc of R, the tube of the wire
        from regrasp_mjx.world.needle_mesh import needle_tube  # here: trimesh's import costs ~0.5 s, rarely needed

        tube = needle_tube(radius, config.wire_radius_mm * 1e-3)
        mesh = spec.mesh("needle_tube")
        mesh.file = ""
        mesh.uservert = np.asarray(tube.vertices, np.float32).ravel()
        mesh.userface = np.asarray(tube.faces, np.int32).ravel()
    spec.site("needle_tip").pos = [0.0, 0.0, config.needle_radius_mm * 1e-3]


def needle_scene(scene: Scene, radius: float | None, wire: float | None) -> Scene:
    """``scene`` with another needle (radius and wire radius in metres; None keeps the scene's), as the
    host (CPU MuJoCo) checks it; the scene itself when the needle is its own (within 1 nm)."""
    cfg = scene.config
    r_mm = cfg.needle_radius_mm if radius is None else float(radius) * 1e3
    w_mm = cfg.wire_radius_mm if wire is None else float(wire) * 1e3
    if abs(r_mm - cfg.needle_radius_mm) < 1e-6 and abs(w_mm - cfg.wire_radius_mm) < 1e-6:
        return scene
    return load_scene(dataclasses.replace(cfg, needle_radius_mm=r_mm, wire_radius_mm=w_mm))


@functools.lru_cache(maxsize=8)
def load_scene(config: SceneConfig = SceneConfig(), mjcf_path: str | None = None) -> Scene:
    """Loads the MJCF, applies ``config``, resolves names once. Cached per config.

    Raises:
      FileNotFoundError: the MJCF file is missing.
      ValueError: the MJCF lacks a geom or joint this package needs, by name.
    """
    path = Path(mjcf_path) if mjcf_path else MJCF_PATH
    if not path.is_file():
        raise FileNotFoundError(f"scene MJCF not found at {path}")
    spec = mujoco.MjSpec.from_file(str(path))
    try:
        _apply_config(spec, config)
    except (AttributeError, TypeError, KeyError) as err:
        raise ValueError(f"{path} lacks a named element the scene needs: {err}") from err
    render_model = spec.compile()
    for geom in list(spec.geoms):
        if geom.contype == 0 and geom.conaffinity == 0:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    model = spec.compile()
    if model.nq != 14 or model.nv != 12:
        raise ValueError(f"{path}: expected two free joints (needle, regrasping tool), got nq={model.nq}")

    names = [model.geom(i).name for i in range(model.ngeom)]
    regrasp = [n for n in names if n.startswith("regrasp_")]
    needle = [n for n in names if n.startswith("needle_")]
    grasp = [n for n in names if n.startswith("grasp_")]
    if not (regrasp and needle and grasp):
        raise ValueError(f"{path} must name geoms regrasp_*, needle_* and grasp_*; it has {names}")
    ids = {n: model.geom(n).id for n in names}
    counted = {ids[n] for n in needle + grasp}
    pairs = tuple((ids[r], j) for r in regrasp for j in range(model.ngeom) if j in counted)
    return Scene(
        config=config,
        model=model,
        render_model=render_model,
        needle_qpos=int(model.joint(NEEDLE_JOINT).qposadr[0]),
        regrasp_qpos=int(model.joint(REGRASP_JOINT).qposadr[0]),
        regrasp_capsules=_capsules(model, regrasp),
        needle_capsules=_capsules(model, needle),
        grasp_capsules=_capsules(model, grasp),
        pairs=pairs,
    )
