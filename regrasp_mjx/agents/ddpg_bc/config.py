"""The learner's typed, frozen config, its scale presets and Table I's exploration settings."""

from __future__ import annotations

import dataclasses
import math

from regrasp_mjx.agents.dagger import DistillConfig
from regrasp_mjx.core.config import (
    GENERAL_TASK,
    ConfigError,
    EnvConfig,
    is_integer,
    require,
    require_flags,
    require_integers,
    require_numbers,
)
from regrasp_mjx.core.config_text import replace


@dataclasses.dataclass(frozen=True)
class Exploration:
    """Mixed exploration (Algorithm 1). Probabilities change once per iteration (batch of episodes):
    ``E_R = max(E_R - dE_R, 0)``, ``E_T = min(E_T + dE_T, 1)``."""

    random_eps: float = 0.3  # E_R^0
    random_eps_decay: float = 6e-4  # dE_R
    targeted_eps: float = 0.1  # E_T^0
    targeted_eps_growth: float = 4.5e-3  # dE_T

    def __post_init__(self) -> None:
        require_numbers(self, ("random_eps", "targeted_eps"), lambda v: 0.0 <= v <= 1.0, "a probability in [0, 1]")
        require_numbers(
            self, ("random_eps_decay", "targeted_eps_growth"), lambda v: 0.0 <= v <= 1.0, "a step in [0, 1]"
        )

    def at(self, iteration: int) -> tuple[float, float]:
        """``(E_R, E_T)`` in force during ``iteration`` (0-based)."""
        e_r = max(self.random_eps - self.random_eps_decay * iteration, 0.0)
        e_t = min(self.targeted_eps + self.targeted_eps_growth * iteration, 1.0) if self.targeted_eps > 0 else 0.0
        return e_r, e_t


# Table I of the paper.
EXPLORATION = {
    "ddpg_bc": Exploration(0.3, 6e-4, 0.0, 0.0),
    "targeted": Exploration(0.02, 0.0, 0.5, 0.0),
    "mixed": Exploration(0.3, 6e-4, 0.1, 4.5e-3),
}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on. Paper values (SPEC "Learner") unless marked ours.

    Attributes:
      env: the MDP.
      exploration: E_R / E_T schedules (Table I).
      settings: Table I settings trained side by side in one program (ours): ``(name, schedule)``
        pairs, each given ``num_seeds`` members; empty = the one setting ``exploration``. Member
        ``m`` has the setting ``m // num_seeds`` and the seed ``seed + m % num_seeds``, so the
        settings' seeds pair up (same initial networks and problems).
      num_envs: environments rolled out in parallel per iteration (paper 5).
      updates_per_iteration: gradient steps per iteration (paper 200).
      iterations_per_epoch: iterations between evaluations and checkpoints (paper 10).
      epochs: paper 500.
      batch_size: transitions per update, demonstrations included (256).
      demo_fraction: share of each batch drawn from the demonstrations (ours: 0.25).
      buffer_size: online replay buffer (1e6).
      gamma, lr_actor, lr_critic, polyak, target_every, action_l2, prm_coef, bc_coef: as SPEC.
      hidden: hidden layer sizes of both networks.
      num_demos: demonstrations for BC (9900); built when the run has none.
      planner_budget_s, planner_workers, planner_queue: the targeted-exploration planner pool.
      demo_chunk: planner demonstrations are added to the online buffer this many transitions at a
        time (one compiled insert).
      action_noise: std of Gaussian noise added to the policy's (non-random) actions in training
        rollouts, clipped to [-1, 1] (HER's ``noise_eps``; ours, 0 = the paper's uniform-only E_R).
        It keeps exploring after E_R reaches 0, so the replay buffer keeps actions around the
        policy's own for the critic to rank (see experiments/RESULTS.md, "Why training decayed").
      obs_noise_mm, obs_bias_mm: domain randomisation over needle-pose noise (ours; 0 = off): in
        training rollouts the policy acts on, and the buffer stores, observations of a needle
        estimate (:mod:`regrasp_mjx.envs.estimates`' model) with per-step noise of sigma drawn per
        environment and iteration from U[0, obs_noise_mm], after a bias of U[0, obs_bias_mm] mm in
        a random direction, fixed per environment and iteration (its episodes). Evaluation stays
        noise-free.
      obs_tool_noise_mm: with it (> 0) the camera sees both tools too (ours, issue 45): each
        frame's tool poses get noise of sigma_tool drawn per environment and iteration from
        U[0, obs_tool_noise_mm] (:func:`regrasp_mjx.envs.estimates.camera_view`).
      critics: 1 (the paper) or 2 (ours: TD3's clipped double Q, the target takes the minimum).
      critic_layer_norm: a layer norm after each hidden layer of the critic (ours; off by default,
        see experiments/RESULTS.md, "Table I over the paper's full 500 epochs"). The exported
        actor is unchanged.
      target_noise, target_noise_clip: std and clip of the Gaussian noise on the target policy's
        action in the critic's target (ours: TD3's target policy smoothing; 0 = off).
      actor_ema: per-update decay of an exponential moving average of the actor's weights, which
        evaluation, model selection and export use (ours; 0 = off, the raw actor).
      bc_decay_epochs: the BC coefficient falls by a cosine from ``bc_coef`` to ``bc_coef *
        bc_decay_to`` over this many epochs and stays there (ours; 0 = constant, the paper). The
        demonstrations still fill a share of every batch for the critic.
      bc_decay_to: the fraction of ``bc_coef`` that BC decays to (ours; 0 = off at the end).
      action_l2_decay: the action penalty ``action_l2`` follows the BC coefficient's schedule
        (ours; off = constant, the paper).
      lr_decay_to: both learning rates follow a cosine from their value to this fraction of it
        over the configured epochs (ours; 1 = constant, the paper).
      distill: after the last epoch, each seed's exported policy teaches a student by DAgger with
        lookahead (ours, :mod:`regrasp_mjx.agents.dagger`); ``distill.iterations`` 0 = no such stage.
      checkpoint_every: epochs between checkpoints (the last epoch always writes one); a checkpoint
        holds the full replay buffers (200 MB per seed once full), so writing it every epoch can cost
        more than the epoch.
      validation_size: problems (from a seed of their own) that pick the exported epoch (ours).
      seed: PRNG seed of everything but the planners' own sampling.
      num_seeds: independent learners with seeds ``seed .. seed + num_seeds - 1`` trained as one
        vmapped program (ours; Table I's three seeds in one run).
      devices: local devices the run uses (ours; 0 = all that JAX sees), shared as ``shard`` says.
      shard: how several devices share the work (ours): ``members`` puts whole learners (seeds x
        settings) on each device, with no communication, each learner computing what it computes
        on one device; ``envs`` splits the environments, buffer and batches, data parallel with
        replicated networks and averaged gradients (``num_envs``, ``buffer_size``, ``demo_chunk``
        and both parts of the batch must divide by the device count); ``auto`` (default) takes
        ``members`` when the learners divide evenly over the devices, else ``envs``.
    """

    env: EnvConfig = EnvConfig(check_actions=False)
    exploration: Exploration = EXPLORATION["mixed"]
    settings: tuple[tuple[str, Exploration], ...] = ()
    num_envs: int = 5
    updates_per_iteration: int = 200
    iterations_per_epoch: int = 10
    epochs: int = 500
    batch_size: int = 256
    demo_fraction: float = 0.25
    buffer_size: int = 1_000_000
    gamma: float = 0.99
    lr_actor: float = 1e-4
    lr_critic: float = 1e-4
    polyak: float = 0.95
    target_every: int = 40
    action_l2: float = 1.0
    prm_coef: float = 1e-3
    bc_coef: float = 1e-3
    hidden: tuple[int, ...] = (512, 512, 512)
    num_demos: int = 9900
    planner_budget_s: float = 10.0
    planner_workers: int = 0
    planner_queue: int = 256
    demo_chunk: int = 512
    action_noise: float = 0.2
    obs_noise_mm: float = 0.0
    obs_bias_mm: float = 0.0
    obs_tool_noise_mm: float = 0.0
    critics: int = 2
    critic_layer_norm: bool = False
    target_noise: float = 0.2
    target_noise_clip: float = 0.5
    actor_ema: float = 0.9995
    lr_decay_to: float = 0.1
    bc_decay_epochs: int = 0
    bc_decay_to: float = 0.0
    action_l2_decay: bool = False
    distill: DistillConfig = DistillConfig(iterations=0)
    checkpoint_every: int = 1
    validation_size: int = 1000
    seed: int = 0
    num_seeds: int = 1
    devices: int = 1
    shard: str = "auto"

    def __post_init__(self) -> None:
        learner = ("num_envs", "updates_per_iteration", "iterations_per_epoch", "epochs", "batch_size", "buffer_size")
        others = ("target_every", "num_demos", "planner_queue", "demo_chunk", "num_seeds", "checkpoint_every")
        require_integers(self, learner + others, 1)
        require_integers(self, ("planner_workers", "seed", "devices", "bc_decay_epochs"), 0)
        for name, lo, hi in (("gamma", 0.0, 0.9999), ("polyak", 0.0, 1.0), ("demo_fraction", 0.0, 0.99)):
            require_numbers(self, (name,), lambda v, lo=lo, hi=hi: lo <= v <= hi, f"a number in [{lo}, {hi}]")
        require_numbers(self, ("lr_actor", "lr_critic", "planner_budget_s"), lambda v: v > 0, "a finite number > 0")
        require(self.critics in (1, 2), "critics", self.critics, "1 (the paper) or 2 (clipped double Q)")
        require_numbers(self, ("bc_decay_to",), lambda v: 0.0 <= v <= 1.0, "a fraction in [0, 1]")
        require_flags(self, ("action_l2_decay", "critic_layer_norm"))
        require_numbers(self, ("actor_ema",), lambda v: 0.0 <= v < 1.0, "a decay in [0, 1) (0 = off)")
        require_numbers(self, ("lr_decay_to",), lambda v: 0.0 < v <= 1.0, "a fraction in (0, 1] (1 = constant)")
        require_numbers(
            self,
            ("action_l2", "prm_coef", "bc_coef", "action_noise", "target_noise", "target_noise_clip"),
            lambda v: v >= 0,
            "a finite number >= 0",
        )
        noises = ("obs_noise_mm", "obs_bias_mm", "obs_tool_noise_mm")
        require_numbers(self, noises, lambda v: 0 <= v <= 5, "a noise level in [0, 5] mm")
        require(self.shard in ("auto", "members", "envs"), "shard", self.shard, "one of 'auto', 'members', 'envs'")
        names = [s[0] for s in self.settings]
        ok = len(set(names)) == len(names) and all(isinstance(n, str) and n for n in names)
        require(ok, "settings", names, "distinct, non-empty names")
        ok = bool(self.hidden) and all(is_integer(h) and h > 0 for h in self.hidden)
        require(ok, "hidden", self.hidden, "a tuple of positive layer sizes")
        if self.demo_batch < 1 or self.demo_batch >= self.batch_size:
            raise ConfigError(
                f"batch_size={self.batch_size} with demo_fraction={self.demo_fraction} leaves no "
                "room for online or demonstration samples; accepted: 1 <= round(batch * fraction) < batch"
            )
        require(self.buffer_size >= self.online_batch, "buffer_size", self.buffer_size, "at least one online batch")

    @property
    def demo_batch(self) -> int:
        return int(round(self.batch_size * self.demo_fraction))

    @property
    def online_batch(self) -> int:
        return self.batch_size - self.demo_batch

    @property
    def num_members(self) -> int:
        """Learners in the program: settings x seeds."""
        return max(1, len(self.settings)) * self.num_seeds

    def member_setting(self, m: int) -> tuple[str, Exploration]:
        """``(name, schedule)`` of member ``m`` (name ``""`` when the run has one setting)."""
        return self.settings[m // self.num_seeds] if self.settings else ("", self.exploration)

    def member_seed(self, m: int) -> int:
        return self.seed + m % self.num_seeds

    @property
    def total_updates(self) -> int:
        return self.epochs * self.iterations_per_epoch * self.updates_per_iteration


# Massively parallel (ours): many more episodes per iteration, fewer iterations; the schedules step
# per iteration, so they are scaled to span the same share of training as the paper's.
FAST = TrainConfig(
    num_envs=512,
    updates_per_iteration=200,
    iterations_per_epoch=10,
    epochs=60,
    exploration=Exploration(0.3, 0.3 / 150, 0.1, 0.9 / 60),
    checkpoint_every=10,
)

PRESETS = {
    # The paper's schedule: 500 epochs x 10 iterations x (5 episodes, 200 updates).
    "paper": TrainConfig(),
    "fast": FAST,
    # `fast` with the behaviour-cloning term and the action penalty both decayed to 0 over the first
    # 20 of 60 epochs (ours): BC alone decayed left the penalty shrinking the steps until episodes
    # stalled; with both gone the network takes ~6 steps instead of ~9.5 and plans paper300 at 1.000
    # bare on 3 of 3 seeds (experiments/RESULTS.md, "Decaying BC and the action penalty").
    "decay": dataclasses.replace(FAST, bc_decay_epochs=20, action_l2_decay=True),
    # One network for any goal grasp and needle (ours, issue 15): `decay` on the general task (goal
    # grasp and needle drawn per problem from config.GENERAL_TASK, the observation holding both), with
    # twice the epochs for the wider distribution and BC decayed over the same first third. Its
    # demonstrations come from BIT* (R) on the same ranges.
    "general": dataclasses.replace(
        FAST,
        env=dataclasses.replace(FAST.env, task=GENERAL_TASK),
        epochs=120,
        exploration=Exploration(0.3, 0.3 / 300, 0.1, 0.9 / 120),
        bc_decay_epochs=40,
        action_l2_decay=True,
    ),
    # `fast`, then each seed's exported network teaches a 3x256 student by DAgger with lookahead
    # (the shipped 2x256 default was distilled this way from an earlier `fast` network).
    "distilled": dataclasses.replace(FAST, distill=DistillConfig(iterations=20)),
    # A minute on a CPU: the README's main command and CI.
    "smoke": TrainConfig(
        num_envs=16,
        updates_per_iteration=20,
        iterations_per_epoch=2,
        epochs=2,
        hidden=(64, 64),
        buffer_size=20_000,
        num_demos=24,
        planner_budget_s=2.0,
        planner_workers=1,
        validation_size=100,
        actor_ema=0.99,
        distill=DistillConfig(
            hidden=(64, 64),
            iterations=2,
            problems=32,
            label_states=512,
            updates=20,
            batch_size=128,
            lookahead=20,
            validation_size=100,
        ),
    ),
}


# The paper's learner (SPEC "Learner"): uniform random actions with probability E_R and no other
# exploration noise, one critic, no target smoothing, the raw actor, constant learning rates. Our
# defaults change these five (experiments/RESULTS.md, "Why training decayed"); ``--learner paper``
# puts them back.
PAPER_LEARNER = {"action_noise": 0.0, "critics": 1, "target_noise": 0.0, "actor_ema": 0.0, "lr_decay_to": 1.0}
LEARNERS = ("ours", "paper")


def scaled_exploration(preset: str, setting: str) -> Exploration:
    """Table I's schedule of ``setting``, stretched for presets with fewer iterations than the
    paper's so that E_R and E_T span the same share of training."""
    if setting not in EXPLORATION:
        raise ConfigError(f"exploration={setting!r} is not accepted: one of {sorted(EXPLORATION)}")
    base, explo = PRESETS[preset], EXPLORATION[setting]
    if preset in ("fast", "decay", "distilled", "general") and setting != "targeted":  # keep the scaled schedule's span
        explo = dataclasses.replace(
            base.exploration,
            targeted_eps=explo.targeted_eps,
            targeted_eps_growth=base.exploration.targeted_eps_growth if explo.targeted_eps else 0.0,
        )
    return explo


def grow_with_devices(cfg: TrainConfig, devices: int) -> TrainConfig:
    """Weak scaling for data parallelism (ours): ``cfg``'s sizes read as one device's share, so each
    of ``devices`` devices keeps them and the global ones grow with the count. ``num_envs``,
    ``batch_size``, ``buffer_size`` and ``demo_chunk`` are multiplied by ``devices``; both learning
    rates by ``sqrt(devices)``, the square-root rule for Adam (the gradient noise of a k-times larger
    batch falls by sqrt(k); Malladi et al., "On the SDEs and scaling rules for adaptive gradient
    algorithms", NeurIPS 2022). The schedules step per iteration and stay as they are, and so does
    the replay ratio (updates per environment step). The result runs data parallel (``shard='envs'``).
    """
    if not (isinstance(devices, int) and devices >= 1):
        raise ConfigError(f"devices={devices!r} is not accepted for grow_with_devices: an integer >= 1")
    if cfg.num_members > 1 and cfg.shard == "members":
        raise ConfigError("grow_with_devices is data parallel; shard='members' splits learners instead")
    k, root = devices, math.sqrt(devices)
    return dataclasses.replace(
        cfg,
        num_envs=cfg.num_envs * k,
        batch_size=cfg.batch_size * k,
        buffer_size=cfg.buffer_size * k,
        demo_chunk=cfg.demo_chunk * k,
        lr_actor=cfg.lr_actor * root,
        lr_critic=cfg.lr_critic * root,
        devices=k,
        shard="envs",
    )


def make_config(preset: str, exploration: str = "mixed", learner: str = "ours", **overrides) -> TrainConfig:
    """A preset with Table I's exploration setting (or several, comma-separated, trained side by
    side), the learner (``ours`` or ``paper``) and dotted overrides (``env.horizon=50``)."""

    if preset not in PRESETS:
        raise ConfigError(f"preset={preset!r} is not accepted: one of {sorted(PRESETS)}")
    if learner not in LEARNERS:
        raise ConfigError(f"learner={learner!r} is not accepted: one of {LEARNERS}")
    names = [s.strip() for s in exploration.split(",")]
    if len(set(names)) != len(names):
        raise ConfigError(f"exploration={exploration!r} is not accepted: each setting once")
    schedules = [scaled_exploration(preset, name) for name in names]
    settings = tuple(zip(names, schedules)) if len(names) > 1 else ()
    base = dataclasses.replace(PRESETS[preset], exploration=schedules[0], settings=settings)
    if learner == "paper":
        base = dataclasses.replace(base, **PAPER_LEARNER)
    return replace(base, **overrides)
