"""A third-party learner on our environment (issues 49 and 71): Stable-Baselines3's SAC or TD3,
trained off the shelf on ``gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")`` (the optional ``sb3``
extra: ``pip install -e ".[sb3]"``), with or without our demonstrations read from a Minari dataset,
then judged on a test set through the vector env started from its problems (bare: no shield;
verdicts are RegraspEnv's, the continuous collision test on the true needle, as ``evaluate`` judges
ours). The shipped default runs through the same loop, its row beside.

Without demonstrations (issue 49), SAC with HER for a fixed budget of environment steps:

    python experiments/third_party.py --algo sac --steps 200000 --seed 0 --out experiments/results/third_party

SB3's defaults except: HER (``future``, 4 goals per transition) with ``MultiInputPolicy``, and
``learning_starts`` 1,000; its networks on the CPU (torch) with ``--threads`` threads.

With our demonstrations (issue 71), ``--demos ID`` names a Minari dataset (what
``python -m regrasp_mjx.export_minari`` writes, read by ``minari.load_dataset``):

    python experiments/third_party.py --demos regrasp_mjx/paper-bitstar-v0 --algo td3 --bc-steps 20000 --steps 0 --seed 0 --out experiments/results/third_party

1. Behaviour cloning: the SB3 policy's actor (its deterministic action, ``policy._predict(obs,
   deterministic=True)``: TD3's actor, SAC's squashed mean) regressed onto the demonstrations' actions,
   ``--bc-steps`` Adam steps (``--bc-lr``) on batches of ``--bc-batch`` transitions drawn from all of
   the dataset's, then copied into the actor's target network.
2. ``--steps N`` > 0: SB3 fine-tunes it online for N environment steps with every demonstration
   transition in its replay buffer (a plain ``DictReplayBuffer``, as DDPGfD keeps them; HER's buffer
   does not take transitions from outside its own rollouts), TD3 with Gaussian exploration noise
   of ``--action-noise`` (SB3's TD3 has none by default). Its critic first learns the cloned actor's
   values on the demonstrations alone (``--critic-warmup`` of SB3's own gradient steps with the
   actor's learning rate at 0), so that the first actor updates follow a critic that has seen the
   task rather than a random one.

TD3+BC (Fujimoto & Gu 2021) inside SB3's own update loop, ``--bc-alpha A`` > 0 (issue 71's result:
0.99 on paper300 bare, two seeds; experiments/RESULTS.md, "TD3+BC inside the library"):

    python experiments/third_party.py --demos regrasp_mjx/paper-bitstar9900-v0 --algo td3 --bc-steps 20000 --obs-norm --bc-alpha 2.5 --lr 3e-4 --steps 100000 --n-envs 8 --eval-every 20000 --seed 0 --threads 1 --out experiments/results/third_party

The model is a subclass of SB3's ``TD3`` (``td3_bc_class``) whose ``train`` is SB3's with the actor's
loss ``-lambda Q1(s, pi(s)) + (pi(s) - a)^2``, ``lambda = A / mean|Q1|``, the BC term on the batch's
demonstration rows; the demonstrations in an SB3 ``DictReplayBuffer`` of their own, ``--demo-fraction``
of every batch drawn from it (all of it, ``--offline-steps`` of offline TD3+BC, while SB3's buffer
is empty). Step 2 then runs it from the cloned actor after the critic warm-up, SB3's ``learn`` over
``--n-envs`` environments; ``--no-bc-term`` keeps all of it but the BC term (the ablation). ``--obs-norm`` fixes the demonstrations' mean and standard deviation in
front of the actor and critics (``normalised_extractor``); ``--net-arch`` and ``--lr`` set SB3's
``net_arch`` and ``learning_rate``; ``--eval-every N`` judges the validation problems every N
environment steps (the curve in the results).

Why this learner: ``imitation`` (BC on SB3 policies, the library the issue names) pins
``gymnasium~=0.29`` and ``stable-baselines3~=2.2.1`` in its latest release (1.0.1), and ``d3rlpy``
2.8.1 pins ``gymnasium==1.0.0``: neither installs beside this project's gymnasium 1.2.2. SB3 2.9.2
does (the ``sb3`` extra issue 49 already pinned); it has no BC of its own, so step 1 is the
supervised regression imitation's BC performs on the same networks (mean squared error for a
deterministic actor), written out in a few lines; the networks, the replay buffer and the RL updates
are SB3's. The budget is fixed and stated: the BC steps, the environment steps, the critic warm-up.

Each policy is judged on ``--validation`` problems of their own seed (1,000,003, our learner's
validation seed for its seed 0; the choice of settings was made there) and on the test set; the
test set is reported, never chosen on. A policy from the demonstrations gets rows for the cloned
actor and, with ``--steps`` > 0, the fine-tuned one.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.interfaces.gym_envs import NeedleRegraspVectorEnv, gym_id
from regrasp_mjx.world.sampling import Episode, load_testset

VALIDATION_SEED = 1_000_003  # our learner's validation problems for its seed 0 (world.testsets.make_testset)
INSTALL = "pip install -e '.[sb3,minari]'"


def judge(act, testset, name: str = "NeedleRegrasp", config_overrides: dict | None = None) -> dict:
    """Every problem of ``testset`` (a test set's name or path, or an ``Episode`` batch) rolled out by
    ``act(obs_dict) -> actions`` until it ends (the first end of each row counts; autoreset off), in
    one vector env of as many rows."""
    episodes = testset if isinstance(testset, Episode) else load_testset(testset)[0]
    n = int(np.shape(episodes.needle_pos)[0])
    venv = NeedleRegraspVectorEnv(num_envs=n, name=name, config_overrides=config_overrides, autoreset_mode="disabled")
    obs, _ = venv.reset(seed=0, options={"episodes": episodes})
    outcome = np.full(n, "", dtype=object)
    steps = np.zeros(n, int)
    t0 = time.perf_counter()
    while (outcome == "").any():
        obs, _, terminated, truncated, info = venv.step(act(obs))
        live = outcome == ""
        steps[live] += 1
        ended = live & (terminated | truncated)
        outcome[ended & info["success"]] = "success"
        outcome[ended & info["collision"]] = "collision"
        outcome[ended & ~info["success"] & ~info["collision"]] = "time-out"
    wall = time.perf_counter() - t0
    return {
        "problems": n,
        "success": float(np.mean(outcome == "success")),
        "collision": float(np.mean(outcome == "collision")),
        "time_out": float(np.mean(outcome == "time-out")),
        "mean_steps_success": float(steps[outcome == "success"].mean()) if (outcome == "success").any() else None,
        "judge_wall_s": round(wall, 2),
    }


@dataclasses.dataclass
class Demonstrations:
    """A Minari dataset's transitions, flat: goal-dict observations before and after each step."""

    obs: dict[str, np.ndarray]
    next_obs: dict[str, np.ndarray]
    actions: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    episodes: int
    env_name: str  # the registry / gymnasium name of the dataset's environment
    config_overrides: dict
    dataset_id: str

    def __len__(self) -> int:
        return len(self.actions)


def load_demonstrations(dataset_id: str) -> Demonstrations:
    """Every episode of the Minari dataset ``dataset_id`` (``minari.load_dataset``), flattened. Refuses
    one that is not of a regrasp_mjx environment."""
    import minari

    dataset = minari.load_dataset(dataset_id)
    spec = dataset.env_spec
    if spec is None or not str(spec.id).startswith("regrasp_mjx/"):
        raise SystemExit(f"--demos {dataset_id}: its environment is {spec and spec.id!r}, not a regrasp_mjx one")
    keys = ("achieved_goal", "desired_goal", "observation")
    obs, nxt, actions, rewards, terms = {k: [] for k in keys}, {k: [] for k in keys}, [], [], []
    for episode in dataset.iterate_episodes():
        for k in keys:
            obs[k].append(episode.observations[k][:-1])
            nxt[k].append(episode.observations[k][1:])
        actions.append(episode.actions)
        rewards.append(episode.rewards)
        terms.append(episode.terminations)
    if not actions:
        raise SystemExit(f"--demos {dataset_id}: the dataset has no episodes")

    def cat(xs):
        return np.concatenate(xs).astype(np.float32)

    return Demonstrations(
        obs={k: cat(v) for k, v in obs.items()},
        next_obs={k: cat(v) for k, v in nxt.items()},
        actions=cat(actions),
        rewards=cat(rewards),
        terminations=np.concatenate(terms).astype(bool),
        episodes=len(actions),
        env_name=str(spec.kwargs.get("name", "NeedleRegrasp")),
        config_overrides=dict(spec.kwargs.get("config_overrides") or {}),
        dataset_id=dataset_id,
    )


def behaviour_clone(model, demos: Demonstrations, steps: int, batch: int, lr: float, seed: int) -> list[float]:
    """``steps`` Adam steps of mean squared error between the SB3 policy's deterministic action and
    the demonstrations' (batches drawn with replacement); the actor's target network (TD3's) is then
    set to the cloned actor. Returns the loss every 10 % of the steps."""
    import torch

    policy = model.policy
    optimiser = torch.optim.Adam(policy.actor.parameters(), lr=lr)
    obs = {k: torch.as_tensor(v) for k, v in demos.obs.items()}
    actions = torch.as_tensor(demos.actions)
    rng = np.random.default_rng(seed)
    policy.set_training_mode(True)
    losses = []
    for i in range(steps):
        idx = torch.as_tensor(rng.integers(0, len(demos), batch))
        predicted = policy._predict({k: v[idx] for k, v in obs.items()}, deterministic=True)
        loss = torch.nn.functional.mse_loss(predicted, actions[idx])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if (i + 1) % max(steps // 10, 1) == 0 or i + 1 == steps:
            losses.append(round(float(loss.detach()), 5))
    policy.set_training_mode(False)
    if getattr(model, "actor_target", None) is not None:
        model.actor_target.load_state_dict(model.actor.state_dict())
    return losses


def fill_replay_buffer(model, demos: Demonstrations) -> None:
    """Every demonstration transition into the model's (dict) replay buffer, as SB3 stores its own
    (``done`` on a termination; a demonstration ends at its first success)."""
    buffer = model.replay_buffer
    if len(demos) > buffer.buffer_size:
        raise SystemExit(f"{len(demos)} demonstration transitions do not fit a replay buffer of {buffer.buffer_size}")
    for i in range(len(demos)):
        buffer.add(
            {k: v[i : i + 1] for k, v in demos.obs.items()},
            {k: v[i : i + 1] for k, v in demos.next_obs.items()},
            demos.actions[i : i + 1],
            demos.rewards[i : i + 1],
            demos.terminations[i : i + 1],
            [{}],
        )


def warm_critic(model, steps: int, batch: int) -> None:
    """``steps`` of SB3's own TD3/SAC gradient steps on what the buffer holds (the demonstrations)
    with the actor's learning rate at 0: the critic learns the cloned actor's values, the actor stays."""
    from stable_baselines3.common.logger import Logger

    if getattr(model, "_logger", None) is None:  # learn() sets one up; train() before it needs one
        model.set_logger(Logger(folder=None, output_formats=[]))
    actor_groups = model.actor.optimizer.param_groups
    saved = [g["lr"] for g in actor_groups]
    schedule = model.lr_schedule
    model.lr_schedule = lambda _: schedule(1.0)
    original = model._update_learning_rate

    def keep_actor_still(optimizers):
        original(optimizers)
        for g in actor_groups:
            g["lr"] = 0.0

    model._update_learning_rate = keep_actor_still
    try:
        model.train(gradient_steps=steps, batch_size=batch)
    finally:
        model._update_learning_rate = original
        model.lr_schedule = schedule
        for g, lr in zip(actor_groups, saved):
            g["lr"] = lr
        if getattr(model, "actor_target", None) is not None:
            model.actor_target.load_state_dict(model.actor.state_dict())


def demonstration_statistics(demos: Demonstrations) -> dict[str, dict[str, list[float]]]:
    """Each observation key's per-component mean and standard deviation over the demonstrations'
    transitions (what ``--obs-norm`` fixes in the policy's input layer)."""
    return {
        k: {"mean": v.mean(0).astype(float).tolist(), "std": v.std(0).astype(float).tolist()}
        for k, v in demos.obs.items()
    }


def normalised_extractor(torch, sb3):
    """SB3's ``CombinedExtractor`` with fixed input statistics: each key's components
    ``(x - mean) / max(std, 1e-6)``, clipped to +-5 (brax's running statistics and clip, as our learner
    normalises its inputs, fixed here from the demonstrations), then flattened and concatenated in the
    observation space's key order. The statistics are buffers of the module: they travel with the
    policy; SB3's TD3 gives the actor and each critic an instance of their own."""
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class NormalisedCombinedExtractor(BaseFeaturesExtractor):
        def __init__(self, observation_space, statistics: dict, clip: float = 5.0):
            keys = list(observation_space.spaces)
            if sorted(keys) != sorted(statistics):
                raise ValueError(f"statistics for {sorted(statistics)}, observations have {sorted(keys)}")
            size = sum(int(np.prod(observation_space.spaces[k].shape)) for k in keys)
            super().__init__(observation_space, features_dim=size)
            self.keys, self.clip = keys, clip
            for k in keys:
                shape = observation_space.spaces[k].shape
                mean = torch.as_tensor(statistics[k]["mean"], dtype=torch.float32).reshape(shape)
                std = torch.as_tensor(statistics[k]["std"], dtype=torch.float32).reshape(shape).clamp(min=1e-6)
                self.register_buffer(f"mean_{k}", mean)
                self.register_buffer(f"std_{k}", std)

        def forward(self, observations):
            parts = []
            for k in self.keys:
                x = (observations[k] - getattr(self, f"mean_{k}")) / getattr(self, f"std_{k}")
                parts.append(x.clamp(-self.clip, self.clip).flatten(1))
            return torch.cat(parts, dim=1)

    return NormalisedCombinedExtractor


def td3_bc_class(torch, sb3):
    """SB3's TD3 with TD3+BC's actor loss (Fujimoto & Gu 2021) inside its own ``train``:
    ``-lambda * Q1(s, pi(s)) + (pi(s) - a_demo)^2`` with ``lambda = alpha / mean|Q1|`` (the batch's,
    no gradient through it), the BC term (mean squared error, as the paper's) on the batch's
    demonstration rows. The demonstrations live in a replay buffer of their own (SB3's
    ``DictReplayBuffer``, ``model.demo_buffer``, never overwritten); each batch takes
    ``demo_fraction`` of its transitions from it and the rest from SB3's own buffer (the online
    transitions; DDPGfD's and our learner's split), all of it from the demonstrations while SB3's buffer
    is empty (the offline phase: TD3+BC as the paper's). Everything else is ``TD3.train`` as SB3 2.9
    writes it: twin critics with clipped target-policy noise, the delayed actor update, Polyak targets."""
    from stable_baselines3.common.type_aliases import DictReplayBufferSamples

    functional = torch.nn.functional

    def concatenate(a, b):
        if a is None:
            return None
        if isinstance(a, dict):
            return {k: torch.cat([a[k], b[k]]) for k in a}
        return torch.cat([a, b])

    class TD3BC(sb3.TD3):
        bc_alpha: float = 2.5
        bc_weight: float = 1.0  # 0: the BC term dropped (the ablation, --no-bc-term)
        demo_fraction: float = 0.25
        demo_buffer = None
        last_stats: dict = {}

        def sample_batch(self, batch_size: int):
            """(samples, rows from the demonstrations: the first ones)."""
            online = self.replay_buffer.size() if self.replay_buffer is not None else 0
            n_demo = batch_size if online == 0 else int(round(self.demo_fraction * batch_size))
            demo = self.demo_buffer.sample(n_demo, env=self._vec_normalize_env) if n_demo else None
            if n_demo == batch_size:
                return demo, n_demo
            own = self.replay_buffer.sample(batch_size - n_demo, env=self._vec_normalize_env)
            if demo is None:
                return own, 0
            return DictReplayBufferSamples(*(concatenate(a, b) for a, b in zip(demo, own))), n_demo

        def train(self, gradient_steps: int, batch_size: int = 100) -> None:
            from stable_baselines3.common.utils import polyak_update

            self.policy.set_training_mode(True)
            self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
            actor_losses, critic_losses, bc_losses, lambdas, qs = [], [], [], [], []
            for _ in range(gradient_steps):
                self._n_updates += 1
                data, n_demo = self.sample_batch(batch_size)
                discounts = data.discounts if data.discounts is not None else self.gamma
                with torch.no_grad():
                    noise = data.actions.clone().data.normal_(0, self.target_policy_noise)
                    noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                    next_actions = (self.actor_target(data.next_observations) + noise).clamp(-1, 1)
                    next_q = torch.cat(self.critic_target(data.next_observations, next_actions), dim=1)
                    next_q, _ = torch.min(next_q, dim=1, keepdim=True)
                    target_q = data.rewards + (1 - data.dones) * discounts * next_q
                current_q = self.critic(data.observations, data.actions)
                critic_loss = sum(functional.mse_loss(q, target_q) for q in current_q)
                critic_losses.append(critic_loss.item())
                self.critic.optimizer.zero_grad()
                critic_loss.backward()
                self.critic.optimizer.step()

                if self._n_updates % self.policy_delay == 0:
                    pi = self.actor(data.observations)
                    q = self.critic.q1_forward(data.observations, pi)
                    lam = self.bc_alpha / q.abs().mean().detach().clamp(min=1e-6)
                    bc = functional.mse_loss(pi[:n_demo], data.actions[:n_demo]) if n_demo else pi.sum() * 0.0
                    actor_loss = -lam * q.mean() + self.bc_weight * bc
                    actor_losses.append(actor_loss.item())
                    bc_losses.append(bc.item())
                    lambdas.append(lam.item())
                    qs.append(q.mean().item())
                    self.actor.optimizer.zero_grad()
                    actor_loss.backward()
                    self.actor.optimizer.step()
                    polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                    polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
                    polyak_update(self.critic_batch_norm_stats, self.critic_batch_norm_stats_target, 1.0)
                    polyak_update(self.actor_batch_norm_stats, self.actor_batch_norm_stats_target, 1.0)

            self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
            self.logger.record("train/critic_loss", np.mean(critic_losses))
            if actor_losses:
                self.last_stats = {
                    "critic_loss": float(np.mean(critic_losses)),
                    "actor_loss": float(np.mean(actor_losses)),
                    "bc_loss": float(np.mean(bc_losses)),
                    "lambda": float(np.mean(lambdas)),
                    "q": float(np.mean(qs)),
                }
                self.logger.record("train/actor_loss", self.last_stats["actor_loss"])
                self.logger.record("train/bc_loss", self.last_stats["bc_loss"])

    return TD3BC


def fill_demo_buffer(model, demos: Demonstrations) -> None:
    """A ``DictReplayBuffer`` (SB3's) of exactly the demonstrations, as ``model.demo_buffer``."""
    from stable_baselines3.common.buffers import DictReplayBuffer

    model.demo_buffer = DictReplayBuffer(
        len(demos), model.observation_space, model.action_space, device=model.device, n_envs=1
    )
    real = model.replay_buffer
    model.replay_buffer = model.demo_buffer
    try:
        fill_replay_buffer(model, demos)
    finally:
        model.replay_buffer = real


def train_offline(model, steps: int, batch: int, chunk: int = 1000, log=print) -> list[dict]:
    """``steps`` of the model's own gradient steps while SB3's buffer is empty (TD3+BC on the
    demonstrations alone), in chunks; the statistics of each chunk's last call."""
    from stable_baselines3.common.logger import Logger

    if getattr(model, "_logger", None) is None:
        model.set_logger(Logger(folder=None, output_formats=[]))
    history, t0, done = [], time.perf_counter(), 0
    while done < steps:
        n = min(chunk, steps - done)
        model.train(gradient_steps=n, batch_size=batch)
        done += n
        history.append({"step": done, **{k: round(v, 5) for k, v in model.last_stats.items()}})
        if done % max(steps // 10, 1) < chunk or done == steps:
            log(f"offline TD3+BC {done:,}/{steps:,} steps, {time.perf_counter() - t0:.0f} s: {history[-1]}")
    return history


def _Progress(total: int, t0: float, sb3, evaluate=None, eval_every: int = 0, curve: list | None = None):
    """A line every 5 % of the budget: steps, rate, ETA and the last episodes' success (SB3's own
    progress bar draws only on a terminal); with ``evaluate``, its result every ``eval_every`` steps
    appended to ``curve`` (the time it takes left out of the rate)."""

    class Progress(sb3.common.callbacks.BaseCallback):
        eval_s = 0.0
        next_eval = eval_every
        next_line = every = max(total // 20, 1)

        def _on_step(self) -> bool:  # num_timesteps grows by the number of environments
            if evaluate is not None and eval_every and self.num_timesteps >= self.next_eval:
                self.next_eval += eval_every
                t = time.perf_counter()
                curve.append({"env_steps": self.num_timesteps, **evaluate()})
                self.eval_s += time.perf_counter() - t
                print(f"{self.num_timesteps:,} steps, judged: {curve[-1]}", flush=True)
            if self.num_timesteps >= self.next_line:
                self.next_line += self.every
                rate = self.num_timesteps / (time.perf_counter() - t0 - self.eval_s)
                recent = [float(x) for x in self.model.ep_success_buffer]
                success = f"{np.mean(recent):.2f}" if recent else "n/a"
                stats = getattr(self.model, "last_stats", None)
                print(
                    f"{self.num_timesteps:,}/{total:,} steps, {rate:.0f}/s, ETA {(total - self.num_timesteps) / rate / 60:.1f} min, "
                    f"success of the last {len(recent)} episodes {success}"
                    + (f"; {', '.join(f'{k} {v:.4g}' for k, v in stats.items())}" if stats else ""),
                    flush=True,
                )
            return True

    return Progress()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--algo", choices=("sac", "td3"), default="sac")
    p.add_argument("--no-her", action="store_true", help="a plain replay buffer instead of HER's (without --demos)")
    p.add_argument(
        "--steps",
        type=int,
        default=200_000,
        help="environment steps of RL training (the budget; 0 with --demos: BC only)",
    )
    p.add_argument("--n-envs", type=int, default=1, help="environments SB3 steps side by side (DummyVecEnv)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--testset", default="paper300")
    p.add_argument("--out", default=None)
    demo = p.add_argument_group("with demonstrations (issue 71)")
    demo.add_argument(
        "--demos", default=None, metavar="ID", help="a Minari dataset id (python -m regrasp_mjx.export_minari)"
    )
    demo.add_argument("--bc-steps", type=int, default=20_000, help="behaviour-cloning Adam steps (default 20,000)")
    demo.add_argument("--bc-batch", type=int, default=256)
    demo.add_argument("--bc-lr", type=float, default=1e-3)
    demo.add_argument(
        "--critic-warmup", type=int, default=5_000, help="critic steps on the demonstrations before fine-tuning"
    )
    demo.add_argument("--action-noise", type=float, default=0.1, help="TD3's Gaussian exploration noise (sigma)")
    demo.add_argument(
        "--obs-norm",
        action="store_true",
        help="normalise the policy's inputs by the demonstrations' mean and std (fixed; clipped to +-5)",
    )
    demo.add_argument(
        "--net-arch",
        default=None,
        metavar="N,N,..",
        help="hidden layers of actor and critics (SB3's default: TD3 400,300)",
    )
    demo.add_argument("--lr", type=float, default=None, help="the RL learning rate (SB3's default: TD3 1e-3)")
    demo.add_argument(
        "--bc-alpha",
        type=float,
        default=0.0,
        help="TD3+BC's alpha (Fujimoto & Gu: 2.5): the BC term inside SB3 TD3's updates; 0: SB3's TD3 as is",
    )
    demo.add_argument(
        "--offline-steps",
        type=int,
        default=0,
        help="TD3+BC gradient steps on the demonstrations alone, after the warm-up",
    )
    demo.add_argument(
        "--demo-fraction",
        type=float,
        default=0.25,
        help="TD3+BC online: share of each batch drawn from the demonstrations' buffer (ours: 0.25)",
    )
    demo.add_argument(
        "--no-bc-term",
        action="store_true",
        help="with --bc-alpha: TD3+BC's buffers, batches and warm-up, its actor loss without the BC term (an ablation)",
    )
    demo.add_argument(
        "--eval-every",
        type=int,
        default=0,
        help="judge the validation problems every N env steps of RL training (a curve in the results; 0: never)",
    )
    demo.add_argument(
        "--validation",
        type=int,
        default=300,
        help=f"problems of seed {VALIDATION_SEED} judged beside the test set (0: none)",
    )
    args = p.parse_args(argv)
    if args.steps < 0 or args.n_envs < 1 or (args.steps == 0 and args.demos is None):
        p.error("--steps must be >= 1 (>= 0 with --demos) and --n-envs >= 1")
    if min(args.bc_steps, args.critic_warmup, args.validation) < 0 or args.bc_batch < 1 or not args.bc_lr > 0:
        p.error("--bc-steps, --critic-warmup and --validation must be >= 0, --bc-batch >= 1 and --bc-lr > 0")
    if args.net_arch is not None:
        try:
            args.net_arch = [int(n) for n in args.net_arch.split(",")]
        except ValueError:
            p.error(f"--net-arch {args.net_arch!r}: hidden layer sizes separated by commas, e.g. 512,512,512")
        if not args.net_arch or min(args.net_arch) < 1:
            p.error("--net-arch: hidden layer sizes >= 1")
    if not (args.bc_alpha >= 0 and args.offline_steps >= 0 and args.eval_every >= 0 and 0 <= args.demo_fraction < 1):
        p.error("--bc-alpha, --offline-steps and --eval-every must be >= 0 and --demo-fraction in [0, 1)")
    if (args.bc_alpha > 0 or args.obs_norm) and args.demos is None:
        p.error("--bc-alpha and --obs-norm need --demos (the demonstrations' actions and statistics)")
    if args.bc_alpha > 0 and args.algo != "td3":
        p.error("--bc-alpha is TD3+BC: --algo td3")
    if (args.offline_steps or args.no_bc_term) and not args.bc_alpha > 0:
        p.error("--offline-steps and --no-bc-term are TD3+BC's: give --bc-alpha > 0")
    if args.demos is not None and args.steps and args.n_envs > 1 and not args.bc_alpha > 0:
        p.error(
            "--demos with --steps > 0 and --n-envs > 1 needs --bc-alpha: without it the demonstrations go into SB3's one buffer, which takes a row per environment"
        )
    if args.lr is not None and not args.lr > 0:
        p.error("--lr must be > 0")
    try:  # the optional extras: torch and Stable-Baselines3 (and Minari for --demos)
        import gymnasium
        import stable_baselines3 as sb3
        import stable_baselines3.common.callbacks  # noqa: F401
        import torch
        from stable_baselines3.common.env_util import make_vec_env
        from stable_baselines3.common.noise import NormalActionNoise

        if args.demos is not None:
            import minari  # noqa: F401
    except ImportError as err:
        raise SystemExit(f"{err}: this script needs the sb3 extra (and minari for --demos), {INSTALL}") from None

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    demos = load_demonstrations(args.demos) if args.demos is not None else None
    name, overrides = (demos.env_name, demos.config_overrides) if demos else ("NeedleRegrasp", {})
    env = make_vec_env(
        lambda: gymnasium.make(gym_id(name), config_overrides=overrides), n_envs=args.n_envs, seed=args.seed
    )
    td3_bc = args.bc_alpha > 0
    algo = td3_bc_class(torch, sb3) if td3_bc else {"sac": sb3.SAC, "td3": sb3.TD3}[args.algo]
    kwargs = {"seed": args.seed, "learning_starts": 1000, "verbose": 0}
    policy_kwargs = {}
    if args.net_arch is not None:
        policy_kwargs["net_arch"] = args.net_arch
    if args.obs_norm:
        policy_kwargs["features_extractor_class"] = normalised_extractor(torch, sb3)
        policy_kwargs["features_extractor_kwargs"] = {"statistics": demonstration_statistics(demos)}
    if policy_kwargs:
        kwargs["policy_kwargs"] = policy_kwargs
    if args.lr is not None:
        kwargs["learning_rate"] = args.lr
    if demos is None and not args.no_her:
        kwargs["replay_buffer_class"] = sb3.HerReplayBuffer
    if demos is not None:
        kwargs["learning_starts"] = 0  # the buffer starts full of demonstrations
        if args.algo == "td3":
            kwargs["action_noise"] = NormalActionNoise(np.zeros(6), np.full(6, args.action_noise))
    model = algo("MultiInputPolicy", env, **kwargs)
    if td3_bc:
        model.bc_alpha, model.demo_fraction = args.bc_alpha, args.demo_fraction
        model.bc_weight = 0.0 if args.no_bc_term else 1.0

    def sb3_act(obs):
        return model.predict(obs, deterministic=True)[0]

    def judged(act) -> dict:
        return {
            "test": judge(act, args.testset, name, overrides),
            **({"validation": judge(act, validation, name, overrides)} if validation is not None else {}),
        }

    validation = None
    if demos is not None and args.validation:
        from regrasp_mjx.interfaces import registry
        from regrasp_mjx.world.testsets import make_testset

        config = registry.load(name, config_overrides=overrides).env_config
        validation = make_testset(args.validation, VALIDATION_SEED, config)

    label = f"SB3 {args.algo.upper()}" + ("+BC" if td3_bc and not args.no_bc_term else "")
    if args.no_bc_term:
        label += " (TD3+BC's buffers and batches, no BC term)"
    rows, stages = {}, {}
    t0 = time.perf_counter()
    if demos is not None:
        t = time.perf_counter()
        losses = behaviour_clone(model, demos, args.bc_steps, args.bc_batch, args.bc_lr, args.seed)
        stages["bc_wall_s"] = round(time.perf_counter() - t, 1)
        stages["bc_losses"] = losses
        print(f"BC: {args.bc_steps:,} steps in {stages['bc_wall_s']} s, loss {losses}", flush=True)
        rows[f"SB3 {args.algo.upper()} actor, BC on the demonstrations"] = judged(sb3_act)
        print(json.dumps({k: {s: v[s]["success"] for s in v} for k, v in rows.items()}), flush=True)
    if td3_bc and (args.steps or args.offline_steps):
        t = time.perf_counter()
        fill_demo_buffer(model, demos)
        warm_critic(model, args.critic_warmup, model.batch_size)
        stages["critic_warmup_wall_s"] = round(time.perf_counter() - t, 1)
        print(f"demonstration buffer and critic warm-up: {stages['critic_warmup_wall_s']} s", flush=True)
        if args.offline_steps:
            t = time.perf_counter()
            stages["offline_history"] = train_offline(model, args.offline_steps, model.batch_size)
            stages["offline_wall_s"] = round(time.perf_counter() - t, 1)
            rows[f"{label}, BC then {args.offline_steps:,} TD3+BC steps on the demonstrations"] = judged(sb3_act)
            print(json.dumps({k: {s: v[s]["success"] for s in v} for k, v in rows.items()}), flush=True)
    if args.steps:
        if demos is not None and not td3_bc:
            t = time.perf_counter()
            fill_replay_buffer(model, demos)
            warm_critic(model, args.critic_warmup, model.batch_size)
            stages["critic_warmup_wall_s"] = round(time.perf_counter() - t, 1)
        t = time.perf_counter()
        curve: list[dict] = []

        def evaluate() -> dict:
            result = judge(sb3_act, validation, name, overrides)
            return {k: result[k] for k in ("success", "collision", "time_out")}

        progress = _Progress(args.steps, t, sb3, evaluate if validation is not None else None, args.eval_every, curve)
        model.learn(total_timesteps=args.steps, callback=progress)
        stages["rl_wall_s"] = round(time.perf_counter() - t - progress.eval_s, 1)
        if curve:
            stages["validation_curve"] = curve
            stages["validation_curve_wall_s"] = round(progress.eval_s, 1)
        her = "" if demos is not None or args.no_her else " + HER"
        offline = f", {args.offline_steps:,} TD3+BC steps" if args.offline_steps else ""
        tuned = (
            f"{label}{her}"
            if demos is None
            else f"{label}, BC{offline} then {args.steps:,} env steps with the demonstrations"
        )
        rows[tuned] = judged(sb3_act)
    train_s = time.perf_counter() - t0  # the judging of the cloned actor included (seconds)

    ours_policy = load_policy()
    rows["regrasp_mjx default (shipped)"] = judged(lambda obs: ours_policy.act(obs["observation"]))
    data = {
        "machine": machine(),
        "versions": {"stable_baselines3": sb3.__version__, "torch": torch.__version__},
        "args": vars(args),
        "train_wall_s": round(train_s, 1),
        **stages,
        **({"env_steps_per_s": round(args.steps / stages["rl_wall_s"], 1)} if args.steps else {}),
        **(
            {"demonstrations": {"dataset": demos.dataset_id, "episodes": demos.episodes, "transitions": len(demos)}}
            if demos
            else {}
        ),
        "rows": rows,
    }
    if demos is None:
        head = f"SB3 trained {args.steps:,} env steps (seed {args.seed}) in {train_s:.0f} s"
    else:
        offline = f", {args.offline_steps:,} offline TD3+BC steps" if args.offline_steps else ""
        head = (
            f"{label} from {demos.episodes:,} demonstrations ({args.demos}): BC {args.bc_steps:,} steps{offline}, "
            f"then {args.steps:,} env steps (seed {args.seed}), {train_s:.0f} s"
        )
    sets = ["test"] + (["validation"] if validation is not None else [])
    lines = [
        f"{args.testset}, bare (no shield), each problem's first end; {head} on {machine(devices=False)}",
        "",
        "| learner | " + " | ".join(f"{s} success | {s} collision | {s} time-out" for s in sets) + " |",
        "| --- |" + " ---: | ---: | ---: |" * len(sets),
        *(
            f"| {k} | "
            + " | ".join(f"{v[s]['success']:.3f} | {v[s]['collision']:.3f} | {v[s]['time_out']:.3f}" for s in sets)
            + " |"
            for k, v in rows.items()
        ),
    ]
    if demos is None:
        stem = f"{args.algo}{'' if args.no_her else '_her'}_seed{args.seed}"
    else:
        dataset = args.demos.rsplit("/", 1)[-1]  # the id without its namespace
        tags = "".join(
            (
                "_norm" if args.obs_norm else "",
                f"_net{'x'.join(map(str, args.net_arch))}" if args.net_arch else "",
                f"_lr{args.lr:g}" if args.lr is not None else "",
                f"_td3bc{args.bc_alpha:g}_off{args.offline_steps}_df{args.demo_fraction:g}" if td3_bc else "",
                "_nobc" if args.no_bc_term else "",
                f"_envs{args.n_envs}" if args.n_envs > 1 else "",
                f"_noise{args.action_noise:g}" if args.action_noise != 0.1 else "",
            )
        )
        stem = f"{dataset}_{args.algo}_bc{args.bc_steps}_steps{args.steps}{tags}_seed{args.seed}"
    write_results(args.out, stem, lines, data)
    print("\n".join(lines))
    print(json.dumps({"train_wall_s": data["train_wall_s"], **{k: v["test"]["success"] for k, v in rows.items()}}))


if __name__ == "__main__":
    main()
