"""RegraspEnv: the bimanual needle-regrasping MDP on brax's environment API, batched in MJX.

The grasping tool and the needle it holds never move; the regrasping end-effector moves by the
action. A step is pure kinematics and collision (``mjx.kinematics`` and exact capsule-axis
distances, ``Scene.distance_fn``), no dynamics. The episode's poses live in
``State.pipeline_state`` (an :class:`EpisodeState`), so brax's ``AutoResetWrapper`` restores a
whole episode when it resets.

Read top to bottom: construction, ``reset``/``reset_from``, ``step``, then the reward and the
observation.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct

from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import ConfigError, EnvConfig
from regrasp_mjx.world import continuous, continuous_walk, jaw, walk_kernel
from regrasp_mjx.world.sampling import Episode, sample_episode
from regrasp_mjx.world.scene import Scene, load_scene

ACTION_SIZE = 6


@struct.dataclass
class EpisodeState:
    """What changes within an episode (and what a reset restores). All in the e_g frame.

    Attributes:
      needle_pos, needle_quat: the needle frame, fixed for the episode.
      ee_pos, ee_quat: the regrasping end-effector now.
      goal_pos, goal_quat: the regrasping end-effector at the goal.
      goal_needle_pos, goal_needle_quat: the needle in the goal end-effector frame, ``T_er*_n``,
        which the success test compares against ``T_er_n`` (paper eqs. 8, 9).
      t: steps taken.
      path_length: sum of ``|dp|`` so far [m].
      needle_radius, wire_radius: the needle [m] (the scene's, unless the task draws needles).
      jaw_deg: the regrasping jaws' opening [deg]: the scene's at the start, wider once opened
        (``EnvConfig.jaw_open_deg``; :meth:`RegraspEnv.move`'s ``open_to``).
    """

    needle_pos: jax.Array
    needle_quat: jax.Array
    ee_pos: jax.Array
    ee_quat: jax.Array
    goal_pos: jax.Array
    goal_quat: jax.Array
    goal_needle_pos: jax.Array
    goal_needle_quat: jax.Array
    t: jax.Array
    path_length: jax.Array
    needle_radius: jax.Array
    wire_radius: jax.Array
    jaw_deg: jax.Array


METRIC_NAMES = (
    "success",
    "collision",
    "time_out",
    "distance_mm",
    "angle_deg",
    "clearance_mm",
    "path_length_mm",
    "reset_valid",
)


class RegraspEnv(Env):
    """The regrasping task (SPEC "MDP"): 21-D ego-centric observation, 6-D action in [-1, 1].

    A general task (``config.task.general``: ranges of the goal grasp or the needle, ours) observes
    37 numbers: the 21 and :func:`regrasp_mjx.core.geometry.task_observation` (the goal and the needle);
    where it draws needles each environment checks collisions against its own (one compiled
    program for every size).

    A pose collides when a counted pair is closer than ``clearance_mm`` (0: when it penetrates).

    ``reset(rng)`` samples a problem from the paper's distributions; ``reset_from(episode)`` starts
    from a given one (a test-set row). Both and ``step`` are pure and jit/vmap-able.

    Reward: ``collision_reward`` (-1, ends the episode) if the step's motion is not proved clear
    along its whole length (:mod:`regrasp_mjx.world.continuous`);
    ``success_reward`` (+1, ends it) if the end pose is within ``success_pos_mm`` and
    ``success_rot_deg`` of the goal; ``step_reward`` (beta = -0.02) otherwise. Reaching ``horizon``
    steps ends the episode as a time-out: ``info['truncation'] = 1``, not a terminal state.

    Metrics per step: success, collision, time_out, distance_mm and angle_deg to the goal,
    clearance_mm (smallest surface distance of the counted pairs at the end pose), path_length_mm so
    far, reset_valid.
    """

    def __init__(self, config: EnvConfig = EnvConfig(), scene: Scene | None = None):
        if not isinstance(config, EnvConfig):
            raise ConfigError(f"config must be an EnvConfig, got {type(config).__name__}")
        self.config = config
        self.scene = scene if scene is not None else load_scene(config.scene)
        if self.scene.config != config.scene:
            raise ConfigError(f"scene was built for {self.scene.config}, config asks for {config.scene}")
        self.max_dp = config.max_dp_mm * 1e-3
        self.max_drot = math.radians(config.max_drot_deg)
        self.needle_radius = config.scene.needle_radius_mm * 1e-3
        self.wire_radius = config.scene.wire_radius_mm * 1e-3
        self.clearance = config.clearance_mm * 1e-3
        self.varies_needle = config.task.varies_needle
        self.general = config.task.general
        # the continuous test of a step (regrasp_mjx.world.continuous): each tool capsule's lever
        frames = self.scene.capsule_frames
        levers = continuous.levers(frames.tool_ends)
        self.levers = jnp.asarray(levers, jnp.float32)
        self.distances = self.scene.distance_fn()
        self._place_others, self._gaps, self._interval = self.scene.motion_distance_fn()
        # the same test as one Pallas kernel a batch (where walk_kernel.use_kernel(): on a GPU)
        # the jaws may open on the way (issue 67): the opening sweep's check and the kernel that turns them
        self.opens = config.jaw_open_deg is not None
        self._sweep = jaw.sweep_fn(self.scene)
        self.jaw_margin = config.jaw_open_margin_mm * 1e-3
        sides = frames.jaw_sides if self.opens else None
        self._walk_kernel = walk_kernel.make_kernel(
            frames.tool_ends, frames.tool_radii, levers, self.clearance, jaw_sides=sides
        )
        # what the validity tests use: clearances less the margin (negative = colliding)
        distances, margin = self.distances, self.clearance
        self._free_distances = distances if margin == 0.0 else (lambda *pose: distances(*pose) - margin)

    def needle_distances(self, es, ee_pos: jax.Array, ee_quat: jax.Array) -> jax.Array:
        """Signed distances of the counted pairs for an end-effector pose, around the needle of
        ``es`` (an :class:`EpisodeState` or an :class:`Episode`): its own where the task draws needles."""
        needle = (es.needle_radius, es.wire_radius) if self.varies_needle else ()
        return self.distances(es.needle_pos, es.needle_quat, ee_pos, ee_quat, *needle)

    # ---- brax Env interface ------------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return geometry.OBS_SIZE_GENERAL if self.general else geometry.OBS_SIZE

    @property
    def action_size(self) -> int:
        return ACTION_SIZE

    @property
    def backend(self) -> str:
        return "mjx"

    # ---- reset -------------------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> State:
        """A new problem from the paper's distributions (colliding starts and goals redrawn; with a
        clearance margin, those closer than it too)."""
        episode, valid = sample_episode(
            rng, self.config.task, self.needle_radius, self._free_distances, self.wire_radius
        )
        return self._first_state(episode, valid)

    def reset_from(self, episode: Episode) -> State:
        """Starts from a given problem, e.g. a test-set row (vmap over rows for a batch)."""
        episode = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), episode)
        episode = episode.replace(
            needle_quat=_normalise(episode.needle_quat),
            start_quat=_normalise(episode.start_quat),
            goal_quat=_normalise(episode.goal_quat),
        )
        if episode.needle_radius is None or episode.wire_radius is None:  # a problem of the scene's needle
            episode = episode.replace(
                needle_radius=jnp.float32(self.needle_radius), wire_radius=jnp.float32(self.wire_radius)
            )
        start = self.needle_distances(episode, episode.start_pos, episode.start_quat)
        start_free = jnp.min(start) > self.clearance
        return self._first_state(episode, start_free)

    def _first_state(self, episode: Episode, valid: jax.Array) -> State:
        goal_needle = geometry.relative(
            (episode.goal_pos, episode.goal_quat), (episode.needle_pos, episode.needle_quat)
        )
        es = EpisodeState(
            needle_pos=episode.needle_pos,
            needle_quat=episode.needle_quat,
            ee_pos=episode.start_pos,
            ee_quat=episode.start_quat,
            goal_pos=episode.goal_pos,
            goal_quat=episode.goal_quat,
            goal_needle_pos=goal_needle[0],
            goal_needle_quat=goal_needle[1],
            t=jnp.int32(0),
            path_length=jnp.float32(0.0),
            needle_radius=jnp.asarray(episode.needle_radius, jnp.float32),
            wire_radius=jnp.asarray(episode.wire_radius, jnp.float32),
            jaw_deg=jnp.float32(self.config.scene.jaw_angle_deg),
        )
        dist = self.needle_distances(es, es.ee_pos, es.ee_quat)
        metrics = self._metrics(es, jnp.min(dist), jnp.bool_(False), jnp.bool_(False), jnp.bool_(False))
        metrics["reset_valid"] = valid.astype(jnp.float32)
        zero = jnp.float32(0.0)
        return State(
            pipeline_state=es,
            obs=self.observe(es),
            reward=zero,
            done=zero,
            metrics=metrics,
            info={"truncation": zero},
        )

    # ---- step --------------------------------------------------------------------------------
    def step(self, state: State, action: jax.Array) -> State:
        """Moves the regrasping end-effector by ``action`` and checks the swept motion.

        ``dp = a[0:3] max_dp`` in the e_g frame and ``q_t = exp(a[3:6] max_drot) q_{t-1}`` (paper
        eq. 7); actions are clipped to [-1, 1]. The step collides unless every pose along it,
        ``(p + s dp, exp(s w) q)`` for s in [0, 1], is proved clear of the margin
        (:func:`regrasp_mjx.world.continuous_walk.motion_collides`: not only sampled poses).
        """
        a = self.checked_action(action)
        return self.move(state, a[:3] * self.max_dp, a[3:] * self.max_drot)

    def checked_action(self, action: jax.Array) -> jax.Array:
        """One environment's action as :meth:`step` takes it: shape ``(6,)``, floating point, finite
        (where ``check_actions``), clipped to [-1, 1] as float32; anything else refused with what is accepted."""
        action = jnp.asarray(action)
        if action.shape != (ACTION_SIZE,):
            raise ValueError(
                f"action has shape {action.shape}; accepted: ({ACTION_SIZE},) per environment "
                f"(dp_x, dp_y, dp_z, rot_x, rot_y, rot_z in [-1, 1]), vmapped for a batch"
            )
        if not jnp.issubdtype(action.dtype, jnp.floating):
            raise ValueError(f"action has dtype {action.dtype}; accepted: a floating-point array")
        if self.config.check_actions:
            action = eqx.error_if(
                action,
                ~jnp.all(jnp.isfinite(action)),
                "RegraspEnv.step: action has NaN or inf; accepted: finite values in [-1, 1]",
            )
        return jnp.clip(action.astype(jnp.float32), -1.0, 1.0)

    def move(self, state: State, dp: jax.Array, rotvec: jax.Array, open_to: jax.Array | None = None) -> State:
        """:meth:`step` by a translation ``dp`` [m] and rotation vector ``rotvec`` [rad] (e_g frame)
        as given, not clipped to the action bounds: the motion an arm carries out, which an error
        of its view may turn off the action's axes (:mod:`regrasp_mjx.robot.robot_errors`).

        The jaws (issue 67): where ``open_to`` [deg] is wider than they are, they first open to it,
        the tool holding still (a sweep not proved clear of the margin is a collision): the caller
        decided on its view. Without it, where ``EnvConfig.jaw_open_deg`` is set, they open to that
        once the sweep keeps ``jaw_open_margin_mm`` on this state (:meth:`_opening`). The motion is
        then tested with the jaws where they are."""
        es: EpisodeState = state.pipeline_state
        end_pos = es.ee_pos + dp
        end_quat = geometry.quat_mul(geometry.quat_from_rotvec(rotvec), es.ee_quat)
        needle = (es.needle_radius, es.wire_radius) if self.varies_needle else ()
        placed = self._place_others(es.needle_pos, es.needle_quat, *needle)  # once for the step's poses
        jaw_deg, opening_hit = self._opening(placed, es, open_to)
        held = {} if jaw_deg is None else {"jaw_deg": jaw_deg}
        end = self._gaps(placed, end_pos, end_quat, **held)

        speed = jnp.linalg.norm(dp) + jnp.linalg.norm(rotvec) * self.levers  # [T]: v_t, each tool capsule's
        motion = (placed, es.ee_pos, es.ee_quat, dp, rotvec) + (() if jaw_deg is None else (jaw_deg,))
        ends_in = jnp.any(end < self.clearance)  # a collision whatever the motion before: not walked
        # the end pose clear by v_t: clear along the whole step (s = 1 back to 0), the root not tested
        clear = jnp.all(end.reshape(speed.shape[0], -1) - speed[:, None] - self.clearance >= continuous.SLACK)
        if walk_kernel.use_kernel():  # the root and walk where neither end pose decides, one kernel a batch
            walk = walk_kernel.lane_fn(self._walk_kernel, interpret=jax.default_backend() != "gpu")
            ends, radii = placed
            radii = jnp.broadcast_to(radii, ends.shape[1:2])
            pending = ~ends_in & ~clear
            turned = () if jaw_deg is None else (jnp.radians(jaw_deg - self.config.scene.jaw_angle_deg) / 2.0,)
            collision = ends_in | walk(
                ends[0], radii, es.ee_pos, es.ee_quat, dp, rotvec, jnp.max(speed), pending, *turned
            )
        else:
            collision = continuous_walk.motion_collides(
                self._bounds_along, motion, jnp.max(speed), self.clearance, known=ends_in, proved=clear
            )
        collision = collision | opening_hit

        es = es.replace(
            ee_pos=end_pos,
            ee_quat=geometry.canonical_quat(end_quat),
            t=es.t + 1,
            path_length=es.path_length + jnp.linalg.norm(dp),
            jaw_deg=es.jaw_deg if jaw_deg is None else jaw_deg,
        )
        distance, angle = self._goal_error(es)
        success = (
            (~collision)
            & (distance <= self.config.success_pos_mm * 1e-3)
            & (angle <= math.radians(self.config.success_rot_deg))
        )
        terminal = collision | success
        time_out = (~terminal) & (es.t >= self.config.horizon)
        reward = jnp.where(
            collision,
            self.config.collision_reward,
            jnp.where(success, self.config.success_reward, self.config.step_reward),
        ).astype(jnp.float32)
        metrics = self._metrics(es, jnp.min(end), success, collision, time_out, distance, angle)
        metrics["reset_valid"] = state.metrics["reset_valid"]
        info = {**state.info, "truncation": time_out.astype(jnp.float32)}
        return state.replace(
            pipeline_state=es,
            obs=self.observe(es),
            reward=reward,
            done=(terminal | time_out).astype(jnp.float32),
            metrics=metrics,
            info=info,
        )

    def _bounds_along(self, motion, s, h) -> tuple[jax.Array, jax.Array]:
        """The counted pairs' signed distances at the pose s of a step's motion (:meth:`move`: its
        ``(placed, pos, quat, dp, rotvec[, jaw_deg])``) and their lower bounds over the interval of
        half-width h about it."""
        placed, pos, quat, dp, rotvec, *held = motion
        at = geometry.quat_mul(geometry.quat_from_rotvec(s * rotvec), quat)
        return self._interval(placed, pos + s * dp, at, dp, rotvec, h, *held)

    def opening_room(self, es: EpisodeState, to_deg) -> jax.Array:
        """How much room [m] opening the jaws from where ``es`` has them to ``to_deg`` leaves at its pose,
        the tool holding still (:func:`regrasp_mjx.world.jaw.sweep_fn`: proved between check points);
        one row, vmap-able."""
        needle = (es.needle_radius, es.wire_radius) if self.varies_needle else ()
        placed = self._place_others(es.needle_pos, es.needle_quat, *needle)
        return self._sweep(placed, es.ee_pos, es.ee_quat, es.jaw_deg, jnp.asarray(to_deg, jnp.float32))

    def _opening(self, placed, es: EpisodeState, open_to) -> tuple[jax.Array | None, jax.Array]:
        """The jaws' opening a step moves with (None: the scene's, never opened) and whether opening
        to it collided (:meth:`move`)."""
        if open_to is None and not self.opens:
            return None, jnp.bool_(False)
        if open_to is None:  # the environment's rule, on its own state: open once there is room
            want = jnp.float32(self.config.jaw_open_deg)
            room = self._sweep(placed, es.ee_pos, es.ee_quat, es.jaw_deg, want)
            return jnp.where((want > es.jaw_deg) & (room >= self.jaw_margin), want, es.jaw_deg), jnp.bool_(False)
        want = jnp.maximum(es.jaw_deg, jnp.asarray(open_to, jnp.float32))
        room = self._sweep(placed, es.ee_pos, es.ee_quat, es.jaw_deg, want)
        return want, (want > es.jaw_deg) & (room < self.clearance)

    # ---- reward terms and observation ---------------------------------------------------------
    def _goal_error(self, es: EpisodeState) -> tuple[jax.Array, jax.Array]:
        """Distance [m] and angle [rad] between ``T_er_n`` now and at the goal (eqs. 8, 9)."""
        needle_in_ee = geometry.relative((es.ee_pos, es.ee_quat), (es.needle_pos, es.needle_quat))
        return geometry.pose_error(needle_in_ee, (es.goal_needle_pos, es.goal_needle_quat))

    def _metrics(self, es, clearance, success, collision, time_out, distance=None, angle=None) -> dict:
        if distance is None:
            distance, angle = self._goal_error(es)
        return {
            "success": success.astype(jnp.float32),
            "collision": collision.astype(jnp.float32),
            "time_out": time_out.astype(jnp.float32),
            "distance_mm": distance * 1e3,
            "angle_deg": jnp.degrees(angle),
            "clearance_mm": clearance * 1e3,
            "path_length_mm": es.path_length * 1e3,
        }

    def observe(self, es: EpisodeState) -> jax.Array:
        """The ego-centric state (paper §III-B), world frame = e_g; a general task's adds the goal and
        the needle (:func:`regrasp_mjx.core.geometry.task_observation`)."""
        needle, ee = (es.needle_pos, es.needle_quat), (es.ee_pos, es.ee_quat)
        obs = geometry.ego_observation_eg(needle, ee)
        if not self.general:
            return obs
        goal = (es.goal_pos, es.goal_quat)
        return jnp.concatenate([obs, geometry.task_observation(needle, ee, goal, es.needle_radius, es.wire_radius)])


def _normalise(q: jax.Array) -> jax.Array:
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)
