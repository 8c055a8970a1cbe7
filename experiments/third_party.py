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


def _Progress(total: int, t0: float, sb3):
    """A line every 5 % of the budget: steps, rate, ETA and the last episodes' success (SB3's own
    progress bar draws only on a terminal)."""

    class Progress(sb3.common.callbacks.BaseCallback):
        def _on_step(self) -> bool:
            every = max(total // 20, 1)
            if self.num_timesteps % every == 0:
                rate = self.num_timesteps / (time.perf_counter() - t0)
                recent = [float(x) for x in self.model.ep_success_buffer]
                success = f"{np.mean(recent):.2f}" if recent else "n/a"
                print(
                    f"{self.num_timesteps:,}/{total:,} steps, {rate:.0f}/s, ETA {(total - self.num_timesteps) / rate / 60:.1f} min, "
                    f"success of the last {len(recent)} episodes {success}",
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
    algo = {"sac": sb3.SAC, "td3": sb3.TD3}[args.algo]
    kwargs = {"seed": args.seed, "learning_starts": 1000, "verbose": 0}
    if demos is None and not args.no_her:
        kwargs["replay_buffer_class"] = sb3.HerReplayBuffer
    if demos is not None:
        kwargs["learning_starts"] = 0  # the buffer starts full of demonstrations
        if args.algo == "td3":
            kwargs["action_noise"] = NormalActionNoise(np.zeros(6), np.full(6, args.action_noise))
    model = algo("MultiInputPolicy", env, **kwargs)

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

    label = f"SB3 {args.algo.upper()}"
    rows, stages = {}, {}
    t0 = time.perf_counter()
    if demos is not None:
        t = time.perf_counter()
        losses = behaviour_clone(model, demos, args.bc_steps, args.bc_batch, args.bc_lr, args.seed)
        stages["bc_wall_s"] = round(time.perf_counter() - t, 1)
        stages["bc_losses"] = losses
        print(f"BC: {args.bc_steps:,} steps in {stages['bc_wall_s']} s, loss {losses}", flush=True)
        rows[f"{label} actor, BC on the demonstrations"] = judged(sb3_act)
        print(json.dumps({k: {s: v[s]["success"] for s in v} for k, v in rows.items()}), flush=True)
    if args.steps:
        if demos is not None:
            t = time.perf_counter()
            fill_replay_buffer(model, demos)
            warm_critic(model, args.critic_warmup, model.batch_size)
            stages["critic_warmup_wall_s"] = round(time.perf_counter() - t, 1)
        t = time.perf_counter()
        model.learn(total_timesteps=args.steps, callback=_Progress(args.steps, t, sb3))
        stages["rl_wall_s"] = round(time.perf_counter() - t, 1)
        her = "" if demos is not None or args.no_her else " + HER"
        tuned = (
            f"{label}{her}" if demos is None else f"{label}, BC then {args.steps:,} env steps with the demonstrations"
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
        head = (
            f"SB3 {args.algo.upper()} from {demos.episodes:,} demonstrations ({args.demos}): BC {args.bc_steps:,} steps, "
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
        stem = f"{dataset}_{args.algo}_bc{args.bc_steps}_steps{args.steps}_seed{args.seed}"
    write_results(args.out, stem, lines, data)
    print("\n".join(lines))
    print(json.dumps({"train_wall_s": data["train_wall_s"], **{k: v["test"]["success"] for k, v in rows.items()}}))


if __name__ == "__main__":
    main()
