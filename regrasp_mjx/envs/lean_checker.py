"""The OMPL planners' fast collision checker (``checker="lean"``): :class:`LeanChecker`, the
verdicts of :class:`regrasp_mjx.envs.host.HostChecker` from :mod:`regrasp_mjx.envs.lean_collision`'s
compiled capsule tests, one pose or one whole motion a call."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from regrasp_mjx.core.config import is_number, require
from regrasp_mjx.envs.host import MARGIN_ACCEPTED
from regrasp_mjx.envs.lean_collision import (
    Capsules,
    Fixed,
    Held,
    capsules,
    collides,
    fixed_ends,
    hold,
    make_scratch,
    motion_collides,
)
from regrasp_mjx.envs.lean_geometry import conj, log_rotation, qexp, qmul, unit
from regrasp_mjx.world.continuous import STEP_DP, STEP_DROT
from regrasp_mjx.world.scene import Scene, load_scene


@njit(cache=True)
def _unit_collides(geo, fixed, x, y, z, qw, qx, qy, qz, threshold, tool, tool_mid):
    """:func:`collides` of the pose ``(x, y, z, qw, qx, qy, qz)``, its quaternion normalised (as
    MuJoCo's kinematics does for the host checker)."""
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return collides(geo, fixed, (x, y, z), (qw / n, qx / n, qy / n, qz / n), tool, tool_mid, threshold)


@njit(cache=True)
def _pose_collides(placed, x, y, z, qw, qx, qy, qz, threshold):
    """:func:`_unit_collides` around the needle ``placed`` (:meth:`LeanChecker.place`)."""
    geo_t, fixed_t, tool, tool_mid, _ = placed.state
    return _unit_collides(Capsules(*geo_t), Fixed(*fixed_t), x, y, z, qw, qx, qy, qz, threshold, tool, tool_mid)


@njit(cache=True)
def _motion_between(placed, a, b, threshold, max_dp, max_drot):
    """Whether the motion from pose ``a`` to pose ``b`` (7-vectors) around the needle ``placed``
    collides, position linear and orientation slerped the shorter way (OMPL's
    ``SO3StateSpace::interpolate``), tested as the environment steps that replay it
    (:func:`regrasp_mjx.world.continuous.pieces`), each with :func:`motion_collides`."""
    geo_t, fixed_t, tool, tool_mid, stack = placed.state
    geo, fixed = Capsules(*geo_t), Fixed(*fixed_t)
    qa = unit((a[3], a[4], a[5], a[6]))
    w = log_rotation(qmul(unit((b[3], b[4], b[5], b[6])), conj(qa)))
    dp = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    size = 0.0
    for r in range(3):
        size = max(size, abs(dp[r]) / max_dp, abs(w[r]) / max_drot)
    n = max(1, math.ceil(size - 1e-9))
    for k in range(n):
        f = k / n
        p0 = (a[0] + f * dp[0], a[1] + f * dp[1], a[2] + f * dp[2])
        q0 = qmul(qexp(f * w[0], f * w[1], f * w[2]), qa)
        step_dp, step_w = (dp[0] / n, dp[1] / n, dp[2] / n), (w[0] / n, w[1] / n, w[2] / n)
        if motion_collides(geo, fixed, p0, q0, step_dp, step_w, threshold, tool, tool_mid, stack):
            return True
    return False


@njit(cache=True)
def _placed(geo_t, varies, needle, radius, wire):
    """The needle at ``needle`` (7-vector) placed once: :class:`Fixed` as a tuple."""
    p = (needle[0], needle[1], needle[2])
    return fixed_ends(Capsules(*geo_t), varies, p, (needle[3], needle[4], needle[5], needle[6]), radius, wire)


class LeanChecker:
    """:class:`regrasp_mjx.envs.host.HostChecker`'s collision verdict (a counted pair closer than
    ``clearance_mm``; 0: penetrating) from the same capsules, tested by this module's compiled code
    instead of CPU MuJoCo: several times faster a pose, and a whole motion in one call
    (:meth:`motion_collides`). Other needles are the scene's scaled, as the environment scales them
    (:meth:`for_needle`). Not thread-safe (it owns scratch arrays)."""

    def __init__(self, scene: Scene | None = None, clearance_mm: float = 0.0):
        require(is_number(clearance_mm) and clearance_mm >= 0.0, "clearance_mm", clearance_mm, MARGIN_ACCEPTED)
        self.scene = scene if scene is not None else load_scene()
        self.clearance_mm = float(clearance_mm)
        self.margin = self.clearance_mm * 1e-3
        geo = capsules(self.scene.capsule_frames, self.scene.config.needle_radius_mm * 1e-3)
        self.geo = tuple(geo)  # a plain tuple: numba types it in C
        self.scene_needle = (geo.radius0, self.scene.config.wire_radius_mm * 1e-3)  # radius, wire [m]
        self.needle = self.scene_needle  # the one checked around (for_needle)
        self.scratch = make_scratch(geo.tool_local)
        self._last = None  # (needle pose, its placement) of the last collides call

    def for_needle(self, radius: float | None, wire: float | None) -> LeanChecker:
        """A checker of the same margin around another needle (radius and wire radius [m]; None
        keeps this one's): this checker itself when the needle is its own (within 1 nm)."""
        needle = tuple(v if x is None else float(x) for v, x in zip(self.needle, (radius, wire)))
        if _same(needle, self.needle):
            return self
        other = LeanChecker.__new__(LeanChecker)
        other.__dict__.update(self.__dict__)
        other.needle, other._last = needle, None
        other.scratch = tuple(np.empty_like(s) for s in self.scratch)
        return other

    def place(self, needle: np.ndarray) -> Held:
        """The needle at ``needle`` (7-vector) placed for :meth:`pose_collides` and :meth:`motion_collides`
        (another needle than the scene's: the scene's scaled to it, as the environment scales it),
        held with the capsules and this checker's scratch arrays as one object."""
        varies = not _same(self.needle, self.scene_needle)
        fixed = tuple(_placed(self.geo, varies, np.asarray(needle, np.float64), *self.needle))
        return hold((self.geo, fixed, *self.scratch))

    def collides(self, needle_pos, needle_quat, ee_pos, ee_quat) -> bool:
        """:meth:`regrasp_mjx.envs.host.HostChecker.collides`: whether the pose collides. The last needle's
        placement is kept (a path's poses are checked around one needle)."""
        placed = self._placed_at((*map(float, needle_pos), *map(float, needle_quat)))
        return self.pose_collides(placed, *map(float, ee_pos), *map(float, ee_quat))

    def pose_collides(self, placed: Held, x, y, z, qw, qx, qy, qz) -> bool:
        """Whether the pose collides with the needle :meth:`place` placed."""
        return _pose_collides(placed, x, y, z, qw, qx, qy, qz, self.margin)

    def motion_collides(self, placed: Held, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether any pose of the motion from ``a`` to ``b`` (7-vectors; position linear, orientation
        slerped) collides: :mod:`regrasp_mjx.world.continuous`'s test of the environment steps that replay
        it, one compiled call (:meth:`regrasp_mjx.envs.host.HostChecker.motion_collides_between`'s verdict)."""
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        return _motion_between(placed, a, b, self.margin, STEP_DP, STEP_DROT)

    def motion_collides_between(self, needle: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
        """:meth:`motion_collides` around the needle at ``needle`` (7-vector; the last one's
        placement is kept, as :meth:`collides` keeps it)."""
        return self.motion_collides(self._placed_at(tuple(map(float, needle))), a, b)

    def _placed_at(self, needle: tuple) -> Held:
        """:meth:`place` of ``needle`` (a 7-tuple), kept for the next call around the same needle."""
        if self._last is None or self._last[0] != needle:
            self._last = (needle, self.place(np.array(needle)))
        return self._last[1]


def _same(a: tuple, b: tuple) -> bool:
    """Two needles' (radius, wire) [m] equal within 1 nm (as :func:`regrasp_mjx.world.scene.needle_scene`)."""
    return all(abs(x - y) < 1e-9 for x, y in zip(a, b))
