"""DAgger distillation (ours): one network learns a stronger planner's actions on the states it visits.

The **teacher** is a trained policy (one network or an ensemble) improved by lookahead. At a state
it takes the policy's own action if rolling the policy out from there (bare, ``lookahead`` steps)
reaches the goal; otherwise the first of the collision shield's alternatives
(:mod:`regrasp_mjx.envs.shield`, closest to the policy first) after which the policy's rollout reaches
it; if none does, the first collision-free alternative (what the shield would take); if none is
free, the policy's action. So the teacher does at least what the shielded policy does, and it also
steers away from the states where the policy times out or collides a few steps later.

The **student** is a fresh MLP of any size (smaller is faster to plan with). DAgger (Ross et al.,
"A Reduction of Imitation Learning and Structured Prediction to No-Regret Online Learning", 2011):
each iteration rolls the student out on fresh problems (the teacher's policy in the first
iteration), labels the states it visited with the teacher's actions, adds them to a buffer of
labelled states (flashbax), and fits the student to the buffer by (weighted) mean squared error.
The student's observation normaliser is fixed from the first iteration's states. Every iteration is
one jitted program, the same for all (the first's teacher rollout is a traced flag), and the
teacher's weights are its argument, not constants: distillations of teachers of one shape share the
compiled program through the persistent cache (a recipe's students compile it once). The host picks
the iteration best on validation problems of their own seed.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import flashbax as fbx
import jax
import jax.numpy as jnp
import optax
from brax.training.acme import running_statistics, specs
from flax import struct

from regrasp_mjx.agents.ddpg_bc.networks import make_networks
from regrasp_mjx.core.config import ConfigError, is_integer, require, require_integers, require_numbers
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import noisy_observation
from regrasp_mjx.envs.rollout import rollout
from regrasp_mjx.envs.shield import shield_candidates

MembersFn = Callable[[jax.Array], list]  # obs [B, 21] -> each teacher member's actions [B, 6]
MembersApply = Callable[[Any, jax.Array], list]  # (weights, obs [B, 21]) -> each member's actions [B, 6]


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """A distillation run. All ours.

    Attributes:
      hidden: the student's hidden layers.
      iterations: DAgger iterations (the first rolls the teacher's policy out); in a training config
        (``TrainConfig.distill``) 0 means no distillation stage.
      problems: fresh problems rolled out per iteration (one episode each).
      label_states: visited states labelled per iteration (``problems * horizon`` at most; when fewer
        were visited the rest of the slots carry zero weight).
      updates, batch_size, lr, lr_decay_to: SGD steps per iteration, their batch, Adam's learning
        rate and the fraction of it a cosine reaches at the last update.
      buffer_size: labelled states kept (oldest dropped first).
      lookahead: steps of the teacher's rollouts that judge an action.
      correction_weight: loss weight of states where the teacher overrides its policy (1 = plain MSE).
      seed: PRNG seed; validation_size: problems (of their own seed) that pick the exported iteration.
      obs_noise_mm, obs_bias_mm: needle-pose noise the student learns to act under (0 = off): its
        rollouts act on, and the buffer stores, observations of a needle estimate
        (:func:`regrasp_mjx.envs.estimates.noisy_observation`: a new frame each step, sigma drawn per
        problem from U[0, obs_noise_mm], a bias of U[0, obs_bias_mm] fixed per episode), while the
        teacher labels the true state (privileged: it sees the needle exactly). With noise the
        exported iteration is the one best on validation problems under the same noise.
      obs_tool_noise_mm: with it (> 0), the camera sees both tools too (the ``camera`` view of
        :mod:`regrasp_mjx.robot.robot_errors`): each frame's tool poses get noise of sigma_tool drawn per
        problem from U[0, obs_tool_noise_mm] (ours, issue 45).
      goal_tolerance: the student learns to reach the goal within this fraction of the success
        tolerances (the teacher's lookahead and the rollouts end there; ours: below 1 it aims deeper
        into the goal, where a closed loop that stops inside 0.7 of the tolerances on a noisy
        estimate goes on acting); its policy file keeps the task's own tolerances.
    """

    hidden: tuple[int, ...] = (256, 256, 256)
    iterations: int = 30
    problems: int = 1024
    label_states: int = 16384
    updates: int = 500
    batch_size: int = 1024
    lr: float = 1e-3
    lr_decay_to: float = 0.02
    buffer_size: int = 1_000_000
    lookahead: int = 40
    correction_weight: float = 1.0
    seed: int = 0
    validation_size: int = 1000
    obs_noise_mm: float = 0.0
    obs_bias_mm: float = 0.0
    obs_tool_noise_mm: float = 0.0
    goal_tolerance: float = 1.0

    def __post_init__(self) -> None:
        d = "distill."  # the field's name as --set and the TrainConfig spell it
        require_numbers(self, ("goal_tolerance",), lambda v: 0.1 <= v <= 1.0, "a fraction in [0.1, 1]", d)
        noises = ("obs_noise_mm", "obs_bias_mm", "obs_tool_noise_mm")
        require_numbers(self, noises, lambda v: 0 <= v <= 5, "a noise level in [0, 5] mm", d)
        require_integers(self, ("iterations", "seed"), 0, d)
        names = ("problems", "label_states", "updates", "batch_size", "buffer_size", "lookahead", "validation_size")
        require_integers(self, names, 1, d)
        ok = bool(self.hidden) and all(is_integer(h) and h > 0 for h in self.hidden)
        require(ok, d + "hidden", self.hidden, "a tuple of positive layer sizes")
        require_numbers(self, ("lr", "correction_weight"), lambda v: v > 0, "a finite number > 0", d)
        require_numbers(self, ("lr_decay_to",), lambda v: 0.0 < v <= 1.0, "a fraction in (0, 1]", d)
        require(self.buffer_size >= self.batch_size, d + "buffer_size", self.buffer_size, "at least one batch")


@struct.dataclass
class DistillState:
    params: Any
    opt: Any
    normalizer: Any
    buffer: Any
    key: jax.Array


def aim(env_config, config: DistillConfig):
    """The environment the student learns in: the task's, with its success tolerances scaled by
    ``goal_tolerance`` (the teacher's lookahead and the rollouts end there; the student is judged
    in the task's own)."""
    f = config.goal_tolerance
    if f == 1.0:
        return env_config
    return dataclasses.replace(
        env_config, success_pos_mm=f * env_config.success_pos_mm, success_rot_deg=f * env_config.success_rot_deg
    )


def teacher_actions(env: RegraspEnv, members: MembersFn, state: Any, key: jax.Array, lookahead: int):
    """The teacher's actions at a batch of environment states (see the module docstring).

    Returns ``(action [B, 6], overridden [B], reaches [B])``: whether the teacher's action differs
    from its policy's, and whether some candidate's rollout reached the goal."""
    step = jax.vmap(env.step)
    own = members(state.obs)
    policy_action = sum(own) / len(own)
    cands = jnp.concatenate([policy_action[None], shield_candidates(own, policy_action, key)])  # [K, B, 6]
    k, b = cands.shape[:2]
    tile = lambda x: jnp.broadcast_to(x[None], (k,) + x.shape).reshape((k * b,) + x.shape[1:])  # noqa: E731
    first = step(jax.tree.map(tile, state), cands.reshape(k * b, -1))
    free = first.metrics["collision"] == 0

    def policy(st, t):
        acts = members(st.obs)
        return sum(acts) / len(acts)

    # the policy's rollout after each candidate (a candidate that ends the episode ends it there)
    ok = rollout(env, policy, first, max_steps=lookahead).success
    ok, free = ok.reshape(k, b), free.reshape(k, b)
    pick = jnp.where(ok.any(0), jnp.argmax(ok, 0), jnp.where(free.any(0), jnp.argmax(free, 0), 0))
    return cands[pick, jnp.arange(b)], pick != 0, ok.any(0)


class Distiller:
    """The jitted DAgger iteration for one teacher and one :class:`DistillConfig`: the teacher is
    ``apply(weights, obs) -> [each member's action]`` and its ``weights`` (``Policy.network()``)."""

    def __init__(self, env: RegraspEnv, teacher: tuple[MembersApply, Any], config: DistillConfig):
        if config.iterations < 1:
            raise ConfigError(f"distill.iterations={config.iterations} is not accepted here: at least 1")
        self.env, self.config = env, config
        self.apply, self.weights = teacher
        self.noisy = config.obs_noise_mm > 0 or config.obs_bias_mm > 0 or config.obs_tool_noise_mm > 0
        self.nets = make_networks(env.action_size, config.hidden)
        total = config.iterations * config.updates
        lr = optax.cosine_decay_schedule(config.lr, decay_steps=total, alpha=config.lr_decay_to)
        self.opt = optax.adam(lr)
        self.buffer = fbx.make_item_buffer(
            max_length=config.buffer_size,
            min_length=1,
            sample_batch_size=config.batch_size,
            add_batches=True,
        )
        self._program = jax.jit(self._iteration, donate_argnums=(0,))

    def iteration(self, ds: DistillState, teacher_rollout: bool) -> tuple[DistillState, dict]:
        """One DAgger iteration; ``teacher_rollout``: the first (the teacher's policy rolls out and
        the student's normaliser is fixed from its states)."""
        return self._program(ds, self.weights, jnp.asarray(teacher_rollout))

    def init(self) -> DistillState:
        cfg, obs_size, act_size = self.config, self.env.observation_size, self.env.action_size
        k_init, k_run = jax.random.split(jax.random.PRNGKey(cfg.seed))
        params = self.nets.actor.init(k_init, jnp.zeros((1, obs_size)))
        spec = {"obs": jnp.zeros(obs_size), "action": jnp.zeros(act_size), "weight": jnp.zeros(())}
        return DistillState(
            params=params,
            opt=self.opt.init(params),
            normalizer=running_statistics.init_state(specs.Array((obs_size,), jnp.float32)),
            buffer=self.buffer.init(spec),
            key=k_run,
        )

    def act(self, ds: DistillState, obs: jax.Array) -> jax.Array:
        """The student's action."""
        return self.nets.policy(ds.params, ds.normalizer, obs)

    def _iteration(self, ds: DistillState, weights: Any, teacher_rollout: jax.Array):
        cfg, env = self.config, self.env
        members = functools.partial(self.apply, weights)
        key, k_reset, k_order, k_label, k_upd = jax.random.split(ds.key, 5)
        horizon = env.config.horizon
        first = jax.vmap(env.reset)(jax.random.split(k_reset, cfg.problems))

        def policy(obs):  # both networks are cheap beside a step; one program serves every iteration
            own = members(obs)
            return jnp.where(teacher_rollout, sum(own) / len(own), self.act(ds, obs))

        if self.noisy:  # each problem's noise level, bias and frames (folded off: noise-free runs keep their streams)
            k_rows, k_sigma, k_bias = jax.random.split(jax.random.fold_in(ds.key, 17), 3)
            rows = jax.random.split(k_rows, cfg.problems)
            sigma = jax.random.uniform(k_sigma, (cfg.problems,), maxval=cfg.obs_noise_mm)
            bias = jax.random.uniform(k_bias, (cfg.problems,), maxval=cfg.obs_bias_mm)
            tool = None
            if cfg.obs_tool_noise_mm > 0:  # folded off again: needle-only runs keep their streams
                k_tool = jax.random.fold_in(ds.key, 19)
                tool = jax.random.uniform(k_tool, (cfg.problems,), maxval=cfg.obs_tool_noise_mm)
            seen = lambda state: noisy_observation(env, state.pipeline_state, rows, sigma, bias, tool)  # noqa: E731
        else:
            seen = lambda state: state.obs  # noqa: E731

        # the rollout keeps each visited state and what the student saw there: time-major
        # [horizon, problems], live rows before their end
        roll = rollout(
            env, lambda state, t: policy(seen(state)), first, trace=lambda state, a, nxt: (state, seen(state))
        )
        visited, seen_obs = roll.trace
        live = jnp.arange(horizon)[:, None] < (roll.steps * roll.start_valid)[None, :]
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), (visited, seen_obs))
        live = live.reshape(-1)
        # label_states slots: the visited states first (in random order), then unvisited ones, weight 0
        order = jax.random.permutation(k_order, live.shape[0])
        order = order[jnp.argsort(~live[order], stable=True)][: cfg.label_states]
        states, obs = jax.tree.map(lambda x: x[order], flat)
        valid = live[order].astype(jnp.float32)
        labels, overridden, reaches = teacher_actions(env, members, states, k_label, cfg.lookahead)
        weight = valid * jnp.where(overridden, cfg.correction_weight, 1.0)
        # the first iteration fixes the student's normaliser
        fixed = running_statistics.update(ds.normalizer, obs, weights=valid)
        normalizer = jax.tree.map(lambda a, b: jnp.where(teacher_rollout, a, b), fixed, ds.normalizer)
        buffer = self.buffer.add(ds.buffer, {"obs": obs, "action": labels, "weight": weight})
        ds = ds.replace(normalizer=normalizer, buffer=buffer, key=key)

        def update(ds, k):
            batch = self.buffer.sample(ds.buffer, k).experience

            def loss_fn(params):
                pred = self.nets.policy(params, ds.normalizer, batch["obs"])
                se = jnp.sum(jnp.square(pred - batch["action"]), axis=-1)
                return jnp.sum(batch["weight"] * se) / jnp.maximum(jnp.sum(batch["weight"]), 1.0)

            loss, grad = jax.value_and_grad(loss_fn)(ds.params)
            upd, opt = self.opt.update(grad, ds.opt, ds.params)
            return ds.replace(params=optax.apply_updates(ds.params, upd), opt=opt), loss

        ds, loss = jax.lax.scan(update, ds, jax.random.split(k_upd, cfg.updates))
        n_valid = jnp.maximum(jnp.sum(valid), 1.0)
        metrics = {
            "loss": jnp.mean(loss),
            "loss_last": loss[-1],
            "rollout_success": jnp.mean(roll.success),
            "rollout_collision": jnp.mean(roll.collision),
            "states_visited": jnp.sum(live.astype(jnp.float32)),
            "states_labelled": jnp.sum(valid),
            "overridden": jnp.sum(valid * overridden) / n_valid,
            "teacher_reaches": jnp.sum(valid * reaches) / n_valid,
        }
        return ds, metrics
