"""Pictures of the scene: offscreen MuJoCo images and videos, and a matplotlib sketch as fallback.

:class:`SceneRenderer` draws ``Scene.render_model`` (the MJCF with its meshes) with MuJoCo's own
OpenGL renderer, headless. It makes its GL context itself instead of going through
``mujoco.Renderer``, whose backend is fixed by ``MUJOCO_GL`` when ``mujoco`` is first imported (and
this package imports ``mujoco`` early): the backend is ``MUJOCO_GL`` if set, else EGL (on Linux; Mesa's
EGL renders on the CPU too), else GLFW. Where no backend works it raises :class:`RenderUnavailable`
and :func:`sketch` draws the collision capsules with matplotlib instead.

Poses are 7-vectors ``[x, y, z, qw, qx, qy, qz]`` (metres) in the grasping end-effector frame e_g,
as :class:`regrasp_mjx.inference.plans.Plan` gives them.
"""

from __future__ import annotations

import importlib
import os
import platform
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from regrasp_mjx.core.atomic import atomic_write
from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.envs import host
from regrasp_mjx.inference.policy import PoseError, check_poses
from regrasp_mjx.world.scene import Scene, load_scene

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
GOAL_RGBA = (0.1, 0.8, 0.3, 0.35)  # the regrasping tool at its goal, drawn as a ghost
PATH_RGBA = (1.0, 0.75, 0.1, 1.0)  # the end-effector's path
PATH_WIDTH = 0.00012  # m
BACKGROUND = (236, 238, 242)  # pixels that nothing covers (MuJoCo clears to black)
# The free camera: ``distance`` (m) from a point between the needle's centre and the regrasping tool,
# looking across both tools' shafts (so that neither hides the needle), turned by ``azimuth`` and
# ``elevation`` (degrees) from that direction so that the scene is seen in depth.
DEFAULT_VIEW = {"distance": 0.038, "azimuth": 25.0, "elevation": 25.0}
LOOK_TOWARD_TOOL = 0.3


class RenderUnavailable(RuntimeError):
    """No OpenGL backend could make an offscreen context on this machine."""


def _gl_context(model: mujoco.MjModel, width: int, height: int):
    """An offscreen GL context made current and MuJoCo's render context on it."""
    wanted = os.environ.get("MUJOCO_GL", "").strip().lower()
    if wanted in ("", "1", "on", "true", "enable", "enabled"):
        wanted = "egl" if platform.system() == "Linux" else "glfw"
    if wanted not in ("egl", "osmesa", "glfw", "glx", "cgl", "wgl"):
        raise RenderUnavailable(f"MUJOCO_GL={wanted!r} is not accepted here: egl, osmesa or glfw")
    module = "glfw" if wanted == "glx" else wanted
    try:
        if module == "glfw":  # without a display GLFW still hands out a (dead) context object
            import glfw  # optional: only where a GLFW window system is asked for

            if not glfw.init():
                raise RuntimeError("GLFW could not start (no display?)")
        ctx = importlib.import_module(f"mujoco.{module}").GLContext(width, height)
        ctx.make_current()
        con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
    except Exception as err:  # ImportError, OSError, mujoco.FatalError, GL errors: all mean "no GL here"
        raise RenderUnavailable(
            f"no offscreen OpenGL context with MUJOCO_GL={wanted} ({type(err).__name__}: {err}). Headless "
            "Linux needs EGL (the default; Debian: libegl1 libegl-mesa0) or OSMesa (libosmesa6, with "
            "MUJOCO_GL=osmesa set before Python starts); regrasp_mjx.workflows.render.sketch draws without OpenGL"
        ) from err
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
    return ctx, con


def _pose(name: str, pose: Any) -> np.ndarray:
    """One pose, checked as :meth:`Policy.plan` checks its inputs (finite, unit quaternion)."""
    p = np.asarray(pose, np.float64)
    try:
        if p.shape != (7,):
            raise PoseError(f"got shape {p.shape}")
        return check_poses(name, p)
    except PoseError as err:
        raise ValueError(f"{name} must be a finite pose [x, y, z, qw, qx, qy, qz]: {err}") from err


def _rotation(quat: np.ndarray) -> np.ndarray:
    flat = np.empty(9)
    mujoco.mju_quat2Mat(flat, quat)
    return flat.reshape(3, 3)


def interpolate(poses: Any, substeps: int) -> np.ndarray:
    """``substeps`` poses per step of a trajectory ``[T, 7]``: positions linear, rotations slerped."""
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 7 or len(poses) == 0:
        raise ValueError(f"poses must be [T, 7] with T >= 1, got {poses.shape}")
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    out = []
    for a, b in zip(poses[:-1], poses[1:]):
        qb = b[3:] if np.dot(a[3:], b[3:]) >= 0 else -b[3:]  # the short way round
        delta = host.quat_to_rotvec(host.quat_mul(host.quat_conj(a[3:]), qb))
        for s in np.arange(substeps) / substeps:
            q = host.quat_mul(a[3:], host.quat_from_rotvec(s * delta))
            out.append(np.concatenate([a[:3] + s * (b[:3] - a[:3]), q]))
    out.append(poses[-1])
    return np.stack(out)


class Offscreen:
    """What holds a headless GL context and its MuJoCo render context (``_ctx``, ``_con``, from
    :func:`_gl_context`): a context manager that frees them, or call :meth:`close` (twice is fine)."""

    _ctx: Any = None
    _con: Any = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.make_current()
            self._con.free()
            self._ctx.free()
            self._ctx = None


class SceneRenderer(Offscreen):
    """Offscreen images of one scene; use as a context manager (or call :meth:`close`).

    Args:
      scene: a loaded :class:`Scene` or a :class:`SceneConfig` (default: the default scene).
      width, height: pixels (at most 2048 each).
      view: the free camera's ``distance`` (m) and its ``azimuth`` and ``elevation`` (degrees) away
        from the direction across both tools' shafts (``DEFAULT_VIEW``).
      camera: a camera of the MJCF instead of the free one, e.g. ``"overview"``.

    Raises:
      RenderUnavailable: no OpenGL backend here (see the module's docstring).
    """

    def __init__(
        self,
        scene: Scene | SceneConfig | None = None,
        width: int = 640,
        height: int = 480,
        view: dict[str, float] | None = None,
        camera: str | None = None,
    ):
        if not (16 <= width <= 2048 and 16 <= height <= 2048):
            raise ValueError(f"width and height must be within [16, 2048] pixels, got {width} x {height}")
        self.scene = scene if isinstance(scene, Scene) else load_scene(scene or SceneConfig())
        self.model = self.scene.render_model
        self.width, self.height = int(width), int(height)
        self.view = {**DEFAULT_VIEW, **(view or {})}
        if camera is not None and mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            raise ValueError(f"camera {camera!r} is not in the scene's MJCF")
        self.camera = camera
        # The offscreen buffer must hold the image: grow the model's own size if asked for more.
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, self.width)
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, self.height)
        self._ctx, self._con = _gl_context(self.model, self.width, self.height)
        self._scn = mujoco.MjvScene(self.model, maxgeom=2000)
        self._opt = mujoco.MjvOption()
        self._opt.sitegroup[:] = 0  # frame markers off
        self._data = mujoco.MjData(self.model)
        self._ghost = mujoco.MjData(self.model)
        self._regrasp_body = self.model.body("regrasp_tool").id
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._pert = mujoco.MjvPerturb()

    def _camera(self, needle: np.ndarray, ee: np.ndarray) -> mujoco.MjvCamera:
        cam = mujoco.MjvCamera()
        if self.camera is not None:
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = self.model.camera(self.camera).id
            return cam
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        # Between the needle and the regrasping tool's jaws, nearer the needle: both in the frame.
        cam.lookat[:] = needle[:3] + LOOK_TOWARD_TOOL * (ee[:3] - needle[:3])
        cam.distance = self.view["distance"]
        # MuJoCo's free camera looks along (cos el cos az, cos el sin az, sin el), in degrees.
        forward = -self._eye_direction(needle, ee)
        cam.azimuth = np.degrees(np.arctan2(forward[1], forward[0])) + self.view["azimuth"]
        cam.elevation = np.degrees(np.arcsin(np.clip(forward[2], -1.0, 1.0))) - self.view["elevation"]
        return cam

    @staticmethod
    def _eye_direction(needle: np.ndarray, ee: np.ndarray) -> np.ndarray:
        """Unit vector from the needle's centre to the camera: across both tools' shafts (e_g's z and
        the regrasping end-effector's z), so that neither hides the needle, on the side its plane
        faces (the needle's x axis) so that the arc is seen open rather than edge-on."""
        normal = _rotation(needle[3:])[:, 0]
        across = np.cross([0.0, 0.0, 1.0], _rotation(ee[3:])[:, 2])
        if np.linalg.norm(across) < 0.2:  # shafts nearly parallel: look at the needle's face
            across = normal
        across = across / np.linalg.norm(across)
        return across if np.dot(across, normal) >= 0 else -across

    def image(self, needle: Any, ee: Any, goal: Any = None, path: Any = None, frame_for: Any = None) -> np.ndarray:
        """One RGB image ``[height, width, 3]`` (uint8): the needle, both tools, optionally the
        regrasping tool's goal as a green ghost and a path ``[N, 3]`` (m) as a yellow line. The free
        camera is framed for the regrasping tool at ``frame_for`` (a pose; default ``ee``): a video keeps
        one camera by passing its first pose."""
        if self._ctx is None:
            raise RuntimeError("this SceneRenderer is closed")
        needle, ee = _pose("needle", needle), _pose("ee", ee)
        self._data.qpos[:] = self.scene.qpos(needle[:3], needle[3:], ee[:3], ee[3:])
        mujoco.mj_forward(self.model, self._data)
        cat = mujoco.mjtCatBit.mjCAT_ALL
        mujoco.mjv_updateScene(
            self.model,
            self._data,
            self._opt,
            self._pert,
            self._camera(needle, ee if frame_for is None else _pose("frame_for", frame_for)),
            int(cat),
            self._scn,
        )
        if goal is not None:
            goal = _pose("goal", goal)
            self._ghost.qpos[:] = self.scene.qpos(needle[:3], needle[3:], goal[:3], goal[3:])
            mujoco.mj_forward(self.model, self._ghost)
            first = self._scn.ngeom
            mujoco.mjv_addGeoms(
                self.model, self._ghost, self._opt, self._pert, int(mujoco.mjtCatBit.mjCAT_DYNAMIC), self._scn
            )
            for g in self._scn.geoms[first : self._scn.ngeom]:
                is_tool = (
                    g.objtype == mujoco.mjtObj.mjOBJ_GEOM and self.model.geom_bodyid[g.objid] == self._regrasp_body
                )
                g.rgba[:] = GOAL_RGBA if is_tool else (0.0, 0.0, 0.0, 0.0)  # the needle is drawn once already
        if path is not None:
            self._add_path(np.asarray(path, np.float64))
        self._ctx.make_current()
        mujoco.mjr_render(self._rect, self._scn, self._con)
        rgb = np.empty((self.height, self.width, 3), np.uint8)
        depth = np.empty((self.height, self.width), np.float32)
        mujoco.mjr_readPixels(rgb, depth, self._rect, self._con)
        rgb[depth >= 1.0] = BACKGROUND
        return rgb[::-1].copy()  # OpenGL's rows run bottom-up

    def _add_path(self, points: np.ndarray) -> None:
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise ValueError(f"path must be finite points [N, 3] in metres, got shape {points.shape}")
        for a, b in zip(points[:-1], points[1:]):
            if self._scn.ngeom >= self._scn.maxgeom or np.allclose(a, b):
                continue
            g = self._scn.geoms[self._scn.ngeom]
            mujoco.mjv_initGeom(
                g,
                mujoco.mjtGeom.mjGEOM_CAPSULE,
                np.zeros(3),
                np.zeros(3),
                np.eye(3).ravel(),
                np.asarray(PATH_RGBA, np.float32),
            )
            mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_CAPSULE, PATH_WIDTH, a, b)
            self._scn.ngeom += 1

    def video(self, needle: Any, poses: Any, goal: Any = None, substeps: int = 4, hold: int = 6) -> np.ndarray:
        """Frames ``[F, height, width, 3]`` of the regrasping tool along ``poses [T, 7]``: ``substeps``
        frames per step (interpolated), the path drawn so far, the goal ghost, the last frame held
        ``hold`` extra times."""
        poses = interpolate(poses, substeps)
        first = poses[0]  # one camera for the whole video
        frames = [self.image(needle, p, goal, poses[: i + 1, :3], first) for i, p in enumerate(poses)]
        frames += [frames[-1]] * hold
        return np.stack(frames)


def write_gif(path: str | os.PathLike, frames: np.ndarray, fps: float = 12.0) -> Path:
    """Writes frames ``[F, H, W, 3]`` (uint8) as a looping GIF with Pillow (no ffmpeg needed),
    atomically (a temporary file renamed into place)."""
    from PIL import Image  # optional (the analysis extra): only where a GIF is written

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be uint8 [F, H, W, 3] with F >= 1, got {frames.dtype} {frames.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    atomic_write(
        path,
        lambda f: images[0].save(
            f, format="GIF", save_all=True, append_images=images[1:], duration=1000.0 / fps, loop=0
        ),
    )
    return path


def capsule_segments(scene: Scene, needle: Any, ee: Any) -> dict[str, list[tuple[np.ndarray, np.ndarray, float]]]:
    """The collision capsules at these poses, in e_g: ``{"needle"|"grasp"|"regrasp": [(p0, p1, radius)]}``."""
    needle, ee = _pose("needle", needle), _pose("ee", ee)

    def place(caps, pose):
        rot = _rotation(pose[3:])
        return [(pose[:3] + rot @ c.p0, pose[:3] + rot @ c.p1, c.radius) for c in caps]

    return {
        "grasp": place(scene.grasp_capsules, IDENTITY),  # the grasping tool's frame is the world
        "needle": place(scene.needle_capsules, needle),
        "regrasp": place(scene.regrasp_capsules, ee),
    }


def _clip(seg: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """The part of segment ``seg [2, 3]`` inside the box ``[lo, hi]`` (Liang-Barsky), or None."""
    p0, d = seg[0], seg[1] - seg[0]
    t0, t1 = 0.0, 1.0
    for k in range(3):
        if abs(d[k]) < 1e-15:
            if not lo[k] <= p0[k] <= hi[k]:
                return None
            continue
        a, b = sorted(((lo[k] - p0[k]) / d[k], (hi[k] - p0[k]) / d[k]))
        t0, t1 = max(t0, a), min(t1, b)
        if t0 > t1:
            return None
    return np.stack([p0 + t0 * d, p0 + t1 * d])


def sketch(ax, scene: Scene, needle: Any, ee: Any, goal: Any = None, path: Any = None, half_mm: float = 12.0) -> None:
    """Draws the collision capsules' axes on a matplotlib 3-D axis (millimetres, one scale on every
    axis, a cube of half-width ``half_mm`` around the needle; matplotlib does not clip 3-D lines, so
    the parts outside are cut here), for machines without OpenGL: needle red, grasping tool grey,
    regrasping tool blue, its goal green dashed, the path orange."""
    needle = _pose("needle", needle)
    lo, hi = needle[:3] * 1e3 - half_mm, needle[:3] * 1e3 + half_mm

    def draw(seg, **style):
        seg = _clip(np.asarray(seg, np.float64) * 1e3, lo, hi)
        if seg is not None:
            ax.plot(*seg.T, **style)

    colours = {"grasp": "0.45", "needle": "tab:red", "regrasp": "tab:blue"}
    for part, caps in capsule_segments(scene, needle, ee).items():
        for p0, p1, r in caps:
            draw(np.stack([p0, p1]), color=colours[part], lw=max(1.0, r * 4e3), solid_capstyle="round")
    if goal is not None:
        for p0, p1, _ in capsule_segments(scene, needle, goal)["regrasp"]:
            draw(np.stack([p0, p1]), color="tab:green", lw=1.0, ls="--")
    if path is not None:
        path = np.asarray(path, np.float64)[:, :3]
        for a, b in zip(path[:-1], path[1:]):
            draw(np.stack([a, b]), color="orange", lw=1.5)
    for setter, a, b in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), lo, hi):
        setter(a, b)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
