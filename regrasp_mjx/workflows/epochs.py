"""One training epoch's host-side state and its log rows, for :class:`regrasp_mjx.workflows.trainer.Run`:
what the epochs of a run carry (:class:`Loop`), what one epoch accumulates over its iterations
(:class:`EpochAcc`), and the rows it writes to ``log.jsonl`` (:func:`epoch_rows`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from regrasp_mjx.agents.ddpg_bc import checkpoint
from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.agents.ddpg_bc.exchange import PlannerExchange
from regrasp_mjx.agents.ddpg_bc.learner import TrainingState
from regrasp_mjx.core.host_loop import BestOf, RunLog


@dataclasses.dataclass
class EpochAcc:
    """One epoch's host-side accumulators: each finished iteration's metrics and outcomes, and the
    iteration whose host work is left (it runs while the next is on the device)."""

    metrics: list[dict[str, np.ndarray]] = dataclasses.field(default_factory=list)
    outcomes: list[Any] = dataclasses.field(default_factory=list)
    pending: tuple[Any, Any, Any, np.ndarray] | None = None  # (outcome, metrics, problems, E_T)


@dataclasses.dataclass
class Loop:
    """What the epochs of one :meth:`Run.train` call share and carry from one epoch to the next."""

    ts: TrainingState
    meta: dict[str, Any]  # the checkpoint's metadata: epoch, iteration, planner counts, best, rng state
    best: BestOf
    rng: np.random.Generator
    explos: list[Any]  # each member's exploration schedule
    exchange: PlannerExchange | None
    log: RunLog
    test: Any
    val: Any
    t_start: float
    compile_s: float | None = None
    epochs_run: int = 0  # by this process (a resumed run counts from its resume)
    last: list[dict[str, Any]] = dataclasses.field(default_factory=list)  # the last epoch's rows
    writer: checkpoint.Writer = dataclasses.field(default_factory=checkpoint.Writer)


def epoch_rows(
    cfg: TrainConfig,
    meta: dict[str, Any],
    acc: EpochAcc,
    evs: list[dict[str, Any]],
    vas: list[dict[str, Any]],
    explos: list[Any],
    per_s: float,
    seconds: dict[str, float],
    timing: dict[str, float],
) -> list[dict[str, Any]]:
    """The log rows of the epoch that ``meta`` has just counted, one per member (log.jsonl's keys,
    in its order): ``evs``/``vas`` its test and validation summaries, ``per_s`` its iterations per
    second, ``seconds`` its ``epoch_s``, ``eval_s`` and ``wall_s``, ``timing`` its seconds per phase."""
    seeds, steps_per_iter = cfg.num_members, cfg.num_members * cfg.num_envs * cfg.env.horizon
    mean = {k: np.mean([x[k] for x in acc.metrics], axis=0) for k in acc.metrics[0]}  # [seed]
    out = jax.tree.map(lambda *x: np.concatenate(x, axis=1), *acc.outcomes)
    e_r, e_t = np.array([x.at(meta["iteration"]) for x in explos]).T
    return [
        {
            "run_id": meta["run_id"],
            "epoch": meta["epoch"],
            "setting": cfg.member_setting(m)[0] or None,
            "seed": cfg.member_seed(m),
            "iteration": meta["iteration"],
            "rollout": "bare",  # test and validation: the network alone, no shield
            "test": evs[m],
            "validation": vas[m],
            "train_success": float(out.success[m].mean()),
            "train_collision": float(out.collision[m].mean()),
            "return": float(mean["rollout_reward"][m]),
            "critic_loss": float(mean["critic_loss"][m]),
            "actor_loss": float(mean["actor_loss"][m]),
            "bc_loss": float(mean["bc_loss"][m]),
            "q": float(mean["q"][m]),
            "q_filter_kept": float(mean["q_filter_kept"][m]),
            "E_R": float(e_r[m]),
            "E_T": float(e_t[m]),
            "demos_received": meta["demos_received"][m],
            "planned": meta["planned"][m],
            "env_steps_per_s": steps_per_iter * per_s,  # all seeds together
            "updates_per_s": seeds * cfg.updates_per_iteration * per_s,
            "epoch_s": seconds["epoch_s"],
            "eval_s": seconds["eval_s"],
            "wall_s": seconds["wall_s"],
            "timing": timing,  # the whole run's, the same in every member's row
        }
        for m in range(seeds)
    ]
