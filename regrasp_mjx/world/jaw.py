"""The regrasping tool's jaw opening: the jaws at another opening, and a proof that opening them
from the scene's angle to a wider one, the tool holding still, sweeps clear of the needle and the
grasping tool.

The scene fixes the opening (``SceneConfig.jaw_angle_deg``, 20 degrees; MJCF capsules from the jaw
pivot, the hinge the end-effector's x axis). Opening the jaws by ``d`` degrees turns each jaw
capsule by ``d / 2`` about that hinge, away from the other jaw. Between two openings ``delta``
apart, every angle is within ``delta / 4`` of half-angle of one of them, so every point of a jaw
(at most :func:`jaw_reach` from the hinge) within ``reach * delta / 4`` of where it is at that
opening: an opening whose sampled angles all keep more than that is clear at every angle between
them, not only at the samples (the capsule distance moves no faster than its end points).

The Large Needle Driver opens to 80 degrees (jhu-dvrk/sawIntuitiveResearchKit,
``share/tool/LARGE_NEEDLE_DRIVER_400006.json``: jaw qmax 1.39626 rad); the timed trajectory opens
it at the PSM's own jaw limits (:data:`regrasp_mjx.robot.psm_timing.JAW_V_MAX`, ``JAW_A_MAX``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config import JAW_MAX_DEG
from regrasp_mjx.core.geometry import rotation_matrix, segment_distance
from regrasp_mjx.world.distances import turn_jaws
from regrasp_mjx.world.scene import Scene

SAMPLE_DEG = 1.0  # the sweep's check points, in degrees of opening


def jaw_rows(scene: Scene) -> np.ndarray:
    """The jaw capsules' rows in ``scene.capsule_frames.tool_ends``."""
    return np.flatnonzero(scene.capsule_frames.jaw_sides)


def jaw_reach(scene: Scene) -> float:
    """The farthest a jaw capsule's axis reaches from the hinge (the end-effector's x axis) [m]."""
    ends = scene.capsule_frames.tool_ends[jaw_rows(scene)]
    return float(np.linalg.norm(ends[..., 1:], axis=-1).max())


def opened_ends(scene: Scene, deg: float) -> np.ndarray:
    """``scene.capsule_frames.tool_ends`` ``[T, 2, 3]`` with the jaws opened to ``deg`` (each turned by
    half the change about the hinge, away from the other; a smaller angle closes them)."""
    f = scene.capsule_frames
    half = math.radians(deg - scene.config.jaw_angle_deg) / 2.0
    return turn_jaws(np.asarray(f.tool_ends, np.float64), f.jaw_sides[:, None], half, np)


def sample_angles(base_deg: float, widest_deg: float, step_deg: float = SAMPLE_DEG) -> np.ndarray:
    """The openings a sweep from ``base_deg`` to ``widest_deg`` is checked at: both ends and every
    ``step_deg`` between (float64 degrees)."""
    n = max(1, math.ceil((widest_deg - base_deg) / step_deg - 1e-9))
    return np.linspace(base_deg, widest_deg, n + 1)


@functools.lru_cache(maxsize=16)  # one compiled check per scene and ladder (a table asks for it many times)
def opening_fn(scene: Scene, widest_deg: float, step_deg: float = SAMPLE_DEG) -> tuple[np.ndarray, Callable]:
    """``(angles, fn)``: :func:`sample_angles` from the scene's opening to ``widest_deg`` and the jitted
    ``fn(needle_pos, needle_quat, ee_pos, ee_quat, radius, wire) -> [B, len(angles)]`` (``[B, 7]``
    poses in e_g as ``[B, 3]`` and ``[B, 4]``, each row's needle radius and wire [m]): each row's
    smallest clearance [m] between a jaw at that opening and the needle or the grasping tool, less
    the sweep's slack (how far a jaw point moves between check points, ``reach * step / 4``). Every
    value of a prefix >= 0 proves the jaws open clear from the scene's angle to that prefix's last
    angle, the tool holding still."""
    if not scene.config.jaw_angle_deg <= widest_deg <= JAW_MAX_DEG:
        raise ValueError(
            f"jaw opening {widest_deg!r} deg is not accepted: from the scene's {scene.config.jaw_angle_deg} "
            f"to the LND's {JAW_MAX_DEG} deg"
        )
    angles = sample_angles(scene.config.jaw_angle_deg, widest_deg, step_deg)
    rows = jaw_rows(scene)
    jaws = jnp.asarray(np.stack([opened_ends(scene, a)[rows] for a in angles]), jnp.float32)  # [A, J, 2, 3]
    radii = jnp.asarray(scene.capsule_frames.tool_radii[rows], jnp.float32)
    slack = jaw_reach(scene) * math.radians(float(angles[1] - angles[0]) if len(angles) > 1 else 0.0) / 4.0
    others = scene.motion_distance_fn()[0]

    def one(needle_pos, needle_quat, ee_pos, ee_quat, radius, wire):
        return _jaw_clearance(jaws, radii, others(needle_pos, needle_quat, radius, wire), ee_pos, ee_quat) - slack

    return angles, jax.jit(jax.vmap(one))


def widest_clear(angles: np.ndarray, clearance: np.ndarray, rungs: np.ndarray, margin: float) -> np.ndarray:
    """Each row's widest of ``rungs`` (degrees, ascending, the first the scene's opening) whose sweep
    keeps ``margin`` [m] at every check point up to it (``clearance`` ``[B, len(angles)]``,
    :func:`opening_fn`'s); the first rung where none does."""
    kept = np.minimum.accumulate(np.asarray(clearance) >= margin, axis=1)  # [B, A]: clear up to each angle
    index = np.searchsorted(angles, np.asarray(rungs) - 1e-9)  # each rung's check point
    ok = kept[:, index]
    ok[:, 0] = True  # the scene's own opening: the start as given
    return np.asarray(rungs, np.float64)[ok.sum(axis=1) - 1]  # ok is True up to a rung, then False


SWEEP_STEPS = 10  # an opening sweep's intervals within a step of the environment


def _jaw_clearance(jaws, radii, placed, ee_pos, ee_quat) -> jax.Array:
    """``[A]`` each opening's least clearance [m] between the jaws ``jaws`` ``[A, J, 2, 3]`` (e_r;
    capsule radii ``radii`` ``[J]``) on the tool at ``(ee_pos, ee_quat)`` and the counted capsules
    ``placed`` (``(ends [1, O, 2, 3], radii [O])``, the first of
    :meth:`~regrasp_mjx.world.scene.Scene.motion_distance_fn`'s functions)."""
    ends, other_radii = placed
    at = ee_pos + jnp.sum(rotation_matrix(ee_quat) * jaws[..., None, :], axis=-1)  # [A, J, 2, 3]
    a, b = at[:, :, None], ends[None]  # [A, J, 1, 2, 3] against [1, 1, O, 2, 3]
    gap = segment_distance(a[..., 0, :], a[..., 1, :], b[..., 0, :], b[..., 1, :])
    return jnp.min(gap - radii[None, :, None] - other_radii[None, None, :], axis=(1, 2))


def sweep_fn(scene: Scene, steps: int = SWEEP_STEPS) -> Callable:
    """``fn(placed, ee_pos, ee_quat, from_deg, to_deg) -> clearance`` [m], traced: the least signed
    distance between a jaw and the counted capsules (``placed``, the first of
    :meth:`~regrasp_mjx.world.scene.Scene.motion_distance_fn`'s functions) at ``steps + 1`` openings
    evenly from ``from_deg`` to ``to_deg``, the tool holding still, less how far a jaw point moves
    between two of them (``reach * delta / 4``, as :func:`opening_fn`): a value >= m proves every
    opening between them keeps m. The environment's opening inside a step (issue 67): the jaws alone,
    turned by :func:`~regrasp_mjx.world.distances.turn_jaws`, as :func:`opening_fn` checks them."""
    f, rows = scene.capsule_frames, jaw_rows(scene)
    base, sides = jnp.asarray(f.tool_ends[rows], jnp.float32), jnp.asarray(f.jaw_sides[rows], jnp.float32)[:, None]
    radii = jnp.asarray(f.tool_radii[rows], jnp.float32)
    reach, fractions, base_deg = jaw_reach(scene), jnp.linspace(0.0, 1.0, steps + 1), scene.config.jaw_angle_deg

    def fn(placed, ee_pos, ee_quat, from_deg, to_deg):
        halves = jnp.radians(from_deg + (to_deg - from_deg) * fractions - base_deg) / 2.0  # [A]
        jaws = jax.vmap(lambda half: turn_jaws(base, sides, half))(halves)  # [A, J, 2, 3]
        least = jnp.min(_jaw_clearance(jaws, radii, placed, ee_pos, ee_quat))
        return least - reach * jnp.radians(jnp.abs(to_deg - from_deg) / steps) / 4.0

    return fn
