"""The planning rollout: a policy's networks stepped through the environment until every query has
ended, with the collision shield (ours).

One jitted program per network shape, environment and entry (ego-centric or camera-frame poses,
shield on or off), cached in :data:`PLANNERS` and shared by every policy of that shape (the weights
are its first argument). With the shield, a step whose action would collide (or, given PSM bases,
leave the joint limits) takes instead the first free one of a fixed list of alternatives
(:func:`regrasp_mjx.envs.shield.shield_candidates`), checked with the collision model the plan is
judged by; the alternatives are computed only at steps where some query's action collides.
"""

from __future__ import annotations

import functools
import json
import logging
import sys
import types
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.agents.ddpg_bc.networks import make_networks
from regrasp_mjx.core import geometry
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.rollout import Rollout, rollout
from regrasp_mjx.envs.shield import shield_rows
from regrasp_mjx.robot import dvrk
from regrasp_mjx.world.sampling import Episode

PLANNERS: dict[tuple, Any] = {}  # programs by (hidden, members, env, *setting): :func:`program`
CUT_FROM_QUERIES = 2048  # batches this large, off the CPU, copy only the planned part of their trajectories

# The network's matmuls when a policy plans or acts: full float32. JAX's default on recent NVIDIA
# GPUs is TF32 (a 10-bit mantissa), with which a GPU's plans drifted from the CPU's (and the lean
# path's) by up to 1e-2 in an action; on the CPU both are float32 and the programs are the same.
PLAN_MATMUL_PRECISION = "highest"


def program(policy: Any, setting: tuple, build: Callable[[], Callable] | None = None) -> Callable:
    """The jitted program of ``setting`` with ``policy``'s weights bound: ``(camera, shield)`` for
    planning (:func:`make_planner`), else what ``build()`` makes. Built once per network shape and
    environment (in :data:`PLANNERS`: policies of one shape share it), looked up once per policy (in
    its own ``_programs``)."""
    if setting not in policy._programs:
        key = (policy.hidden, policy.members, json.dumps(policy.contract["env"]), *setting)
        if key not in PLANNERS:
            PLANNERS[key] = build() if build else make_planner(policy.env_config, policy.hidden, *setting)
        policy._programs[setting] = functools.partial(PLANNERS[key], policy._weights)
    return policy._programs[setting]


# Said once per process before the lean planner is first built: its numba functions compile on first
# use (about 20 s on an idle 2-core CPU, over a minute on a busy one) or load from numba's on-disk cache
# (a second or two), without a line otherwise (issue 70, defect 16). Through the logging module where
# the application set up logging; else on stderr. Silenced by
# logging.getLogger("regrasp_mjx").setLevel(logging.WARNING).
LEAN_PREPARES = (
    "preparing the lean planner (numba, once per process: its first call compiles it, tens of seconds on a CPU, "
    "or loads it from numba's cache in about a second) ..."
)
LOG = logging.getLogger(__name__)
_said = False  # LEAN_PREPARES said in this process


def _say_lean_prepares() -> None:
    """:data:`LEAN_PREPARES`, the first time in a process: :data:`LOG`'s ``info`` where logging has a
    handler for it; else printed to stderr unless a ``regrasp_mjx`` logger's level is set above INFO."""
    global _said
    if _said:
        return
    _said = True
    if LOG.hasHandlers():  # the application set up logging: its levels and handlers decide
        LOG.info(LEAN_PREPARES)
        return
    logger = LOG  # the package's nearest logger whose level is set, if any
    while logger.parent is not None and logger.name.startswith("regrasp_mjx.") and not logger.level:
        logger = logger.parent
    if not (logger.name.startswith("regrasp_mjx") and logger.level > logging.INFO):
        print(LEAN_PREPARES, file=sys.stderr, flush=True)


def lean(policy: Any, shield: bool):
    """``policy``'s numba-compiled one-query planner
    (:class:`~regrasp_mjx.inference.lean_planner.LeanPlanner`), built once per policy."""
    if ("lean", shield) not in policy._programs:
        _say_lean_prepares()
        # imported here: numba's import (0.4 s) and first compilation are paid only where it is used
        from regrasp_mjx.inference.lean_planner import LeanPlanner

        policy._programs[("lean", shield)] = LeanPlanner(policy.env_config, policy._weights, shield)
    return policy._programs[("lean", shield)]


def members_apply(hidden: tuple[int, ...]):
    """``apply(weights, obs) -> [each member's action]``, ``weights`` one ``(params, mean, std)``
    per member, multiplied at :data:`PLAN_MATMUL_PRECISION`. Members are unrolled (not vmapped): K
    is small, and exporters (jax2onnx) see plain dense layers."""
    nets = make_networks(6, hidden)

    def apply(weights, obs):
        with jax.default_matmul_precision(PLAN_MATMUL_PRECISION):
            return [nets.policy(p, types.SimpleNamespace(mean=m, std=s), obs) for p, m, s in weights]

    return apply


def mean_action(actions: list[jax.Array]) -> jax.Array:
    """An ensemble's action: the mean of its members' actions."""
    return sum(actions) / len(actions)


class Planner:
    """A jitted planning program and how to read its output: calling it returns
    :class:`PlanArrays` of numpy arrays, the trajectories cut after the longest plan of the batch.

    A small batch (under :data:`CUT_FROM_QUERIES` queries) or any batch on the CPU comes back packed
    into one float32 array ``[B, n]`` (one transfer to the host costs a fifth of several, ~20
    against ~100 us on a CPU; the layout to unpack it is recorded while the program is traced) and
    is cut on the host. A large one on an accelerator returns its outcome packed and its
    horizon-long trajectories apart; these stay on the device until the outcome says how long the
    longest plan is, and only that many steps are copied (a batch's plans take ~7 steps of a horizon
    of 100, and the copy of whole trajectories, not the planning, was most of a large batch's time on
    a GPU)."""

    def __init__(self, program):
        self._layouts: dict[str, Any] = {}
        self._on_cpu = jax.default_backend() == "cpu"  # looked up once: the backend stays for the process

        def packed(*args):
            out = program(*args)
            # runs only while tracing; every batch size has the same per-query layout
            self._layouts["all"] = jax.tree.map(lambda x: (x.shape[1:], x.dtype), out)
            return pack(out)

        def outcome_packed(*args):
            out = program(*args)
            self._layouts["outcome"] = jax.tree.map(lambda x: (x.shape[1:], x.dtype), out.outcome)
            return pack(out.outcome), out._replace(outcome=None)

        self._packed = jax.jit(packed)
        self._outcome_packed = jax.jit(outcome_packed)
        self._cut = jax.jit(_cut, static_argnums=1)

    def whole(self, queries: int) -> bool:
        """Whether a batch of ``queries`` comes back whole in one packed array (else outcome first)."""
        return queries < CUT_FROM_QUERIES or self._on_cpu

    def program(self, queries: int):
        """The jitted program a batch of ``queries`` runs (what a profile times)."""
        return self._packed if self.whole(queries) else self._outcome_packed

    def __call__(self, *args) -> PlanArrays:
        if self.whole(len(args[1])):
            out = unpack(np.asarray(self._packed(*args)), self._layouts["all"])
            return _cut(out, _longest(out.outcome))
        packed, trajectories = self._outcome_packed(*args)
        outcome = unpack(np.asarray(packed), self._layouts["outcome"])
        steps = _longest(outcome)
        # cut on the device to a multiple of 8 steps (few compiled cuts), then copied
        horizon = trajectories.actions.shape[1]
        trajectories = jax.device_get(self._cut(trajectories, min(-(-steps // 8) * 8, horizon)))
        return _cut(trajectories, steps)._replace(outcome=outcome)


def _longest(outcome: Rollout) -> int:
    """The most steps any plan of a batch took (0 for an empty batch)."""
    return int(outcome.steps.max()) if outcome.steps.size else 0


def _cut(trajectories: PlanArrays, steps: int) -> PlanArrays:
    """Trajectories cut after ``steps`` steps (``steps + 1`` poses); the outcome left as it is."""
    cut = lambda x, n: None if x is None else x[:, :n]  # noqa: E731
    t = trajectories
    return t._replace(
        poses=cut(t.poses, steps + 1), actions=cut(t.actions, steps), poses_camera=cut(t.poses_camera, steps + 1)
    )


class PlanArrays(NamedTuple):
    """What a planning program returns (``[B, ...]``): how each query ended, its trajectory and
    actions, and (from camera-frame poses) the trajectory in the camera frame. Read through
    :class:`Planner`, the trajectories have ``T + 1`` poses and ``T`` actions, T the longest plan's
    steps; inside the program, ``horizon + 1`` and ``horizon``."""

    outcome: Rollout  # without its trace
    poses: Any  # [B, T + 1, 7] in e_g; rows after the end repeat the last pose
    actions: Any  # [B, T, 6] in [-1, 1]; zero from the end on
    poses_camera: Any = None  # [B, T + 1, 7]


def pack(tree: Any) -> jax.Array:
    """The leaves of a pytree of ``[B, ...]`` arrays as one float32 array ``[B, n]``."""
    leaves = jax.tree.leaves(tree)
    return jnp.concatenate([x.reshape(x.shape[0], -1).astype(jnp.float32) for x in leaves], axis=1)


def unpack(packed: np.ndarray, layout: Any) -> Any:
    """The pytree :func:`pack` made ``packed`` of; ``layout``: its leaves' ``(shape without the
    batch axis, dtype)`` in a tree of the same structure."""
    specs, treedef = jax.tree.flatten(layout, is_leaf=lambda x: isinstance(x, tuple) and len(x) == 2)
    sizes = [int(np.prod(shape)) for shape, _ in specs]
    parts = np.split(packed, np.cumsum(sizes)[:-1], axis=1)
    b = packed.shape[0]
    return jax.tree.unflatten(
        treedef, [p.reshape((b,) + shape).astype(dtype, copy=False) for p, (shape, dtype) in zip(parts, specs)]
    )


def make_planner(env_config: Any, hidden: tuple[int, ...], camera: bool, shield: bool) -> Planner:
    """The planning program of a network shape in an environment, taking the weights (one
    ``(params, mean, std)`` per member) as its first argument: ``(weights, needle, start, goal,
    radii[, base_inv])``; from camera-frame poses ``(weights, c_eg, c_er, c_n, goal_grasp, radii[,
    base_inv])``. ``radii`` ``[B, 2]``: each query's needle radius and wire radius [m];
    ``goal_grasp`` ``[B, 4]``: ``(alpha*, d* [m], theta*, phi*)``; ``base_inv`` ``[B, 4, 4]``
    (optional): the inverse of each query's regrasping PSM base frame in e_g, so that the shield
    also replaces actions that leave the joint limits. Returns :class:`PlanArrays`."""
    env = RegraspEnv(env_config)
    horizon = env.config.horizon
    apply = members_apply(tuple(hidden))
    step = jax.vmap(env.step)

    def make_shield(weights, limits: bool):
        def reach(st, _rows=None):
            """Within the joint limits (each row's base frame rides in its state's info, so the
            rows' indices that :func:`shield_rows` passes are not needed)."""
            if not limits:
                return jnp.ones(st.pipeline_state.t.shape, bool)
            es = st.pipeline_state
            return jax.vmap(dvrk.within_limits_jax)(st.info["base_inv"], es.ee_pos, es.ee_quat)

        def hook(state, t, a, nxt, live):
            need = ((nxt.metrics["collision"] > 0) | ~reach(nxt)) & live
            members = lambda sub: apply(weights, sub.obs)  # noqa: E731
            return shield_rows(step, members, state, t, a, nxt, need, reach if limits else None)

        return hook

    def plan(weights, needle, start, goal, radii, base_inv=None) -> PlanArrays:
        episodes = Episode.from_poses(needle, start, goal, radii)
        first = jax.vmap(env.reset_from)(episodes)
        if base_inv is not None:  # per-row data rides in the states, so the rollout may narrow to some rows
            first = first.replace(info={**first.info, "base_inv": base_inv})
        out = rollout(
            env,
            lambda state, t: mean_action(apply(weights, state.obs)),
            first,
            compact=True,
            shield=make_shield(weights, base_inv is not None) if shield else None,
            trace=lambda state, a, nxt: (
                jnp.concatenate([nxt.pipeline_state.ee_pos, nxt.pipeline_state.ee_quat], 1),
                a,
            ),
        )
        poses, actions = (jnp.swapaxes(x, 0, 1) for x in out.trace)  # [B, horizon, ...]
        poses = jnp.concatenate([start[:, None], poses], axis=1)
        # rows after the end repeat the last pose
        last = jnp.take_along_axis(poses, out.steps[:, None, None], axis=1)
        poses = jnp.where(jnp.arange(horizon + 1)[None, :, None] <= out.steps[:, None, None], poses, last)
        return PlanArrays(out._replace(trace=None), poses, jnp.clip(actions, -1.0, 1.0))

    def from_camera(weights, c_eg, c_er, c_n, goal_grasp, radii, base_inv=None) -> PlanArrays:
        pose = lambda x: (x[:, :3], x[:, 3:])  # noqa: E731
        join = lambda p: jnp.concatenate([p[0], p[1]], axis=-1)  # noqa: E731
        eg_inv = geometry.inverse(pose(c_eg))
        needle = geometry.compose(eg_inv, pose(c_n))
        start = geometry.compose(eg_inv, pose(c_er))
        goal = join(geometry.compose(needle, goal_pose_in_needle(goal_grasp, radii[:, 0])))
        needle, start = join(needle), join(start)
        start = start.at[:, 3:].set(geometry.canonical_quat(start[:, 3:]))
        needle = needle.at[:, 3:].set(geometry.canonical_quat(needle[:, 3:]))
        out = plan(weights, needle, start, goal, radii, base_inv)
        cam = jax.vmap(lambda c, p: join(geometry.compose(pose(c[None]), pose(p))))(c_eg, out.poses)
        return out._replace(poses_camera=cam)

    return Planner(from_camera if camera else plan)


def goal_pose_in_needle(goal_grasp: jax.Array, radius: jax.Array):
    """The goal end-effector poses ``T_n_er*`` of goal grasps ``[..., 4]`` = ``(alpha*, d* [m], theta*,
    phi*)`` on needles of ``radius`` [m] (paper eq. 3)."""
    g = goal_grasp
    return geometry.grasp_pose(g[..., 0], g[..., 1], g[..., 2], g[..., 3], radius)
