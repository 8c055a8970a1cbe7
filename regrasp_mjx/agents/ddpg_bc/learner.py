"""The learner: one jitted program per iteration joining the exploration rollouts, the buffer inserts
and the DDPG+BC gradient steps in a scan.

An iteration resets ``num_envs`` environments to fresh problems and runs their exploration rollout
(:mod:`~regrasp_mjx.agents.ddpg_bc.exploration`: ``horizon`` steps, random actions with probability
E_R, noisy observations when asked); every one of the ``num_envs * horizon`` transitions goes into the
online buffer. Then ``updates_per_iteration`` DDPG+BC updates (this module), each on ``online_batch``
online and ``demo_batch`` demonstration samples (flashbax item buffers); the target networks move by
polyak averaging every ``target_every`` updates. The first episode of each environment is the one
that counts for Algorithm 1: the host sends failed ones to the planner pool with probability E_T.

Members are a batch axis: ``num_members`` independent learners (seeds ``seed, seed + 1, ...``, for
each of the config's ``settings``; E_R comes per member), each with its own networks, optimisers,
normaliser, buffers and key, run as one vmapped program, so several seeds of Table I cost about what
one costs on a GPU. Every state leaf has that leading axis (1 for a single seed); the single-learner
functions (``init_one``, ``update``, ``iteration_one``, ``evaluate_one``) are the ones vmapped.

Several devices (``devices`` in the config) share the work by whole members or data parallel
(:mod:`~regrasp_mjx.agents.ddpg_bc.placement`); schedules: :mod:`~regrasp_mjx.agents.ddpg_bc.schedules`.
"""

from __future__ import annotations

import functools
from typing import Any

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from brax.training.acme import running_statistics, specs
from flax import struct
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from regrasp_mjx.agents.ddpg_bc import exploration, losses
from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.agents.ddpg_bc.networks import DDPGNetworks, init_params, make_networks
from regrasp_mjx.agents.ddpg_bc.placement import AXIS, Placement
from regrasp_mjx.agents.ddpg_bc.schedules import Schedules
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.rollout import Rollout, rollout
from regrasp_mjx.world.sampling import Episode

TRANSITION = ("obs", "action", "reward", "next_obs", "terminal")


@struct.dataclass
class TrainingState:
    actor: Any
    critic: Any
    ema_actor: Any  # moving average of the actor (what is evaluated and exported when actor_ema > 0)
    target_actor: Any
    target_critic: Any
    actor_opt: Any
    critic_opt: Any
    normalizer: Any
    online: Any
    demos: Any
    key: jax.Array
    updates: jax.Array  # gradient steps so far
    iteration: jax.Array


def _transition_spec(obs_size: int, action_size: int) -> dict[str, jax.Array]:
    return {
        "obs": jnp.zeros(obs_size),
        "action": jnp.zeros(action_size),
        "reward": jnp.zeros(()),
        "next_obs": jnp.zeros(obs_size),
        "terminal": jnp.zeros(()),
    }


class Learner(Placement, Schedules):
    """Builds the networks, buffers and jitted programs for one :class:`TrainConfig`."""

    def __init__(self, config: TrainConfig, env: RegraspEnv | None = None):
        self.config = config
        self.env = env if env is not None else RegraspEnv(config.env)
        self.nets: DDPGNetworks = make_networks(
            self.env.action_size, config.hidden, config.critics, config.critic_layer_norm
        )
        self.actor_opt = optax.adam(self._learning_rate(config.lr_actor))
        self.critic_opt = optax.adam(self._learning_rate(config.lr_critic))
        self._init_placement(config)
        # Each device's slice of the online buffer, and its share of every batch.
        self.online_buffer = fbx.make_item_buffer(
            max_length=config.buffer_size // self.devices,
            min_length=config.online_batch // self.devices,
            sample_batch_size=config.online_batch // self.devices,
            add_batches=True,
        )
        self.trace_count = 0  # how often the iteration program was traced (tests assert one)
        self.iteration = jax.jit(self._iteration, donate_argnums=(0,))
        # actor and normaliser carry the seed axis; the problems are shared
        self.evaluate = jax.jit(jax.vmap(self.evaluate_one, in_axes=(0, 0, None)))
        # ... and with the critic: its estimate at the start against the return the rollout got
        self.evaluate_q = jax.jit(jax.vmap(self.evaluate_one, in_axes=(0, 0, None, 0)))
        self.add_online = jax.jit(self._add_online, donate_argnums=(0,))
        self.demo_buffer = None

    def policy_params(self, ts: TrainingState) -> Any:
        """The actor that is evaluated, selected and exported: the moving average when ``actor_ema``
        > 0, else the actor itself. (Rollouts explore with the actor itself.)"""
        return ts.ema_actor if self.config.actor_ema > 0 else ts.actor

    # ---- state --------------------------------------------------------------------------------
    def init(self, demos: dict[str, jax.Array]) -> TrainingState:
        """Fresh learners, one per member (``TrainConfig.member_seed``), stacked on a leading axis."""
        cfg = self.config
        # host values: in a distributed run every process passes the same ones to the jitted program
        keys = np.stack([np.asarray(jax.random.PRNGKey(cfg.member_seed(m))) for m in range(cfg.num_members)])
        demos = jax.tree.map(np.asarray, demos)

        def make(keys, demos):
            ts = jax.vmap(self.init_one, in_axes=(0, None))(keys, demos)
            # The online buffer spans all devices' slices: [seed, 1, buffer_size, ...].
            full = lambda x: jnp.zeros(x.shape[:2] + (cfg.buffer_size,) + x.shape[3:], x.dtype)  # noqa: E731
            ts = ts.replace(online=ts.online.replace(experience=jax.tree.map(full, ts.online.experience)))
            # No weakly typed leaves: a state restored from a checkpoint then traces like a fresh one.
            return jax.tree.map(lambda x: jax.lax.convert_element_type(x, x.dtype), ts)

        shardings = self.state_shardings(jax.eval_shape(make, keys, demos))
        return jax.jit(make, out_shardings=shardings)(keys, demos)

    def init_one(self, key: jax.Array, demos: dict[str, jax.Array]) -> TrainingState:
        """One learner: fresh networks and optimisers, the demonstrations loaded, the normaliser
        seeded with them."""
        cfg = self.config
        obs_size, action_size = self.env.observation_size, self.env.action_size
        k_init, k_run = jax.random.split(key)
        actor, critic = init_params(self.nets, k_init, obs_size, action_size)
        spec = _transition_spec(obs_size, action_size)
        n_demo = int(demos["obs"].shape[0])
        if n_demo < cfg.demo_batch:
            raise ValueError(
                f"{n_demo} demonstration transitions are fewer than one demonstration batch "
                f"({cfg.demo_batch}); add demonstrations or lower batch_size/demo_fraction"
            )
        self.attach_demo_buffer(n_demo)
        demo_state = self.demo_buffer.add(
            self.demo_buffer.init(spec), {k: jnp.asarray(demos[k], jnp.float32) for k in TRANSITION}
        )
        normalizer = running_statistics.init_state(specs.Array((obs_size,), jnp.float32))
        normalizer = running_statistics.update(normalizer, jnp.asarray(demos["obs"], jnp.float32))
        return TrainingState(
            actor=actor,
            critic=critic,  # targets start equal, in buffers of their own (donation)
            ema_actor=jax.tree.map(jnp.copy, actor),
            target_actor=jax.tree.map(jnp.copy, actor),
            target_critic=jax.tree.map(jnp.copy, critic),
            actor_opt=self.actor_opt.init(actor),
            critic_opt=self.critic_opt.init(critic),
            normalizer=normalizer,
            online=self.online_buffer.init(spec),
            demos=demo_state,
            key=k_run,
            updates=jnp.int32(0),
            iteration=jnp.int32(0),
        )

    def attach_demo_buffer(self, num_demo_transitions: int) -> None:
        """Builds the demonstration buffer's functions for ``num_demo_transitions`` items (``init``
        calls it; a checkpoint restores into the state that ``init`` built, so its buffer matches)."""
        self.demo_buffer = fbx.make_item_buffer(
            max_length=num_demo_transitions,
            min_length=1,
            sample_batch_size=self.config.demo_batch // self.devices,
            add_batches=True,
        )

    # ---- the jitted iteration --------------------------------------------------------------------
    def _policy(self, ts: TrainingState):
        return functools.partial(self.nets.policy, ts.actor, ts.normalizer)

    def _reset_keys(self, key: jax.Array) -> jax.Array:
        """One learner's reset keys for the iteration, all devices' in device order: ``[num_envs, 2]``."""
        k_roll = jax.random.split(key, 3)[1]  # as iteration_one splits the learner's key
        per_device = [jax.random.fold_in(k_roll, d) if self.axis else k_roll for d in range(self.devices)]
        return jnp.concatenate([jax.random.split(jax.random.split(k)[0], self.local_envs) for k in per_device])

    def _rollout(self, ts: TrainingState, first, key: jax.Array, random_eps: jax.Array):
        """One learner's exploration rollout on this device (:func:`~regrasp_mjx.agents.ddpg_bc.exploration.explore`)
        with its actor: ``(outcome, transitions, rewards)``."""
        return exploration.explore(self.env, self.config, self._policy(ts), first, self._device_key(key), random_eps)

    def update(self, ts: TrainingState, key: jax.Array):
        """One DDPG+BC gradient step of one learner: this device's share of a batch, then :meth:`learn`."""
        k_online, k_demo = jax.random.split(self._device_key(key))
        online = self.online_buffer.sample(ts.online, k_online).experience
        demo = self.demo_buffer.sample(ts.demos, k_demo).experience
        # folded, not split: the batches stay those of runs without target noise
        k_noise = jax.random.fold_in(self._device_key(key), 1)
        return self.learn(ts, jax.tree.map(lambda a, b: jnp.concatenate([a, b]), online, demo), k_noise)

    def learn(self, ts: TrainingState, batch: dict[str, jax.Array], key: jax.Array | None = None):
        """The gradient step on a batch (online samples first, then demonstrations); under several
        devices ``batch`` is this device's share and the gradients are averaged across devices.
        ``key`` draws the target-policy noise (needed when ``target_noise`` > 0)."""
        cfg, nets = self.config, self.nets
        if cfg.target_noise > 0 and key is None:
            raise ValueError("learn() needs a key when target_noise > 0 (it draws the target-policy noise)")
        n_online = cfg.online_batch // self.devices
        is_demo = jnp.arange(batch["reward"].shape[0]) >= n_online
        policy = lambda p, o: nets.policy(p, ts.normalizer, o)  # noqa: E731
        q = lambda p, o, a: nets.q(p, ts.normalizer, o, a)  # noqa: E731

        (_, c_metrics), c_grad = jax.value_and_grad(losses.critic_loss, has_aux=True)(
            ts.critic,
            ts.target_actor,
            ts.target_critic,
            batch,
            policy,
            q,
            cfg.gamma,
            key,
            cfg.target_noise,
            cfg.target_noise_clip,
        )
        c_upd, critic_opt = self.critic_opt.update(self._pmean(c_grad), ts.critic_opt, ts.critic)
        critic = optax.apply_updates(ts.critic, c_upd)
        # The BC term is a sum over the batch's demonstrations (the means are means): scaled by the
        # device count, its averaged gradient is the whole batch's sum.
        (_, a_metrics), a_grad = jax.value_and_grad(losses.actor_loss, has_aux=True)(
            ts.actor,
            critic,
            batch,
            is_demo,
            policy,
            q,
            cfg.prm_coef,
            self.bc_coef(ts.updates) * self.devices,
            self.action_l2(ts.updates),
        )
        a_upd, actor_opt = self.actor_opt.update(self._pmean(a_grad), ts.actor_opt, ts.actor)
        actor = optax.apply_updates(ts.actor, a_upd)

        if cfg.actor_ema > 0:
            ema_actor = jax.tree.map(lambda e, a: cfg.actor_ema * e + (1.0 - cfg.actor_ema) * a, ts.ema_actor, actor)
        else:
            ema_actor = ts.ema_actor
        updates = ts.updates + 1
        sync = (updates % cfg.target_every) == 0
        blend = lambda t, p: jnp.where(sync, cfg.polyak * t + (1.0 - cfg.polyak) * p, t)  # noqa: E731
        ts = ts.replace(
            actor=actor,
            critic=critic,
            ema_actor=ema_actor,
            actor_opt=actor_opt,
            critic_opt=critic_opt,
            updates=updates,
            target_actor=jax.tree.map(blend, ts.target_actor, actor),
            target_critic=jax.tree.map(blend, ts.target_critic, critic),
        )
        return ts, {**c_metrics, **a_metrics}

    def iteration_one(self, ts: TrainingState, first, random_eps: jax.Array):
        """One learner's iteration from its environments' first states: rollouts, inserts,
        ``updates_per_iteration`` updates."""
        key, k_roll, k_upd = jax.random.split(ts.key, 3)
        outcome, transitions, rewards = self._rollout(ts, first, k_roll, random_eps)
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), transitions)
        online = self.online_buffer.add(ts.online, flat)
        normalizer = running_statistics.update(ts.normalizer, flat["obs"], pmap_axis_name=self.axis)
        ts = ts.replace(online=online, normalizer=normalizer, key=key)
        ts, metrics = jax.lax.scan(self.update, ts, jax.random.split(k_upd, self.config.updates_per_iteration))
        metrics = jax.tree.map(jnp.mean, metrics)
        metrics["rollout_reward"] = jnp.sum(rewards) / self.local_envs
        ts = ts.replace(iteration=ts.iteration + 1)
        return ts, self._pmean(metrics), outcome

    def _iteration(self, ts: TrainingState, random_eps: jax.Array):
        """All members' iterations as one program: ``(state, metrics[S], outcome, problems)``, ``outcome``
        the :class:`~regrasp_mjx.envs.rollout.Rollout` of each environment's first episode (``[S, N]``),
        environments (outcomes and problems: axis 1) split over the devices; ``random_eps`` is each
        member's E_R, ``[S]`` (or one for all).

        The resets are drawn outside the ``shard_map``, partitioned by XLA from a sharding
        constraint: on two H200s (jax 0.11.2) XLA's GPU compiler crashes (segfault) on the reset's
        rejection-sampling while loop (collision distances in its body) inside a manually sharded
        program, and compiles the same loop auto-partitioned."""
        self.trace_count += 1
        random_eps = jnp.broadcast_to(random_eps, ts.iteration.shape)  # one for all, or one per member
        by_member = self.member_devices > 1
        split = P(AXIS) if by_member else P(None, AXIS)  # members, or each member's environments
        keys = jax.lax.with_sharding_constraint(jax.vmap(self._reset_keys)(ts.key), NamedSharding(self.mesh, split))
        first = jax.lax.with_sharding_constraint(
            jax.vmap(jax.vmap(self.env.reset))(keys), NamedSharding(self.mesh, split)
        )
        specs = self.state_specs(ts)
        body = jax.vmap(self.iteration_one, in_axes=(0, 0, 0))
        per_member = P(AXIS) if by_member else P()
        ts, metrics, outcome = self._shard_map(body, (specs, split, per_member), (specs, per_member, split))(
            ts, first, random_eps
        )
        return ts, metrics, outcome, first.pipeline_state

    def _add_online(self, ts: TrainingState, member: jax.Array, chunk: dict[str, jax.Array]) -> TrainingState:
        """Adds a chunk of planner demonstrations to one seed's online buffer (and normaliser); with
        several devices each adds its share of the chunk to its slice."""

        def add(ts, member, chunk):
            pick = lambda tree: jax.tree.map(lambda x: x[member], tree)  # noqa: E731
            put = lambda tree, one: jax.tree.map(lambda x, y: x.at[member].set(y), tree, one)  # noqa: E731
            online = self.online_buffer.add(pick(ts.online), chunk)
            normalizer = running_statistics.update(pick(ts.normalizer), chunk["obs"], pmap_axis_name=self.axis)
            return ts.replace(online=put(ts.online, online), normalizer=put(ts.normalizer, normalizer))

        specs = self.state_specs(ts)
        if self.member_devices == 1:
            return self._shard_map(add, (specs, P(), P(AXIS)), specs)(ts, member, chunk)

        def own(ts, member, chunk):
            # whole members per device: only the device holding ``member`` adds the whole chunk
            here = ts.iteration.shape[0]  # members on this device
            local = member - jax.lax.axis_index(AXIS) * here
            mine = (local >= 0) & (local < here)
            return jax.lax.cond(mine, add, lambda ts, *_: ts, ts, jnp.clip(local, 0, here - 1), chunk)

        return self._shard_map(own, (specs, P(), P()), specs)(ts, member, chunk)

    # ---- evaluation ---------------------------------------------------------------------------
    def evaluate_one(self, actor: Any, normalizer: Any, episodes: Episode, critic: Any = None) -> tuple[Rollout, Any]:
        """Deterministic policy on given problems, one pass: ``(rollout, q_start)``.

        With ``critic``, ``q_start`` is the critic's estimate at each start, ``Q(s_0, pi(s_0))``
        (the first critic), to set against the discounted return the rollout actually got: their
        difference is the critic's over-estimation on the policy's own starts (time-outs bootstrap
        in training, so theirs reads low by at most ``gamma^horizon``); without, ``None``."""
        policy = functools.partial(self.nets.policy, actor, normalizer)
        start = jax.vmap(self.env.reset_from)(episodes)
        out = rollout(self.env, lambda state, t: policy(state.obs), start, gamma=self.config.gamma, compact=True)
        if critic is None:
            return out, None
        q0 = self.nets.q(critic, normalizer, start.obs, policy(start.obs))
        return out, q0 if q0.ndim == 1 else q0[0]
