"""Datasets of labelled stereo frames for the estimator: ``N`` episodes of ``F`` frames each, rendered from a
seed to one npz file (written atomically), and read back with its checks.

An episode is one problem of the task's distribution (:func:`regrasp_mjx.world.testsets.make_testset`
with the dataset's seed) with one randomisation draw (camera jitter, lights, materials, image blur and
gain); over its frames the regrasping tool moves from its start to its goal (positions linear,
rotations slerped) and each frame has its own image noise. Rows are episode-major (row ``e * F + f``),
so the errors of one episode's frames can be split into the part fixed per episode and the part that
changes per frame. With ``jaw_open`` the regrasping jaws open on the way, as a policy with jaws that open
does: each episode draws an opening in that range and its later frames (from frame ``F // 2``) draw the
jaws there, the earlier ones at the scene's opening (``jaw_deg``, one per row). The keypoints are the estimator's (:func:`regrasp_mjx.vision.layout.layout`), their
visibility from the rendered depth and segmentation, which are not kept (RGB only: 0.35 MB a pair at
320 x 180).

Rendering runs in ``workers`` processes (one OpenGL context each; JAX on the CPU there, so that none
takes the GPU) over chunks of episodes; each finished chunk is a file of its own in ``OUT.parts/``, so
a killed render resumes where it stopped; the chunks are joined into ``OUT`` at the end.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import json
import multiprocessing
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from regrasp_mjx.core.atomic import atomic_write, dumps, write_json
from regrasp_mjx.core.config import JAW_MAX_DEG, TASKS, EnvConfig, SceneConfig
from regrasp_mjx.core.host_loop import eta
from regrasp_mjx.vision import layout as kp_layout
from regrasp_mjx.workflows.frames import FrameRenderer, label
from regrasp_mjx.workflows.render import interpolate
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.sampling import episode_poses
from regrasp_mjx.world.scene import load_scene
from regrasp_mjx.world.testsets import make_testset, versions

DATASET_FORMAT = "regrasp_mjx.frames"
DATASET_VERSION = 1
MAX_PAIRS = 1_000_000
CHUNK_EPISODES = 32
ARRAYS = {  # name: (dtype, shape after N), K keypoints, H x W images
    "rgb": ("uint8", "2, H, W, 3"),
    "pixels": ("float32", "2, K, 2"),
    "visible": ("bool", "2, K"),
    "keypoint_depth": ("float32", "2, K"),
    "poses": ("float64", "3, 7"),
    "extrinsics": ("float64", "2, 4, 4"),
    "episode": ("int32", ""),
    "frame": ("int32", ""),
    "seeds": ("int64", ""),
    "jaw_deg": ("float32", ""),
}
# arrays a file written before them lacks, with what they were then: the jaws at the scene's opening
OPTIONAL = {
    "jaw_deg": lambda meta, n: np.full(
        n, meta.get("jaws", {}).get("base_deg", kp_layout.JAW_DEG_BEFORE_OPENING), np.float32
    )
}


class DatasetError(ValueError):
    """A frame dataset that is missing, corrupt, or not what a command needs."""


@dataclasses.dataclass(frozen=True)
class FrameDataset:
    """Labelled stereo pairs (:data:`ARRAYS`), the cameras' ``intrinsics`` ``[3, 3]`` and the file's ``meta``."""

    rgb: np.ndarray
    pixels: np.ndarray
    visible: np.ndarray
    keypoint_depth: np.ndarray
    poses: np.ndarray
    extrinsics: np.ndarray
    episode: np.ndarray
    frame: np.ndarray
    seeds: np.ndarray
    jaw_deg: np.ndarray
    intrinsics: np.ndarray
    meta: dict[str, Any]

    @property
    def keypoints(self) -> endoscope.Keypoints:
        return kp_layout.from_json(self.meta["keypoints"])

    def camera_poses(self, camera: int = 0) -> np.ndarray:
        """The objects' poses ``[N, 3, 7]`` (needle, grasping tool, regrasping tool) in camera ``camera``'s
        frame (OpenCV axes; ``qw >= 0``)."""
        obj = np.zeros(self.poses.shape[:2] + (4, 4))
        obj[..., :3, :3] = endoscope.quat_matrix(self.poses[..., 3:])
        obj[..., :3, 3], obj[..., 3, 3] = self.poses[..., :3], 1.0
        cam = self.extrinsics[:, camera, None] @ obj
        quat = np.stack([_quat(r) for r in cam[..., :3, :3].reshape(-1, 3, 3)]).reshape(cam.shape[:2] + (4,))
        return np.concatenate([cam[..., :3, 3], quat], axis=-1)


def _quat(rot: np.ndarray) -> np.ndarray:
    """A rotation matrix's unit quaternion (wxyz, ``w >= 0``), by the largest of its four squares."""
    tr = np.trace(rot)
    sq = np.array([1 + tr, 1 + 2 * rot[0, 0] - tr, 1 + 2 * rot[1, 1] - tr, 1 + 2 * rot[2, 2] - tr])
    i = int(np.argmax(sq))
    s = 2.0 * np.sqrt(sq[i])
    off = [rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]]
    plus = [rot[0, 1] + rot[1, 0], rot[0, 2] + rot[2, 0], rot[1, 2] + rot[2, 1]]
    q = [
        np.array([s / 4, off[0] / s, off[1] / s, off[2] / s]),
        np.array([off[0] / s, s / 4, plus[0] / s, plus[1] / s]),
        np.array([off[1] / s, plus[0] / s, s / 4, plus[2] / s]),
        np.array([off[2] / s, plus[1] / s, plus[2] / s, s / 4]),
    ][i]
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def episode_states(
    episodes: int, frames: int, seed: int, task: str = "paper", jaw_open: tuple[float, float] | None = None
) -> tuple[np.ndarray, ...]:
    """The needles ``[E, 7]``, the regrasping tool's poses ``[E, F, 7]`` (start to goal), the episodes'
    randomisation seeds ``[E]`` and the jaws' opening in each frame ``[E, F]`` of a dataset's ``seed``:
    the scene's, or with ``jaw_open`` (least, most; degrees) the scene's in the first ``F // 2`` frames
    and an opening drawn per episode in that range after (the jaws open on the way, near the goal)."""
    problems = make_testset(int(episodes), int(seed), EnvConfig(task=TASKS[task]))
    needle, start, goal = episode_poses(problems)
    ee = np.stack([interpolate(np.stack([s, g]), frames - 1) if frames > 1 else s[None] for s, g in zip(start, goal)])
    render_seeds = np.random.default_rng([int(seed), 68]).integers(0, 2**31 - 1, size=episodes)
    jaws = np.full((episodes, frames), SceneConfig().jaw_angle_deg)
    if jaw_open is not None:  # its own stream: the problems and the pictures stay those of the seed without it
        opened = np.random.default_rng([int(seed), 68, 67]).uniform(*jaw_open, size=episodes)
        jaws[:, frames // 2 :] = opened[:, None]
    return needle, ee, render_seeds, jaws


# ---- rendering, in this process or in workers ------------------------------------------------------

_RENDERER: dict[str, FrameRenderer] = {}


def _renderer(width: int, height: int) -> FrameRenderer:
    key = f"{width}x{height}"
    if key not in _RENDERER:
        _RENDERER[key] = FrameRenderer(rig=endoscope.Rig(width=width, height=height))
    return _RENDERER[key]


def render_chunk(
    needle: np.ndarray, ee: np.ndarray, seeds: np.ndarray, jaws: np.ndarray, first: int, width: int, height: int
) -> dict:
    """The rows of episodes ``first ..`` (needles ``[e, 7]``, tool poses ``[e, F, 7]``, seeds ``[e]``, the
    jaws' openings ``[e, F]``)."""
    r = _renderer(width, height)
    kp = kp_layout.layout(r.endo.scene)
    e, f = ee.shape[:2]
    rows: dict[str, list] = {k: [] for k in ARRAYS}
    for j in range(f):
        fr = r.render(needle, ee[:, j], seeds=seeds, frame=j, jaw_deg=jaws[:, j])
        _, pixels, z, seen = label(r.endo, kp, needle, ee[:, j], fr.extrinsics, fr.depth, fr.segmentation, jaws[:, j])
        parts = {"rgb": fr.rgb, "pixels": pixels, "visible": seen, "keypoint_depth": z, "poses": fr.poses}
        parts |= {"extrinsics": fr.extrinsics, "episode": first + np.arange(e), "frame": np.full(e, j), "seeds": seeds}
        parts |= {"jaw_deg": jaws[:, j]}
        for k, v in parts.items():
            rows[k].append(np.asarray(v).astype(ARRAYS[k][0]))
    # frame-major lists to episode-major rows: [F, e, ...] -> [e, F, ...] -> [e * F, ...]
    return {k: np.swapaxes(np.stack(v), 0, 1).reshape((e * f,) + v[0].shape[1:]) for k, v in rows.items()}


def _render_to_file(path: Path, *args) -> Path:
    part = render_chunk(*args)
    atomic_write(path, lambda fh: np.savez(fh, **part))
    return path


@contextlib.contextmanager
def _cpu_children():
    """JAX on the CPU in the worker processes started inside (they inherit the environment): only the
    parent may take the GPU."""
    before = os.environ.get("JAX_PLATFORMS")
    os.environ["JAX_PLATFORMS"] = "cpu"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("JAX_PLATFORMS", None)
        else:
            os.environ["JAX_PLATFORMS"] = before


def render_dataset(
    out: str | os.PathLike,
    episodes: int,
    frames: int,
    seed: int,
    width: int = endoscope.RESOLUTION[0],
    height: int = endoscope.RESOLUTION[1],
    task: str = "paper",
    workers: int = 1,
    log=print,
    jaw_open: tuple[float, float] | None = None,
) -> Path:
    """Renders ``episodes`` x ``frames`` labelled stereo pairs of ``seed`` to ``out`` (npz, atomically),
    resuming from the chunks an earlier run with the same arguments left in ``OUT.parts/``. ``jaw_open``
    (least, most opening, degrees; None: the jaws stay at the scene's): the jaws open on the way
    (:func:`episode_states`).

    Raises:
      DatasetError: bad sizes, or ``OUT.parts/`` holds another dataset's chunks.
      RenderUnavailable: no OpenGL context can be made here.
    """
    if not (1 <= episodes and 1 <= frames and episodes * frames <= MAX_PAIRS):
        raise DatasetError(
            f"{episodes} episodes x {frames} frames: accepted 1 or more of each, at most {MAX_PAIRS} pairs"
        )
    if task not in TASKS or workers < 1:
        raise DatasetError(f"task {task!r}, workers {workers}: accepted a task of {sorted(TASKS)} and workers >= 1")
    base = SceneConfig().jaw_angle_deg
    if jaw_open is not None:
        try:
            lo, hi = (float(d) for d in jaw_open)
        except (TypeError, ValueError):
            raise DatasetError(
                f"jaw_open={jaw_open!r} is not accepted: two openings (least, most) in degrees"
            ) from None
        if not (base <= lo <= hi <= JAW_MAX_DEG):
            raise DatasetError(
                f"jaw_open={jaw_open!r} is not accepted: least <= most, within [{base:g}, {JAW_MAX_DEG:g}] degrees "
                "(from the scene's opening to the jaw's widest)"
            )
        jaw_open = (lo, hi)
    rig = endoscope.Rig(width=width, height=height)  # checks the size
    out = Path(out)
    parts = out.with_name(out.name + ".parts")
    args = {"episodes": episodes, "frames": frames, "seed": seed, "width": width, "height": height, "task": task}
    args |= {"jaw_open": None if jaw_open is None else list(jaw_open)}
    manifest = parts / "manifest.json"
    if manifest.is_file() and json.loads(manifest.read_text()) != args:
        raise DatasetError(
            f"{parts} holds the chunks of another dataset ({manifest.read_text().strip()}); accepted: the same "
            "arguments to resume it, or remove that folder"
        )
    write_json(manifest, args)
    t0 = time.perf_counter()
    needle, ee, seeds, jaws = episode_states(episodes, frames, seed, task, jaw_open)
    chunks = [(i, min(i + CHUNK_EPISODES, episodes)) for i in range(0, episodes, CHUNK_EPISODES)]
    todo = [(a, b) for a, b in chunks if not (parts / f"chunk_{a:07d}.npz").is_file()]
    mb = episodes * frames * 6 * width * height / 2**20
    log(
        f"render {episodes} episodes x {frames} frames at {width} x {height} ({mb:,.0f} MB of RGB) to {out}; "
        f"{len(chunks) - len(todo)} of {len(chunks)} chunks already rendered; {workers} worker(s)"
    )
    jobs = [
        (parts / f"chunk_{a:07d}.npz", needle[a:b], ee[a:b], seeds[a:b], jaws[a:b], a, width, height) for a, b in todo
    ]
    done, pairs, t1 = 0, 0, time.perf_counter()

    def progress(job_pairs: int) -> None:
        nonlocal done, pairs
        done, pairs = done + 1, pairs + job_pairs
        seconds = time.perf_counter() - t1
        log(
            f"  chunk {done}/{len(todo)}: {pairs} pairs, {pairs / seconds:,.1f} pairs/s, {eta(done, len(todo), seconds)}"
        )

    if workers == 1 or len(jobs) <= 1:
        for job in jobs:
            _render_to_file(*job)
            progress(len(job[1]) * frames)
    else:
        with (
            _cpu_children(),
            concurrent.futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool,
        ):
            futures = {pool.submit(_render_to_file, *job): len(job[1]) * frames for job in jobs}
            for fut in concurrent.futures.as_completed(futures):
                fut.result()
                progress(futures[fut])
    data: dict[str, list] = {k: [] for k in ARRAYS}
    for a, _ in chunks:
        with np.load(parts / f"chunk_{a:07d}.npz", allow_pickle=False) as f:
            for k in ARRAYS:
                data[k].append(f[k])
    arrays = {k: np.concatenate(v) for k, v in data.items()}
    meta = {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        **args,
        "pairs": episodes * frames,
        "rig": dataclasses.asdict(rig),
        "keypoints": kp_layout.to_json(kp_layout.layout(load_scene(SceneConfig()))),  # the scene FrameRenderer draws
        "jaws": {
            "base_deg": base,
            "open_deg": None if jaw_open is None else list(jaw_open),
            "rule": "the keypoints' model at base_deg; with open_deg each episode draws an opening in it, its frames "
            "from frames // 2 on draw the regrasping jaws there (their tips' labels turned with them): jaw_deg",
        },
        "renderer": f"MuJoCo OpenGL (MUJOCO_GL={os.environ.get('MUJOCO_GL', 'egl by default')})",
        "rows": "episode-major: row e * frames + f; in an episode the regrasping tool moves from its start to its goal",
        "units": "metres, OpenCV camera axes, extrinsics world (e_g) to camera, poses [x, y, z, qw, qx, qy, qz] in e_g",
        "arrays": {k: f"{d} [N, {s}]".replace(", ]", "]") for k, (d, s) in ARRAYS.items()},
        "versions": versions(),
    }
    atomic_write(out, lambda fh: np.savez(fh, meta=np.array(dumps(meta)), intrinsics=rig.intrinsics(), **arrays))
    shutil.rmtree(parts)
    log(f"wrote {out}: {episodes * frames} pairs in {time.perf_counter() - t0:.1f} s")
    return out


def load_dataset(path: str | os.PathLike) -> FrameDataset:
    """A dataset :func:`render_dataset` wrote, checked; a :class:`DatasetError` says what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"frame dataset not found: {path}; accepted: an npz that `estimator render` wrote")
    try:
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta"]))
            arrays = {k: f[k] for k in (*ARRAYS, "intrinsics") if k in f.files or k not in OPTIONAL}
    except Exception as err:  # truncated, foreign, without a key: zipfile, KeyError, ValueError, JSON
        raise DatasetError(f"{path} is not a readable frame dataset ({type(err).__name__}: {err})") from err
    if (meta.get("format"), meta.get("version")) != (DATASET_FORMAT, DATASET_VERSION):
        raise DatasetError(
            f"{path}: {meta.get('format')!r} version {meta.get('version')!r}; this package reads "
            f"{DATASET_FORMAT!r} version {DATASET_VERSION}"
        )
    try:
        for name, old in OPTIONAL.items():
            if name not in arrays:
                arrays[name] = old(meta, int(meta["pairs"]))
        sizes = {"N": int(meta["pairs"]), "K": len(meta["keypoints"]["names"])}
        sizes |= {"H": int(meta["height"]), "W": int(meta["width"])}
        kp_layout.from_json(meta["keypoints"])
    except (KeyError, TypeError, ValueError) as err:
        raise DatasetError(f"{path}: incomplete meta ({err})") from err
    for name, (dtype, shape) in ARRAYS.items():
        want = (sizes["N"], *(int(sizes.get(d, d)) for d in shape.split(", ") if d))
        if arrays[name].shape != want or arrays[name].dtype != np.dtype(dtype):
            raise DatasetError(f"{path}: {name} is {arrays[name].dtype}{arrays[name].shape}, expected {dtype}{want}")
    if arrays["intrinsics"].shape != (3, 3):
        raise DatasetError(f"{path}: intrinsics has shape {arrays['intrinsics'].shape}, expected (3, 3)")
    if not all(np.all(np.isfinite(arrays[n])) for n in ("pixels", "poses", "extrinsics", "intrinsics", "jaw_deg")):
        raise DatasetError(f"{path}: pixels, poses, extrinsics, intrinsics or jaw_deg hold NaN or inf")
    return FrameDataset(**arrays, meta=meta)
