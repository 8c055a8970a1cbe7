"""The paper's start and goal distributions (§IV; SPEC "Distributions") and test-set files.

An :class:`Episode` is one regrasping problem, every pose in the grasping end-effector frame e_g
(the world frame of the scene). :func:`draw_episode` draws one from the distributions;
:func:`sample_episode` redraws until neither the start nor the goal pose collides. Both are pure
JAX and run under jit and vmap. Test sets are ``.npz`` files of plain arrays plus a JSON ``meta``
string; :func:`load_testset` validates them and never unpickles.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from regrasp_mjx.core import geometry
from regrasp_mjx.core.atomic import atomic_write, dumps
from regrasp_mjx.core.config import SceneConfig, TaskConfig

# The paper300 test set (SPEC seed 2021), shipped inside the package so that an installed copy finds it
# (experiments/testsets/paper300.npz is a link to this file).
PAPER300 = Path(__file__).resolve().parents[1] / "data" / "paper300.npz"
# The general task's test set (issue 15): 1000 problems from config.GENERAL_TASK's full ranges, seed 2026,
# `python -m regrasp_mjx.testset --task general --n 1000 --seed 2026` (experiments/testsets links to it).
GENERAL1000 = Path(__file__).resolve().parents[1] / "data" / "general1000.npz"
TESTSETS = {"paper300": PAPER300, "general1000": GENERAL1000}  # the shipped test sets, by name
DEFAULT_TESTSET = PAPER300  # what every command reports on unless told (train, distill, evaluate, sweep)

TESTSET_FORMAT = "regrasp_mjx.testset"
TESTSET_VERSION = 1


@struct.dataclass
class Episode:
    """One regrasping problem. Positions in metres, quaternions wxyz, all in the e_g frame.

    Attributes:
      needle_pos, needle_quat: the needle frame n (held by the grasping tool, never moves).
      start_pos, start_quat: the regrasping end-effector at the start.
      goal_pos, goal_quat: the regrasping end-effector at the goal.
      grasp: the initial grasp ``(alpha [rad], depth [m], theta [rad], phi [rad])``.
      goal_depth: the goal's depth d* [m].
      goal_grasp: the goal grasp ``(alpha* [rad], d* [m], theta* [rad], phi* [rad])``; None where
        not known (then the goal is only its pose).
      needle_radius, wire_radius: this problem's needle [m]; None: the environment's scene's.
    """

    needle_pos: jax.Array
    needle_quat: jax.Array
    start_pos: jax.Array
    start_quat: jax.Array
    goal_pos: jax.Array
    goal_quat: jax.Array
    grasp: jax.Array
    goal_depth: jax.Array
    goal_grasp: jax.Array | None = None
    needle_radius: jax.Array | None = None
    wire_radius: jax.Array | None = None

    def __len__(self) -> int:
        return int(self.needle_pos.shape[0]) if self.needle_pos.ndim == 2 else 1

    @classmethod
    def from_poses(
        cls, needle: jax.Array, start: jax.Array, goal: jax.Array, radii: jax.Array | None = None
    ) -> Episode:
        """A batch of problems from ``[B, 7]`` needle, start and goal poses (the grasps unknown:
        zeros), on needles ``radii`` ``[B, 2]`` (radius, wire radius [m]; None: the scene's)."""
        zeros = jnp.zeros((needle.shape[0], 4))
        poses = (needle[:, :3], needle[:, 3:], start[:, :3], start[:, 3:], goal[:, :3], goal[:, 3:])
        radius, wire_radius = (None, None) if radii is None else (radii[:, 0], radii[:, 1])
        return cls(*poses, zeros, zeros[:, 0], needle_radius=radius, wire_radius=wire_radius)

    def row(self, i: Any) -> Episode:
        """The i-th problem of a batch, or the problems ``i`` picks (a slice, indices or a mask)."""
        return jax.tree.map(lambda x: x[i], self)

    def problem(self, i: int) -> dict[str, Any]:
        """The i-th problem of a batch as a planner job (:mod:`regrasp_mjx.planning.pool`): needle,
        start and goal 7-vectors, and the needle's radii [m] where the problem names them."""
        out: dict[str, Any] = {
            "needle": np.r_[self.needle_pos[i], self.needle_quat[i]],
            "start": np.r_[self.start_pos[i], self.start_quat[i]],
            "goal": np.r_[self.goal_pos[i], self.goal_quat[i]],
        }
        for name in ("needle_radius", "wire_radius"):
            if getattr(self, name) is not None:
                out[name] = float(np.asarray(getattr(self, name))[i])
        return out


FIELD_SHAPES: dict[str, tuple[int, ...]] = {
    "needle_pos": (3,),
    "needle_quat": (4,),
    "start_pos": (3,),
    "start_quat": (4,),
    "goal_pos": (3,),
    "goal_quat": (4,),
    "grasp": (4,),
    "goal_depth": (),
    "goal_grasp": (4,),
    "needle_radius": (),
    "wire_radius": (),
}
# fields a file written before the general task (issue 15) lacks: filled in from its meta on load
ADDED_FIELDS = ("goal_grasp", "needle_radius", "wire_radius")
FIELD_DOCS: dict[str, str] = {
    "needle_pos": "needle frame origin in e_g [m]",
    "needle_quat": "needle frame orientation in e_g [wxyz]",
    "start_pos": "regrasping end-effector at the start, in e_g [m]",
    "start_quat": "regrasping end-effector orientation at the start, in e_g [wxyz]",
    "goal_pos": "regrasping end-effector at the goal, in e_g [m]",
    "goal_quat": "regrasping end-effector orientation at the goal, in e_g [wxyz]",
    "grasp": "initial grasp (alpha [rad], depth [m], theta [rad], phi [rad])",
    "goal_depth": "goal depth d* [m]",
    "goal_grasp": "goal grasp (alpha* [rad], d* [m], theta* [rad], phi* [rad])",
    "needle_radius": "needle radius R [m]",
    "wire_radius": "needle wire radius [m]",
}


def _uniform(key: jax.Array, rng: tuple[float, float], scale: float = 1.0) -> jax.Array:
    return jax.random.uniform(key, (), minval=rng[0] * scale, maxval=rng[1] * scale)


def goal_in_needle(task: TaskConfig, goal_depth: jax.Array, radius: float, goal_angles=None) -> geometry.Pose:
    """The goal end-effector pose ``T_n_er*`` for a goal depth (metres) on a needle of ``radius``;
    ``goal_angles`` ``(alpha*, theta*, phi*)`` default to the task's fixed goal grasp."""
    alpha, theta, phi = goal_angles or (task.goal_alpha_rad, task.goal_theta_rad, task.goal_phi_rad)
    return geometry.grasp_pose(alpha, goal_depth, theta, phi, radius)


def _draw_or_fixed(key: jax.Array, rng: tuple[float, float]):
    """A uniform draw from ``rng``, or the fixed value itself where the range is one value: a task
    without ranges then computes exactly what it did before ranges existed."""
    return rng[0] if rng[0] == rng[1] else _uniform(key, rng)


def draw_episode(key: jax.Array, task: TaskConfig, radius: float, wire: float | None = None) -> Episode:
    """One draw from the distributions, without the collision test.

    The start: the point ``start_distance`` from the needle centre on the ray through the goal
    end-effector position, each needle-frame axis moved by ``U(-noise, noise)``; the goal
    orientation turned by ``U(-rot_noise, rot_noise)`` about a uniformly random unit axis (applied
    in the needle frame). ``radius`` and ``wire`` [m] are the needle's where the task draws none
    (``wire`` None: the default scene's).
    With a needle-radius range the start lies as far beyond the goal as ``start_distance`` puts it
    for the reference needle (``geometry.NEEDLE_RADIUS``) with the same goal grasp.
    """
    k = jax.random.split(key, 9)
    grasp = jnp.stack(
        [
            _uniform(k[0], task.init_alpha_rad),
            _uniform(k[1], task.init_depth_mm, 1e-3),
            _uniform(k[2], task.init_theta_rad),
            _uniform(k[3], task.init_phi_rad),
        ]
    )
    goal_depth = _uniform(k[4], task.goal_depth_mm, 1e-3)
    # the general task's draws come from a key of their own (k[8]), so the paper's draws are unchanged
    g = jax.random.split(k[8], 5)
    angles = (
        _draw_or_fixed(g[0], task.span("goal_alpha_range_rad", task.goal_alpha_rad)),
        _draw_or_fixed(g[1], task.span("goal_theta_range_rad", task.goal_theta_rad)),
        _draw_or_fixed(g[2], task.span("goal_phi_range_rad", task.goal_phi_rad)),
    )
    wire = SceneConfig().wire_radius_mm * 1e-3 if wire is None else wire
    if task.needle_radius_range_mm is not None:
        radius = _uniform(g[3], task.needle_radius_range_mm, 1e-3)
    if task.wire_radius_range_mm is not None:
        wire = _uniform(g[4], task.wire_radius_range_mm, 1e-3)
    needle = geometry.inverse(geometry.grasp_pose(grasp[0], grasp[1], grasp[2], grasp[3], radius))
    goal_n = goal_in_needle(task, goal_depth, radius, angles)
    norm = jnp.linalg.norm(goal_n[0])
    direction = goal_n[0] / norm
    distance = task.start_distance_mm * 1e-3
    if task.needle_radius_range_mm is not None:  # as far beyond the goal as for the reference needle
        reference = goal_in_needle(task, goal_depth, geometry.NEEDLE_RADIUS, angles)[0]
        distance = distance + norm - jnp.linalg.norm(reference)
    noise = task.start_pos_noise_mm * 1e-3
    start_pos_n = distance * direction + jax.random.uniform(k[5], (3,), minval=-noise, maxval=noise)
    axis = jax.random.normal(k[6], (3,))
    axis = axis / jnp.linalg.norm(axis)
    angle = jax.random.uniform(k[7], (), minval=-1.0, maxval=1.0) * math.radians(task.start_rot_noise_deg)
    start_quat_n = geometry.quat_mul(geometry.quat_from_rotvec(axis * angle), goal_n[1])
    start = geometry.compose(needle, (start_pos_n, start_quat_n))
    goal = geometry.compose(needle, goal_n)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return Episode(
        needle_pos=needle[0],
        needle_quat=needle[1],
        start_pos=start[0],
        start_quat=start[1],
        goal_pos=goal[0],
        goal_quat=goal[1],
        grasp=grasp,
        goal_depth=goal_depth,
        goal_grasp=jnp.stack([f32(angles[0]), f32(goal_depth), f32(angles[1]), f32(angles[2])]),
        needle_radius=f32(radius),
        wire_radius=f32(wire),
    )


def sample_episode(
    key: jax.Array, task: TaskConfig, radius: float, distance_fn: Callable[..., jax.Array], wire: float | None = None
) -> tuple[Episode, jax.Array]:
    """Draws until neither the start nor the goal pose collides (SPEC: such starts are redrawn).
    ``distance_fn(needle_pos, needle_quat, ee_pos, ee_quat[, needle])`` is a scene's
    (:meth:`regrasp_mjx.world.scene.Scene.distance_fn`); where the task draws the needle, it is called
    with ``needle=(radius, wire)`` of the draw.

    Returns:
      ``(episode, valid)``: ``valid`` is False only if ``task.max_sample_tries`` draws all collided
      (the last draw is returned then); with the default distributions this does not happen.
    """

    def is_free(ep: Episode) -> jax.Array:
        needle = (ep.needle_radius, ep.wire_radius) if task.varies_needle else ()
        start = distance_fn(ep.needle_pos, ep.needle_quat, ep.start_pos, ep.start_quat, *needle)
        goal = distance_fn(ep.needle_pos, ep.needle_quat, ep.goal_pos, ep.goal_quat, *needle)
        return (jnp.min(start) > 0.0) & (jnp.min(goal) > 0.0)

    def body(carry):
        key, _, tries, _ = carry
        key, sub = jax.random.split(key)
        ep = draw_episode(sub, task, radius, wire)
        return key, ep, tries + 1, is_free(ep)

    def cond(carry):
        _, _, tries, valid = carry
        return (~valid) & (tries < task.max_sample_tries)

    shapes = jax.eval_shape(lambda k: draw_episode(k, task, radius, wire), key)
    empty = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    _, ep, _, valid = jax.lax.while_loop(cond, body, (key, empty, jnp.int32(0), jnp.bool_(False)))
    return ep, valid


# ----------------------------------------------------------------------------------------------
# Test-set files.
# ----------------------------------------------------------------------------------------------
class TestsetError(ValueError):
    """A test-set file that is missing, unreadable, or has wrong keys, shapes or values."""

    __test__ = False  # not a pytest class, despite its name


def save_testset(path: str | os.PathLike, episodes: Episode, meta: dict[str, Any]) -> Path:
    """Writes ``episodes`` (a batch) and ``meta`` to ``path`` atomically (temp file + rename)."""
    path = Path(path)
    arrays = {name: np.asarray(getattr(episodes, name), dtype=np.float64) for name in FIELD_SHAPES}
    meta = {"format": TESTSET_FORMAT, "version": TESTSET_VERSION, "n": len(episodes), "fields": FIELD_DOCS, **meta}
    atomic_write(path, lambda f: np.savez_compressed(f, meta=np.array(dumps(meta, sort_keys=True)), **arrays))
    return path


def episode_poses(ep) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Needle, start and goal poses ``[N, 7]`` of test-set rows (the inputs of ``Policy.plan``)."""
    cat = lambda p, q: np.concatenate([p, q], axis=1)  # noqa: E731
    return (
        cat(ep.needle_pos, ep.needle_quat),
        cat(ep.start_pos, ep.start_quat),
        cat(ep.goal_pos, ep.goal_quat),
    )


def episode_needles(ep) -> dict[str, np.ndarray]:
    """The needles of test-set rows as ``Policy.plan`` takes them (``needle_radius_mm``, ``wire_radius_mm``)."""
    return {
        "needle_radius_mm": np.asarray(ep.needle_radius, np.float64) * 1e3,
        "wire_radius_mm": np.asarray(ep.wire_radius, np.float64) * 1e3,
    }


def testset_path(name_or_path: str | os.PathLike) -> Path:
    """The file of a shipped test set named in :data:`TESTSETS` (a name that is no existing path),
    else ``name_or_path``."""
    if str(name_or_path) in TESTSETS and not Path(name_or_path).exists():
        return TESTSETS[str(name_or_path)]
    return Path(name_or_path)


def load_testset(path: str | os.PathLike) -> tuple[Episode, dict[str, Any]]:
    """Reads and validates a test-set file written by :func:`save_testset`, or a shipped one by
    name (:data:`TESTSETS`: ``paper300``, ``general1000``).

    Returns:
      ``(episodes, meta)``: numpy arrays (float64) with a leading row axis, and the JSON metadata.

    Raises:
      TestsetError: missing file, missing keys, wrong shapes, NaN/inf, non-unit quaternions
        (beyond ``geometry.QUAT_NORM_TOLERANCE``; within it they are normalised).
    """
    path = testset_path(path)
    if not path.is_file():
        raise TestsetError(
            f"test-set file not found: {path}; accepted: a shipped name ({', '.join(TESTSETS)}) or an .npz "
            "file (make one with `python -m regrasp_mjx.testset`)"
        )
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic[:2] != b"PK":  # np.load would read other files as pickles and blame that
        raise TestsetError(f"{path} is not an .npz test-set file (it does not start as a zip archive does)")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except Exception as err:  # zip or header errors all mean the same to the user
        raise TestsetError(f"{path} is not a readable .npz test-set file: {err}") from err
    if "meta" in data and "goal_depth" in data:
        _fill_added_fields(data, path)
    missing = [k for k in (*FIELD_SHAPES, "meta") if k not in data]
    if missing:
        raise TestsetError(f"{path} lacks keys {missing}; a test set holds {sorted([*FIELD_SHAPES, 'meta'])}")
    try:
        meta = json.loads(str(data["meta"]))
    except json.JSONDecodeError as err:
        raise TestsetError(f"{path}: 'meta' is not valid JSON: {err}") from err
    n = data["needle_pos"].shape[0] if data["needle_pos"].ndim == 2 else -1
    if n < 1:
        raise TestsetError(f"{path}: needle_pos must have shape (N, 3) with N >= 1, got {data['needle_pos'].shape}")
    fields = {}
    for name, shape in FIELD_SHAPES.items():
        arr = np.asarray(data[name])
        if arr.shape != (n, *shape) or not np.issubdtype(arr.dtype, np.floating):
            raise TestsetError(
                f"{path}: {name} must be a float array of shape {(n, *shape)}, got {arr.dtype} {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            row = int(np.argwhere(~np.isfinite(arr))[0][0])
            raise TestsetError(f"{path}: {name} has NaN or inf (row {row}); all values must be finite")
        fields[name] = geometry.unit_quaternions(f"{path}: {name}", arr, TestsetError) if name.endswith("quat") else arr
    for name, lo, hi in (("needle_radius", 1e-3, 20e-3), ("wire_radius", 0.05e-3, 1e-3)):
        bad = np.flatnonzero((fields[name] < lo - 1e-12) | (fields[name] > hi + 1e-12))
        if bad.size:
            raise TestsetError(
                f"{path}: {name} {float(fields[name][bad[0]]):g} in row {bad[0]} is out of range; "
                f"accepted: [{lo:g}, {hi:g}] m"
            )
    return Episode(**fields), meta


def _fill_added_fields(data: dict[str, np.ndarray], path: Path) -> None:
    """A file from before the general task: its one needle and goal grasp from its meta (the
    defaults where the meta does not say), broadcast over its rows."""
    try:
        meta = json.loads(str(data["meta"]))
    except json.JSONDecodeError:
        return  # reported by the caller
    scene, task = meta.get("scene", {}), meta.get("task", {})
    defaults = TaskConfig()
    n = np.asarray(data["goal_depth"]).shape[:1]
    if "needle_radius" not in data:
        data["needle_radius"] = np.full(n, scene.get("needle_radius_mm", 5.4) * 1e-3)
    if "wire_radius" not in data:
        data["wire_radius"] = np.full(n, scene.get("wire_radius_mm", 0.25) * 1e-3)
    if "goal_grasp" not in data:
        angles = [task.get(k, getattr(defaults, k)) for k in ("goal_alpha_rad", "goal_theta_rad", "goal_phi_rad")]
        depth = np.asarray(data["goal_depth"], np.float64)
        data["goal_grasp"] = np.stack(
            [np.full(n, angles[0]), depth, np.full(n, angles[1]), np.full(n, angles[2])], axis=-1
        )
