"""The planner exchange of mixed exploration: failed episodes out to BIT* (reverse), demonstrations in.

Between iterations the host sends each seed's chosen failed episodes (probability E_T) to a pool of
planner processes, never waiting for them; paths that come back are replayed in the environment and
collected per seed until they fill a ``demo_chunk``, which goes into that seed's online buffer in a
later iteration. In a distributed run the pool is process 0's and the chunks it inserts are
broadcast, so every process inserts the same ones.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import numpy as np

from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.agents.ddpg_bc.learner import TRANSITION, Learner, TrainingState
from regrasp_mjx.core import distributed
from regrasp_mjx.planning.episodes import make_replay, replay_paths
from regrasp_mjx.planning.ompl_planner import PlannerConfig
from regrasp_mjx.planning.pool import PlannerPool
from regrasp_mjx.world.sampling import Episode

Chunk = tuple[int, dict[str, np.ndarray]]  # (member, one demo_chunk of transitions)


def _to_episode(problems: Any, rows: np.ndarray) -> Episode:
    take = lambda x: np.asarray(x)[rows]  # noqa: E731
    n = len(rows)
    return Episode(
        needle_pos=take(problems.needle_pos),
        needle_quat=take(problems.needle_quat),
        start_pos=take(problems.ee_pos),
        start_quat=take(problems.ee_quat),
        goal_pos=take(problems.goal_pos),
        goal_quat=take(problems.goal_quat),
        grasp=np.zeros((n, 4)),
        goal_depth=np.zeros(n),
        needle_radius=take(problems.needle_radius),
        wire_radius=take(problems.wire_radius),
    )


class PlannerExchange:
    """One run's planner pool (process 0's) and the demonstrations waiting per member."""

    def __init__(self, cfg: TrainConfig, learner: Learner):
        self.cfg, self.learner = cfg, learner
        self.pool = self._pool() if distributed.is_main() else None
        self.pending: list[dict[str, list[np.ndarray]]] = [{k: [] for k in TRANSITION} for _ in range(cfg.num_members)]
        self.replay = None

    def _pool(self):
        cfg = self.cfg
        planner = PlannerConfig(planner="BITstar", direction="reverse", budget_s=cfg.planner_budget_s)
        options = {"planner": dataclasses.asdict(planner), "scene": dataclasses.asdict(cfg.env.scene), "seed": cfg.seed}
        workers = cfg.planner_workers or max(1, (os.cpu_count() or 2) - 1)
        return PlannerPool(
            workers, options=options, queue_size=cfg.planner_queue, timeout_s=3 * cfg.planner_budget_s + 30
        )

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()

    def after_iteration(
        self, ts: TrainingState, success: np.ndarray, problems: Any, e_t: np.ndarray, rng: np.random.Generator, meta
    ) -> TrainingState:
        """One iteration's exchange: each member's failed episodes (``success`` ``[member, env]``) are
        chosen with probability ``e_t[member]`` and sent, and the demonstrations ready are inserted.
        Every process draws the same choices from the same generator."""
        chosen = []
        for m in range(len(success)):
            failed = np.flatnonzero(~success[m])
            chosen.append(failed[rng.random(len(failed)) < e_t[m]])
        if any(len(rows) for rows in chosen):
            self.submit(distributed.to_host(problems), chosen, meta)  # to_host: a collective, every process
        return self.receive(ts, meta)

    def submit(self, problems: Any, chosen: list[np.ndarray], meta: dict[str, Any]) -> None:
        """Sends the chosen failed episodes of every seed (``problems`` on the host) to the pool,
        taking the seeds in turn so that a full queue is shared fairly; stops at a full queue (the
        learner never waits). Counts them in ``meta['planned']``."""
        if self.pool is None or not any(len(rows) for rows in chosen):
            return
        episodes = [_to_episode(jax.tree.map(lambda x, m=m: x[m], problems), rows) for m, rows in enumerate(chosen)]
        for j in range(max(len(rows) for rows in chosen)):
            for m, ep in enumerate(episodes):
                if j >= len(chosen[m]):
                    continue
                job = self.pool.submit(ep.problem(j), payload=(m, jax.tree.map(lambda x, j=j: x[j], ep)))
                if job is None:
                    return
                meta["planned"][m] += 1

    def receive(self, ts: TrainingState, meta: dict[str, Any]) -> TrainingState:
        """Inserts the demonstrations that fill a ``demo_chunk`` into their seed's online buffer
        (every process calls it; the chunks are process 0's)."""
        chunks = self._ready_chunks(meta) if self.pool is not None else []
        if distributed.multi_process():
            chunks = self.broadcast_chunks(chunks)
        for m, data in chunks:
            ts = self.learner.add_online(ts, np.int32(m), data)
        return ts

    def _ready_chunks(self, meta: dict[str, Any]) -> list[Chunk]:
        done = [r for r in self.pool.collect() if r.ok and r.result["solved"]]
        if done:
            if self.replay is None:
                self.replay = make_replay(self.learner.env)
            eps = jax.tree.map(lambda *x: np.stack(x), *[r.payload[1] for r in done])
            ok, rows = replay_paths(self.learner.env, self.replay, eps, [r.result["poses"] for r in done], batch=64)
            for r, good, row in zip(done, ok, rows):
                if good:
                    m = r.payload[0]
                    meta["demos_received"][m] += 1
                    for k in ("obs", "action", "reward", "next_obs"):
                        self.pending[m][k].append(row[k])
                    self.pending[m]["terminal"].append(row["done"])
        chunk, chunks = self.cfg.demo_chunk, []
        for m, waiting in enumerate(self.pending):
            while sum(len(x) for x in waiting["obs"]) >= chunk:
                cat = {k: np.concatenate(v) for k, v in waiting.items()}
                chunks.append((m, {k: np.asarray(v[:chunk], np.float32) for k, v in cat.items()}))
                for k in waiting:
                    waiting[k] = [cat[k][chunk:]] if len(cat[k]) > chunk else []
        return chunks

    def broadcast_chunks(self, chunks: list[Chunk]) -> list[Chunk]:
        """Process 0's ``chunks`` on every process: their count first, then the stacked arrays."""
        n = int(distributed.broadcast(np.int32(len(chunks))))
        if n == 0:
            return []
        size, env = self.cfg.demo_chunk, self.learner.env
        obs, act = env.observation_size, env.action_size
        shapes = {"obs": (obs,), "action": (act,), "reward": (), "next_obs": (obs,), "terminal": ()}
        if chunks:
            stacked = {k: np.stack([c[1][k] for c in chunks]) for k in TRANSITION}
            members = np.array([c[0] for c in chunks], np.int32)
        else:
            stacked = {k: np.zeros((n, size, *shapes[k]), np.float32) for k in TRANSITION}
            members = np.zeros(n, np.int32)
        members, stacked = distributed.broadcast((members, stacked))
        return [(int(members[i]), {k: v[i] for k, v in stacked.items()}) for i in range(n)]
