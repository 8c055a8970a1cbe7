"""A library of valid initial grasps, and the projection of a noisy needle pose onto the nearest.

A needle pose from vision carries errors of a millimetre or a few degrees; one that puts the wire
inside a jaw, or the needle where no trained start lies, leaves the policy far from anything it
was trained on (the paper's real-world failure, §V-C). The library holds ``n`` needle poses in the
grasping end-effector frame e_g, each from the paper's initial-grasp distribution with a
collision-free start and goal (``RegraspEnv.reset``'s draws). The distance is the success test's
two terms on one scale: ``|dp| in mm + angle in degrees / 5`` (1 mm and 5 degrees weigh the same).

Built by ``python -m regrasp_mjx.grasps``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from pathlib import Path

import numpy as np

from regrasp_mjx.core.atomic import atomic_write, dumps
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.world.testsets import make_testset

DEFAULT_LIBRARY = Path(__file__).resolve().parents[1] / "data" / "grasps1000.npz"
ANGLE_WEIGHT_DEG = 5.0  # degrees that weigh as much as one millimetre


def pose_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``|p_a - p_b|`` [mm] + ``angle(q_a, q_b)`` [deg] / 5, broadcasting over leading axes."""
    dp = np.linalg.norm(a[..., :3] - b[..., :3], axis=-1) * 1e3
    qa = a[..., 3:] / np.linalg.norm(a[..., 3:], axis=-1, keepdims=True)
    qb = b[..., 3:] / np.linalg.norm(b[..., 3:], axis=-1, keepdims=True)
    dot = np.clip(np.abs(np.sum(qa * qb, axis=-1)), 0.0, 1.0)
    return dp + np.degrees(2.0 * np.arccos(dot)) / ANGLE_WEIGHT_DEG


class GraspLibrary:
    """Needle poses ``[n, 7]`` (e_g frame, ``[x, y, z, qw, qx, qy, qz]``) and their grasps ``[n, 4]``."""

    def __init__(self, needle: np.ndarray, grasp: np.ndarray, meta: dict):
        self.needle, self.grasp, self.meta = needle, grasp, meta

    @classmethod
    def make(cls, n: int = 1000, seed: int = 7, env_config=None) -> GraspLibrary:

        env_config = env_config or EnvConfig(check_actions=False)
        ep = make_testset(n, seed, env_config)
        needle = np.concatenate([ep.needle_pos, ep.needle_quat], axis=1)

        return cls(needle, np.asarray(ep.grasp), {"n": n, "seed": seed, "env": dataclasses.asdict(env_config)})

    def save(self, path: str | os.PathLike) -> None:

        meta = dumps(self.meta)
        atomic_write(Path(path), lambda f: np.savez(f, needle=self.needle, grasp=self.grasp, meta=np.array(meta)))

    @classmethod
    def load(cls, path: str | os.PathLike) -> GraspLibrary:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"grasp library not found: {path} (make one with python -m regrasp_mjx.grasps)")
        with np.load(path, allow_pickle=False) as f:
            needle, grasp, meta = f["needle"], f["grasp"], json.loads(str(f["meta"]))
        if needle.ndim != 2 or needle.shape[1] != 7 or not np.all(np.isfinite(needle)):
            raise ValueError(f"{path}: needle must be finite [n, 7], got {needle.shape}")
        return cls(needle, grasp, meta)

    @classmethod
    @functools.cache
    def default(cls) -> GraspLibrary:
        return cls.load(DEFAULT_LIBRARY)

    def nearest(self, needle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index and distance of the nearest library pose for each needle pose ``[..., 7]``
        (:func:`pose_distance`, against the library's unit quaternions made once; 1024 needles at a
        time, so a large batch holds no ``[n, library]`` array)."""
        needle = np.asarray(needle, np.float64)
        flat = needle.reshape(-1, 7)
        positions, quats, _ = self.unit_arrays
        index, dist = np.empty(len(flat), np.int64), np.empty(len(flat))
        for a in range(0, len(flat), 1024):
            x = flat[a : a + 1024]
            q = x[:, 3:] / np.linalg.norm(x[:, 3:], axis=1, keepdims=True)
            d = np.linalg.norm(x[:, None, :3] - positions, axis=-1) * 1e3
            d += np.degrees(2.0 * np.arccos(np.minimum(np.abs(q @ quats.T), 1.0))) / ANGLE_WEIGHT_DEG
            index[a : a + 1024] = np.argmin(d, axis=1)
            dist[a : a + 1024] = d[np.arange(len(x)), index[a : a + 1024]]
        return index.reshape(needle.shape[:-1]), dist.reshape(needle.shape[:-1])

    @functools.cached_property
    def unit_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions ``[n, 3]`` and unit quaternions ``[n, 4]`` of the library's needle poses as
        contiguous float64, and both as float32 columns ``[7, n]`` (what the lean planner's compiled
        nearest-grasp search takes)."""
        q = self.needle[:, 3:] / np.linalg.norm(self.needle[:, 3:], axis=1, keepdims=True)
        columns = np.ascontiguousarray(np.concatenate([self.needle[:, :3], q], axis=1).T, np.float32)
        return np.ascontiguousarray(self.needle[:, :3], np.float64), np.ascontiguousarray(q, np.float64), columns

    def project(self, needle: np.ndarray) -> np.ndarray:
        """The nearest valid library pose for each needle pose ``[..., 7]``."""
        return self.needle[self.nearest(needle)[0]]
