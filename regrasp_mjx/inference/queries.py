"""What a query asks and how it is checked: poses, the goal grasp and needle (:class:`TaskSpec`),
each checked against what a policy was trained for (:class:`TaskRanges`), and the warnings for
starts and needles far from anything trained on.

Every entry point of a policy (``plan``, ``plan_from_camera``, ``closed_loop_step``, ``execute``)
takes the same six goal-grasp and needle keywords; they are one :class:`TaskSpec` here, resolved
once into each query's goal grasp ``[n, 4]`` and needle ``[n, 2]``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from typing import Any

import numpy as np

from regrasp_mjx.core.geometry import QUAT_NORM_TOLERANCE, unit_quaternions
from regrasp_mjx.inference.grasps import GraspLibrary

START_WARN_MM = 60.0  # a start this far from its needle is no regrasping problem we trained on
OOD_WARN_DISTANCE = 4.0  # nearest-grasp distance (mm + deg/5) beyond which a plan warns (fresh draws: p99 2.7)


class PoseError(ValueError):
    """A pose that is not a finite 7-vector ``[x, y, z, qw, qx, qy, qz]`` with a unit quaternion."""


def check_poses(name: str, poses: Any) -> np.ndarray:
    """``poses[..., 7]`` as float64 with unit quaternions, or a :class:`PoseError` saying why not."""
    try:
        arr = np.asarray(poses, np.float64)
    except (TypeError, ValueError):  # a string, a ragged list, None ...
        raise PoseError(
            f"{name}={poses!r:.60} is not accepted: numbers, (7,) or (B, 7) = [x, y, z, qw, qx, qy, qz] in metres"
        ) from None
    if arr.shape == (7,):  # one good pose in scalar arithmetic: numpy's calls would cost more than a lean plan
        x = arr.tolist()
        norm = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5] + x[6] * x[6])
        if all(map(math.isfinite, x)) and abs(norm - 1.0) <= QUAT_NORM_TOLERANCE:
            return np.array(x[:3] + [v / norm for v in x[3:]])
    if arr.ndim not in (1, 2) or arr.shape[-1] != 7:
        raise PoseError(f"{name} has shape {arr.shape}; accepted: (7,) or (B, 7) = [x, y, z, qw, qx, qy, qz] in metres")
    if arr.shape[0] == 0:
        raise PoseError(f"{name} has shape {arr.shape}: an empty batch; accepted: at least one pose")
    if not np.all(np.isfinite(arr)):
        raise PoseError(f"{name} has NaN or inf; accepted: finite values")
    return np.concatenate([arr[..., :3], unit_quaternions(name, arr[..., 3:], PoseError)], axis=-1)


def batch_poses(**named: Any) -> tuple[list[np.ndarray], bool]:
    """Checked poses ``[B, 7]`` of one batch size (each given as a 7-vector or ``[B, 7]``), in the
    order named, and whether one query was given; a :class:`PoseError` names the poses that differ."""
    poses = [check_poses(name, p) for name, p in named.items()]
    single = poses[0].ndim == 1
    poses = [np.atleast_2d(p) for p in poses]
    if len({p.shape for p in poses}) > 1:
        shapes = ", ".join(f"{name} {p.shape}" for name, p in zip(named, poses))
        raise PoseError(f"poses differ in batch size: {shapes}")
    return poses, single


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """A query's goal grasp and needle, each None (the policy's own: the task's goal grasp, the
    middle of the trained depth range, the scene's needle), a scalar or one value per query.
    Angles in radians, lengths in millimetres."""

    goal_alpha_rad: Any = None
    goal_depth_mm: Any = None
    goal_theta_rad: Any = None
    goal_phi_rad: Any = None
    needle_radius_mm: Any = None
    wire_radius_mm: Any = None

    @classmethod
    def of(cls, task: dict[str, Any]) -> TaskSpec:
        """From keyword arguments; an unknown name is a :class:`PoseError` listing the accepted ones."""
        if not task:
            return PLAIN
        unknown = set(task) - set(TASK_FIELDS)
        if unknown:
            raise PoseError(
                f"{', '.join(sorted(unknown))} is not accepted; the goal grasp and needle: {', '.join(TASK_FIELDS)}"
            )
        return cls(**task)

    def __post_init__(self) -> None:
        # nothing given: the policy's own goal grasp and needle (looked at on every plan: kept)
        object.__setattr__(self, "plain", all(getattr(self, f) is None for f in TASK_FIELDS))


TASK_FIELDS = tuple(f.name for f in dataclasses.fields(TaskSpec))
PLAIN = TaskSpec()  # no goal grasp or needle given
_COLUMN = {name: col for col, name in enumerate(TASK_FIELDS)}


# keyword sets whose vectors TaskRanges.keywords_vector keeps (a task's distinct needles and goals)
MEMO_SIZE = 1024


@dataclasses.dataclass(frozen=True)
class TaskRanges:
    """What a policy was trained for: each :class:`TaskSpec` field's default, low and high (one
    value twice where it was fixed), and whether theta* spans a full turn."""

    default: np.ndarray
    low: np.ndarray
    high: np.ndarray
    general: bool

    @classmethod
    def of(cls, env: Any) -> TaskRanges:
        """The ranges of an :class:`~regrasp_mjx.core.config.EnvConfig`."""
        task = env.task
        spans = {
            "goal_alpha_rad": task.span("goal_alpha_range_rad", task.goal_alpha_rad),
            "goal_depth_mm": tuple(float(v) for v in task.goal_depth_mm),
            "goal_theta_rad": task.span("goal_theta_range_rad", task.goal_theta_rad),
            "goal_phi_rad": task.span("goal_phi_range_rad", task.goal_phi_rad),
            "needle_radius_mm": task.span("needle_radius_range_mm", env.scene.needle_radius_mm),
            "wire_radius_mm": task.span("wire_radius_range_mm", env.scene.wire_radius_mm),
        }
        default = {
            "goal_alpha_rad": task.goal_alpha_rad,
            "goal_depth_mm": sum(task.goal_depth_mm) / 2,
            "goal_theta_rad": task.goal_theta_rad,
            "goal_phi_rad": task.goal_phi_rad,
            "needle_radius_mm": env.scene.needle_radius_mm,
            "wire_radius_mm": env.scene.wire_radius_mm,
        }
        arr = lambda xs: np.array([xs[f] for f in TASK_FIELDS], np.float64)  # noqa: E731
        return cls(
            arr(default),
            arr({f: s[0] for f, s in spans.items()}),
            arr({f: s[1] for f, s in spans.items()}),
            task.general,
        )

    def as_dict(self) -> dict[str, tuple[float, float]]:
        return {f: (float(lo), float(hi)) for f, lo, hi in zip(TASK_FIELDS, self.low, self.high)}

    def values(self, n: int, spec: TaskSpec) -> np.ndarray:
        """``[n, 6]`` of the :data:`TASK_FIELDS` for ``n`` queries, theta* wrapped into a full trained
        turn, each checked against the trained range: a :class:`PoseError` names the range (a
        specialist's is one value)."""
        values = np.empty((n, len(TASK_FIELDS)))
        values[:] = self.default
        for col, name in enumerate(TASK_FIELDS):
            given = getattr(spec, name)
            if given is not None:
                values[:, col] = np.asarray(given, np.float64)
        lo, hi = self.low, self.high
        if hi[2] - lo[2] >= 2 * np.pi - 1e-6:  # any azimuth: wrapped into the trained turn
            values[:, 2] = lo[2] + np.mod(values[:, 2] - lo[2], 2 * np.pi)
        tol = 1e-6 * np.maximum(1.0, np.abs(hi))
        bad = ~np.isfinite(values) | (values < lo - tol) | (values > hi + tol)
        if bad.any():
            row, col = (int(v) for v in np.argwhere(bad)[0])
            name = TASK_FIELDS[col]
            trained = f"{lo[col]:.6g}" if lo[col] == hi[col] else f"[{lo[col]:.6g}, {hi[col]:.6g}]"
            hint = "" if self.general else " (a specialist: load_policy('general') plans any goal grasp and needle)"
            where = f" (query {row})" if n > 1 else ""
            raise PoseError(
                f"{name}={values[row, col]:.6g}{where} is not accepted: this policy was trained for {name} = "
                f"{trained}{hint}"
            )
        return values

    def resolve(self, n: int, spec: TaskSpec) -> tuple[np.ndarray, np.ndarray]:
        """Each query's goal grasp ``[n, 4]`` = ``(alpha*, d* [m], theta*, phi*)`` and needle ``[n, 2]``
        = ``(R, wire radius)`` [m] (see :meth:`values`); one plain query's is made once (read-only)."""
        return self._plain if n == 1 and spec.plain else self._in_metres(self.values(n, spec))

    @staticmethod
    def _in_metres(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        grasp = values[:, :4].copy()
        grasp[:, 1] *= 1e-3
        return grasp, values[:, 4:] * 1e-3

    def vector(self, spec: TaskSpec) -> np.ndarray:
        """One query's ``(alpha*, d*, theta*, phi*, R, wire)`` [m], as the lean planner takes it; any
        input :meth:`keywords_vector` does not take, or a value out of range, goes through
        :meth:`resolve` (which names it)."""
        if spec.plain:
            return self._plain_vector
        v = self.keywords_vector({name: getattr(spec, name) for name in TASK_FIELDS})
        return self._vector_of(spec) if v is None else v

    def keywords_vector(self, task: dict[str, Any]) -> np.ndarray | None:
        """:meth:`vector` of ``Policy.plan``'s keywords as given (no :class:`TaskSpec` made), or None
        where a name is unknown, a value is not a scalar or None, or a value is out of range: the
        caller's checks then name it. Checked in plain floats (numpy's calls, and making the spec,
        would cost a tenth of a lean plan), and kept for the same keywords again: the vector is
        shared, to be read only."""
        if not task:
            return self._plain_vector
        key = tuple(task.items())
        try:  # the same keywords again (a needle's radii on every query): the vector made for them
            return self._memo[key]
        except (KeyError, TypeError):  # new, or an unhashable value (not a scalar: refused below)
            pass
        (lo, hi), values = self._bounds, self._default_list.copy()
        for name, given in task.items():
            col = _COLUMN.get(name)
            if col is None or not (given is None or isinstance(given, (float, int, np.floating, np.integer))):
                return None
            if given is not None:
                values[col] = float(given)
        if hi[2][0] - lo[2][0] >= 2 * math.pi - 1e-6:  # any azimuth: wrapped into the trained turn
            values[2] = lo[2][0] + (values[2] - lo[2][0]) % (2 * math.pi)
        if not all(math.isfinite(v) and lo[c][1] <= v <= hi[c][1] for c, v in enumerate(values)):
            return None
        vector = np.array([values[0], values[1] * 1e-3, values[2], values[3], values[4] * 1e-3, values[5] * 1e-3])
        if len(self._memo) < MEMO_SIZE:
            self._memo[key] = vector
        return vector

    @functools.cached_property
    def _memo(self) -> dict[tuple, np.ndarray]:
        return {}

    def _vector_of(self, spec: TaskSpec) -> np.ndarray:
        grasp, radii = self.resolve(1, spec)
        return np.concatenate([grasp[0], radii[0]])

    @functools.cached_property
    def _default_list(self) -> list[float]:
        return self.default.tolist()

    @functools.cached_property
    def _bounds(self) -> tuple[list, list]:
        """``(low, low less tolerance)`` and ``(high, high plus tolerance)`` per field, as :meth:`values` checks."""
        tol = 1e-6 * np.maximum(1.0, np.abs(self.high))
        return list(zip(self.low.tolist(), (self.low - tol).tolist())), list(
            zip(self.high.tolist(), (self.high + tol).tolist())
        )

    @functools.cached_property
    def _plain(self) -> tuple[np.ndarray, np.ndarray]:
        out = self._in_metres(self.values(1, PLAIN))
        for x in out:
            x.flags.writeable = False
        return out

    @functools.cached_property
    def _plain_vector(self) -> np.ndarray:
        return np.concatenate([self._plain[0][0], self._plain[1][0]])


def start_distance_mm(needle: np.ndarray, start: np.ndarray) -> np.ndarray:
    """``[n]`` distances of starts ``[n, 7]`` from their needles ``[n, 7]``, mm."""
    if len(start) == 1:  # one query: plain floats (numpy's calls would cost as much as a lean plan)
        return np.array([math.dist(start[0, :3].tolist(), needle[0, :3].tolist()) * 1e3])
    return np.linalg.norm(start[:, :3] - needle[:, :3], axis=1) * 1e3


def far_starts(needle: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Which starts ``[n, 7]`` lie implausibly far from their needles ``[n, 7]`` (beyond
    :data:`START_WARN_MM`; every trained start lies within about 30 mm): a bool ``[n]``."""
    return start_distance_mm(np.asarray(needle), np.asarray(start)) > START_WARN_MM


def warn_far_starts(distance_mm: np.ndarray, stacklevel: int = 4) -> None:
    """Warns about starts implausibly far from their needle (e.g. given in millimetres, not metres)."""
    far = distance_mm > START_WARN_MM
    if far.any():
        warnings.warn(
            f"start {int(np.argmax(far))} is {float(distance_mm[far][0]):.4g} mm from its needle (beyond "
            f"{START_WARN_MM:g} mm, where no start was trained): poses are in metres; check the units and the frame",
            stacklevel=stacklevel,
        )


def nearest_grasps(needle: np.ndarray) -> np.ndarray:
    """Each needle pose's ``[n, 7]`` distance to the nearest valid grasp of the library."""
    return GraspLibrary.default().nearest(needle)[1]


def warn_far_grasps(distance: np.ndarray, stacklevel: int = 4) -> None:
    """Warns about needle poses far from every valid grasp of the library (a paper-task policy's)."""
    far = distance > OOD_WARN_DISTANCE
    if np.any(far):
        warnings.warn(
            f"needle pose {int(np.argmax(far))} is {float(distance[far][0]):.2f} (mm + deg/5) from the nearest "
            f"valid grasp of the library (beyond {OOD_WARN_DISTANCE}): far from anything trained on; "
            "project it with regrasp_mjx.grasps.GraspLibrary.project or check the pose estimate",
            stacklevel=stacklevel,
        )
