"""The counted pairs' signed distances as pure JAX functions of a scene (:class:`~regrasp_mjx.world.scene.Scene`,
whose :meth:`~regrasp_mjx.world.scene.Scene.distance_fn` and
:meth:`~regrasp_mjx.world.scene.Scene.motion_distance_fn` return them): at one pose, posed by
``mjx.kinematics`` (:func:`distance_fn`), and in parts for the many poses of one motion, the
continuous test's (:func:`motion_distance_fn`). Both around the scene's needle or any other given
as numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from mujoco import mjx

from regrasp_mjx.core.geometry import dot3, rotation_matrix, segment_distance, segment_gap
from regrasp_mjx.world import continuous

DistanceFn = Callable[[jax.Array, jax.Array, jax.Array, jax.Array], jax.Array]


class _Capsules(NamedTuple):
    """The counted pairs' capsules (:attr:`Scene.capsule_frames`) as both distance functions hold
    them: float32 arrays, and the scene's needle radius the chords are scaled from."""

    tool_ends: jax.Array  # [T, 2, 3] in e_r, the jaws at the scene's opening
    jaw_sides: jax.Array  # [T, 1] +-1 for the jaws (the way each turns as they open), 0 the rest
    other_ends: jax.Array  # [O, 2, 3] in n (needle) or e_g
    on_needle: jax.Array  # [O] bool
    tool_radii: jax.Array  # [T, 1]
    other_radii: jax.Array  # [O]
    inflation0: jax.Array  # [O] a chord's radius over the wire's at the scene's needle
    radius0: float  # the scene's needle radius [m]
    jaw0_deg: float  # the scene's jaw opening [deg]

    def needle(self, radius: Any, wire: Any) -> tuple[Any, jax.Array]:
        """For a needle of ``radius`` and ``wire`` [m] (None: the scene's own): the factor its
        chords are scaled by about the needle centre, and the counted capsules' radii ``[O]`` (a
        chord's the wire's plus the scaled inflation)."""
        if radius is None:
            return 1.0, self.other_radii
        scale = radius / self.radius0
        return scale, jnp.where(self.on_needle, wire + self.inflation0 * scale, self.other_radii)

    def tool(self, jaw_deg: Any) -> jax.Array:
        """The regrasping tool's capsule ends ``[T, 2, 3]`` with its jaws at ``jaw_deg`` (None: the
        scene's opening, the constant itself)."""
        if jaw_deg is None:
            return self.tool_ends
        return turn_jaws(self.tool_ends, self.jaw_sides, jnp.radians(jaw_deg - self.jaw0_deg) / 2.0)


def turn_jaws(ends: Any, sides: Any, half: Any, xp: Any = jnp) -> Any:
    """Tool capsule ends ``[T, 2, 3]`` (e_r) with each turned by ``sides * half`` [rad] about the hinge,
    the x axis (``sides [T, 1]``: +-1 the jaws, 0 the rest, left exactly as they are): the jaws opened
    by ``2 half`` from where ``ends`` has them."""
    c, s = xp.cos(sides * half), xp.sin(sides * half)  # [T, 1] against each capsule's two ends
    x, y, z = ends[..., 0], ends[..., 1], ends[..., 2]
    return xp.stack([x, c * y + s * z, -s * y + c * z], axis=-1)


def _capsules(scene: Any) -> _Capsules:
    """:class:`_Capsules` of ``scene``."""
    f = scene.capsule_frames
    return _Capsules(
        tool_ends=jnp.asarray(f.tool_ends, jnp.float32),
        jaw_sides=jnp.asarray(f.jaw_sides, jnp.float32)[:, None],
        other_ends=jnp.asarray(f.other_ends, jnp.float32),
        on_needle=jnp.asarray(f.on_needle),
        tool_radii=jnp.asarray(f.tool_radii, jnp.float32)[:, None],
        other_radii=jnp.asarray(f.other_radii, jnp.float32),
        inflation0=jnp.asarray(f.inflation, jnp.float32),
        radius0=scene.config.needle_radius_mm * 1e-3,
        jaw0_deg=scene.config.jaw_angle_deg,
    )


def distance_fn(scene: Any) -> DistanceFn:
    """A pure JAX function ``(needle_pos, needle_quat, ee_pos, ee_quat[, radius, wire], jaw_deg=None) ->
    distances[npairs]`` of ``scene`` (a :class:`~regrasp_mjx.world.scene.Scene`).

    With ``jaw_deg`` (traced: one program for every opening) the regrasping jaws are at that opening
    instead of the scene's, exactly the capsules the scene built at it has (:func:`turn_jaws`).

    With ``radius`` and ``wire`` [m] (traced values: one compiled program serves every needle)
    the needle is that one instead of the scene's: its chords scaled by ``radius / R`` about the
    needle centre, their radius the wire's plus the scaled inflation (with
    ``conservative_needle``), exactly the capsules :func:`~regrasp_mjx.world.scene.load_scene` builds for that needle.

    Signed surface distances (m) of the counted pairs in the order of :attr:`Scene.pairs` (regrasping
    capsule by regrasping capsule), negative when they penetrate; the minimum is the clearance.
    The two free bodies are posed by ``mjx.kinematics`` (on :attr:`Scene.mjx_body_model`) and the
    counted capsules placed from their bodies' frames, only those; the distances are
    the exact closest points of the capsule axes (Ericson, Real-Time Collision Detection,
    5.1.9), what CPU MuJoCo's ``mj_geomDistance`` computes, every regrasping capsule against
    every counted one by broadcasting ``[T, 1] x [1, O]`` rather than gathering both capsules
    of each of the T x O pairs. (``mjx.collision``'s
    capsule-capsule contact is one clip-and-project pass that overestimates some distances by
    tens of microns, up to 20x at a few microns' clearance on this scene, so it is not used.)
    """
    c = _capsules(scene)
    bodies = scene.mjx_body_model
    data0 = mjx.make_data(bodies, device=jax.local_devices()[0])
    needle_body, tool_body = scene.body_ids

    def place(ends, d, body, scale=1.0):
        # products and sums, not a matmul: on the GPU a float32 matmul may run in TF32 (10-bit
        # mantissa), which moves a capsule 50 mm from its body's origin by tens of microns
        return d.xpos[body] + jnp.sum(d.xmat[body] * (scale * ends)[..., None, :], axis=-1)

    def distances(needle_pos, needle_quat, ee_pos, ee_quat, radius=None, wire=None, jaw_deg=None):
        d = mjx.kinematics(bodies, data0.replace(qpos=scene.qpos(needle_pos, needle_quat, ee_pos, ee_quat)))
        tool = place(c.tool(jaw_deg), d, tool_body)[:, None]  # [T, 1, 2, 3]
        scale, others = c.needle(radius, wire)
        needle = place(c.other_ends, d, needle_body, scale)  # another needle: chords scaled about its centre
        other = jnp.where(c.on_needle[:, None, None], needle, c.other_ends)[None]  # [1, O, 2, 3]
        gap = segment_distance(tool[..., 0, :], tool[..., 1, :], other[..., 0, :], other[..., 1, :])
        return (gap - c.tool_radii - others).reshape(-1)

    return distances


def motion_distance_fn(scene: Any) -> tuple[Callable, Callable, Callable]:
    """:func:`distance_fn` cut in parts for the many poses of one motion (the continuous test):
    ``others(needle_pos, needle_quat[, radius, wire]) -> (ends [1, O, 2, 3], radii [O])``, the
    counted capsules placed once; ``gaps(others, ee_pos, ee_quat) -> [npairs]``, the signed
    distances for one end-effector pose; and ``interval(others, ee_pos, ee_quat, dp, rotvec, h)
    -> (gaps, low)``, those and their lower bounds over the interval of half-width h about the
    pose of the motion ``(dp, rotvec)`` (:func:`regrasp_mjx.world.continuous.interval_low`). The
    bodies are posed from their quaternions directly (the same frames ``mjx.kinematics``
    computes, without its per-call work). ``gaps`` and ``interval`` take ``jaw_deg`` as
    :func:`distance_fn` does (the jaws held at it along the motion: turning about the hinge keeps
    each end point's distance from the origin, so the levers are the scene's)."""
    c = _capsules(scene)
    levers = jnp.asarray(continuous.levers(scene.capsule_frames.tool_ends), jnp.float32)

    def place(ends, pos, quat):
        # products and sums, not a matmul (TF32 on a GPU; see distance_fn)
        return pos + jnp.sum(rotation_matrix(quat) * ends[..., None, :], axis=-1)

    def others(needle_pos, needle_quat, radius=None, wire=None):
        scale, radii = c.needle(radius, wire)
        needle = place(scale * c.other_ends, needle_pos, needle_quat)
        ends = jnp.where(c.on_needle[:, None, None], needle, c.other_ends)[None]
        return ends, radii

    def pose(placed, ee_pos, ee_quat, jaw_deg):
        ends, radii = placed
        tool = place(c.tool(jaw_deg), ee_pos, ee_quat)  # [T, 2, 3]
        t = tool[:, None]
        gap = segment_gap(t[..., 0, :], t[..., 1, :], ends[..., 0, :], ends[..., 1, :])  # [T, O, 3]
        return tool, gap, jnp.sqrt(dot3(gap, gap)) - c.tool_radii - radii

    def gaps(placed, ee_pos, ee_quat, jaw_deg=None):
        """Every pair's signed distance."""
        return pose(placed, ee_pos, ee_quat, jaw_deg)[2].reshape(-1)

    def interval(placed, ee_pos, ee_quat, dp, rotvec, h, jaw_deg=None):
        """Every pair's signed distance and its lower bound over the interval."""
        tool, gap, d = pose(placed, ee_pos, ee_quat, jaw_deg)
        low = continuous.interval_low(tool, ee_pos, placed[0][0], gap, d, h, dp, rotvec, levers)
        return d.reshape(-1), low.reshape(-1)

    return others, gaps, interval
