"""A third-party learner on our environment (issue 49): Stable-Baselines3's SAC or TD3, with HER
by default, trained off the shelf for a fixed budget of environment steps on
``gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")`` (the optional ``sb3`` extra:
``pip install -e ".[sb3]"``), then judged on a test set through the vector env started from its
problems (bare: no shield; verdicts are RegraspEnv's, the continuous collision test on the true
needle, as ``evaluate`` judges ours). The shipped default runs through the same loop, its row beside.

    python experiments/third_party.py --algo sac --steps 200000 --seed 0 --out experiments/results/third_party

SB3's defaults except: HER (``future``, 4 goals per transition) with ``MultiInputPolicy``, and
``learning_starts`` 1,000; its networks on the CPU (torch) with ``--threads`` threads.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.interfaces.gym_envs import NeedleRegraspVectorEnv, gym_id
from regrasp_mjx.world.sampling import load_testset


def judge(act, testset: str, name: str = "NeedleRegrasp") -> dict:
    """Every problem of ``testset`` rolled out by ``act(obs_dict) -> actions`` until it ends (the
    first end of each row counts; autoreset off), in one vector env of as many rows."""
    episodes, _ = load_testset(testset)
    n = int(np.shape(episodes.needle_pos)[0])
    venv = NeedleRegraspVectorEnv(num_envs=n, name=name, autoreset_mode="disabled")
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--algo", choices=("sac", "td3"), default="sac")
    p.add_argument("--no-her", action="store_true", help="a plain replay buffer instead of HER's")
    p.add_argument("--steps", type=int, default=200_000, help="environment steps of training (the budget)")
    p.add_argument("--n-envs", type=int, default=1, help="environments SB3 steps side by side (DummyVecEnv)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--testset", default="paper300")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    if args.steps < 1 or args.n_envs < 1:
        p.error("--steps and --n-envs must be >= 1")
    try:  # the optional extra: torch and Stable-Baselines3
        import gymnasium
        import stable_baselines3 as sb3
        import stable_baselines3.common.callbacks  # noqa: F401
        import torch
        from stable_baselines3.common.env_util import make_vec_env
    except ImportError as err:
        raise SystemExit(f"{err}: this script needs the sb3 extra, pip install -e '.[sb3]'") from None

    torch.set_num_threads(args.threads)
    env = make_vec_env(lambda: gymnasium.make(gym_id("NeedleRegrasp")), n_envs=args.n_envs, seed=args.seed)
    algo = {"sac": sb3.SAC, "td3": sb3.TD3}[args.algo]
    her = {} if args.no_her else {"replay_buffer_class": sb3.HerReplayBuffer}
    model = algo("MultiInputPolicy", env, seed=args.seed, learning_starts=1000, verbose=0, **her)
    t0 = time.perf_counter()
    model.learn(total_timesteps=args.steps, callback=_Progress(args.steps, t0, sb3))
    train_s = time.perf_counter() - t0

    def sb3_act(obs):
        return model.predict(obs, deterministic=True)[0]

    ours_policy = load_policy()
    rows = {
        f"SB3 {args.algo.upper()}{'' if args.no_her else ' + HER'}": judge(sb3_act, args.testset),
        "regrasp_mjx default (shipped)": judge(lambda obs: ours_policy.act(obs["observation"]), args.testset),
    }
    data = {
        "machine": machine(),
        "versions": {"stable_baselines3": sb3.__version__, "torch": torch.__version__},
        "args": vars(args),
        "train_wall_s": round(train_s, 1),
        "env_steps_per_s": round(args.steps / train_s, 1),
        "rows": rows,
    }
    lines = [
        f"{args.testset}, bare (no shield), each problem's first end; SB3 trained {args.steps:,} env steps "
        f"(seed {args.seed}) in {train_s:.0f} s on {machine(devices=False)}",
        "",
        "| learner | success | collision | time-out |",
        "| --- | ---: | ---: | ---: |",
        *(f"| {k} | {v['success']:.3f} | {v['collision']:.3f} | {v['time_out']:.3f} |" for k, v in rows.items()),
    ]
    write_results(args.out, f"{args.algo}{'' if args.no_her else '_her'}_seed{args.seed}", lines, data)
    print("\n".join(lines))
    print(json.dumps({"train_wall_s": data["train_wall_s"], **{k: v["success"] for k, v in rows.items()}}))


if __name__ == "__main__":
    main()
