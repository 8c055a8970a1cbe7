"""Planned paths become episodes: actions within the bounds, replayed in the environment.

A path (poses from start to goal, e_g frame) is cut into steps that respect the action bounds and
turned into actions; the actions are replayed in :class:`~regrasp_mjx.envs.env.RegraspEnv` (batched,
jitted) and only episodes that succeed there are kept (SPEC "Planners"). The environment's own
observations and rewards are stored, so a demonstration is exactly what the learner would have
seen.

A demonstration set on disk (``demos.npz`` + ``meta.json``, written by ``python -m
regrasp_mjx.demos``) is plain arrays of flat transitions, ``S`` steps over ``D`` episodes:

==================  ========  ==============================================================
key                 shape     meaning
==================  ========  ==============================================================
obs                 (S, O)    observation before the step (O = 21; 37 for a general task)
action              (S, 6)    action in [-1, 1]
reward              (S,)      reward of the step
done                (S,)      1.0 on the episode's last step (success), else 0.0
next_obs            (S, O)    observation after the step
episode             (S,)      episode number 0..D-1 of the step
problem_index       (D,)      the problem's index (its PRNG key is fold_in(PRNGKey(seed), i))
length              (D,)      steps of each episode
path_length_mm      (D,)      sum of |dp| of each episode
plan_time_s         (D,)      the planner's time
==================  ========  ==============================================================
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.atomic import atomic_write, dumps
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.host import quat_conj, quat_mul, quat_to_rotvec
from regrasp_mjx.envs.rollout import Rollout, rollout
from regrasp_mjx.world import continuous
from regrasp_mjx.world.sampling import Episode

DEMOS_FORMAT = "regrasp_mjx.demos"
DEMOS_VERSION = 1
TRANSITION_KEYS = {"obs": ("O",), "action": (6,), "reward": (), "done": (), "next_obs": ("O",), "episode": ()}
OBS_SIZES = (21, 37)  # the paper's task, a general one (geometry.OBS_SIZE, OBS_SIZE_GENERAL)
EPISODE_KEYS = {"problem_index": (), "length": (), "path_length_mm": (), "plan_time_s": ()}


def path_to_actions(poses: np.ndarray, max_dp: float, max_drot: float) -> np.ndarray:
    """Cuts a path into steps within the action bounds; returns actions (K, 6) in [-1, 1].

    Each segment from pose a to pose b is split into ``n`` equal steps, ``n`` the smallest count
    for which every axis of the translation step is at most ``max_dp`` and every axis of the
    rotation-vector step at most ``max_drot``. The environment composes ``exp(w) q`` per step, so
    n steps of ``log(q_b q_a^-1) / n`` end exactly at ``q_b``: the same geodesic OMPL interpolates
    and checked.
    """
    poses = np.asarray(poses, np.float64)
    actions = []
    for a, b in zip(poses[:-1], poses[1:]):
        dp = b[:3] - a[:3]
        rotvec = quat_to_rotvec(quat_mul(b[3:], quat_conj(a[3:])))
        n = continuous.pieces(dp, rotvec, max_dp, max_drot)
        step = np.concatenate([dp / n / max_dp, rotvec / n / max_drot])
        actions.extend([step] * n)
    return np.clip(np.array(actions, np.float32).reshape(-1, 6), -1.0, 1.0)


def make_replay(env: RegraspEnv):
    """A jitted ``replay(episodes, actions[B, H, 6]) -> Rollout`` over a batch, H = the horizon:
    the actions stepped open loop from the episodes' starts. Its ``trace`` holds per step ``obs``,
    ``next_obs``, ``reward`` and ``done`` (``[H, B, ...]``); see :func:`replayed` for which
    replays are demonstrations."""

    def replay(episodes: Episode, actions: jax.Array) -> Rollout:
        def keep(state, a, nxt):
            return {"obs": state.obs, "next_obs": nxt.obs, "reward": nxt.reward, "done": nxt.done}

        return rollout(env, lambda state, t: actions[:, t], jax.vmap(env.reset_from)(episodes), trace=keep)

    return jax.jit(replay)


def replayed(out: Rollout, lengths: np.ndarray) -> np.ndarray:
    """Which replays of paths of ``lengths`` actions are demonstrations: those that succeed at or
    before their last action (the goal tolerance is often met a step or two before the path's last
    pose; the episode then ends there, after ``out.steps`` actions). Past its end a path's actions
    are zero, which cannot reach the goal the last pose missed."""
    return np.asarray(out.success) & (np.asarray(out.steps) <= np.asarray(lengths))


def replay_paths(
    env: RegraspEnv, replay, episodes: Episode, paths: list[np.ndarray], batch: int = 256
) -> tuple[np.ndarray, list[dict[str, np.ndarray]]]:
    """Replays planned paths (start to goal) in ``env``; returns ``(ok[N], transitions per path)``.

    ``transitions[i]`` holds obs, action, reward, done, next_obs of path i's steps (empty for a
    path that did not succeed or needs more steps than the horizon).
    """
    horizon = env.config.horizon
    actions = [path_to_actions(p, env.max_dp, env.max_drot) for p in paths]
    lengths = np.array([len(a) for a in actions])
    ok = np.zeros(len(paths), bool)
    out_rows: list[dict[str, np.ndarray]] = [{} for _ in paths]
    idx = np.flatnonzero(lengths <= horizon)
    for lo in range(0, len(idx), batch):
        rows = idx[lo : lo + batch]
        padded = np.zeros((batch, horizon, 6), np.float32)
        for j, i in enumerate(rows):
            padded[j, : lengths[i]] = actions[i]
        take = np.concatenate([rows, np.full(batch - len(rows), rows[0])])  # pad the batch: one compile
        eps = jax.tree.map(lambda x, take=take: jnp.asarray(np.asarray(x)[take], jnp.float32), episodes)
        out = jax.device_get(replay(eps, jnp.asarray(padded)))
        good = replayed(out, lengths[take])
        trace = {k: np.swapaxes(v, 0, 1) for k, v in out.trace.items()}  # [batch, H, ...]
        for j, i in enumerate(rows):
            if not good[j]:
                continue
            ok[i] = True
            n = out.steps[j]
            out_rows[i] = {
                "obs": trace["obs"][j, :n],
                "action": padded[j, :n],
                "reward": trace["reward"][j, :n],
                "done": trace["done"][j, :n],
                "next_obs": trace["next_obs"][j, :n],
                "path_length_mm": float(out.path_length_mm[j]),
            }
    return ok, out_rows


# ---- demonstration sets on disk ----------------------------------------------------------------
class DemosError(ValueError):
    """A demonstration set that is missing, unreadable or malformed."""


@dataclasses.dataclass(frozen=True)
class Demos:
    """A loaded demonstration set: flat transitions plus per-episode records (numpy)."""

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    done: np.ndarray
    next_obs: np.ndarray
    episode: np.ndarray
    problem_index: np.ndarray
    length: np.ndarray
    path_length_mm: np.ndarray
    plan_time_s: np.ndarray
    meta: dict[str, Any]

    @property
    def num_episodes(self) -> int:
        return int(self.length.shape[0])


def save_demos(path: str | os.PathLike, episodes: list[dict[str, Any]], meta: dict[str, Any]) -> Path:
    """Writes episodes (dicts from :func:`replay_paths` plus ``problem_index``, ``plan_time_s``)."""
    path = Path(path)
    if not episodes:
        raise DemosError("no demonstrations to write")
    cat = {
        k: np.concatenate([e[k] for e in episodes]).astype(np.float32)
        for k in ("obs", "action", "reward", "done", "next_obs")
    }
    cat["episode"] = np.concatenate([np.full(len(e["action"]), i, np.int32) for i, e in enumerate(episodes)])
    cat["problem_index"] = np.array([e["problem_index"] for e in episodes], np.int64)
    cat["length"] = np.array([len(e["action"]) for e in episodes], np.int32)
    cat["path_length_mm"] = np.array([e["path_length_mm"] for e in episodes], np.float32)
    cat["plan_time_s"] = np.array([e["plan_time_s"] for e in episodes], np.float32)
    meta = {
        "format": DEMOS_FORMAT,
        "version": DEMOS_VERSION,
        "episodes": len(episodes),
        "steps": int(cat["length"].sum()),
        **meta,
    }
    atomic_write(path, lambda f: np.savez_compressed(f, meta=np.array(dumps(meta, sort_keys=True)), **cat))
    return path


def load_demos(path: str | os.PathLike) -> Demos:
    """Reads and validates a demonstration set (a ``demos.npz`` or the folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "demos.npz"
    if not path.is_file():
        raise DemosError(f"demonstration set not found: {path} (make one with `python -m regrasp_mjx.demos`)")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
        meta = json.loads(str(data.pop("meta")))
    except Exception as err:
        raise DemosError(f"{path} is not a readable demonstration set: {err}") from err
    missing = [k for k in (*TRANSITION_KEYS, *EPISODE_KEYS) if k not in data]
    if missing or meta.get("format") != DEMOS_FORMAT:
        raise DemosError(
            f"{path} lacks {missing or 'its format tag'}; a demonstration set holds "
            f"{sorted([*TRANSITION_KEYS, *EPISODE_KEYS, 'meta'])}"
        )
    s, d = data["obs"].shape[0], data["length"].shape[0]
    width = data["obs"].shape[1] if data["obs"].ndim == 2 else -1
    if width not in OBS_SIZES:
        raise DemosError(f"{path}: obs has shape {data['obs'].shape}; accepted: (S, O) with O in {OBS_SIZES}")
    for keys, n in ((TRANSITION_KEYS, s), (EPISODE_KEYS, d)):
        for k, shape in keys.items():
            shape = tuple(width if v == "O" else v for v in shape)
            if data[k].shape != (n, *shape):
                raise DemosError(f"{path}: {k} has shape {data[k].shape}, expected {(n, *shape)}")
    if (
        int(data["length"].sum()) != s
        or not np.all(np.isfinite(data["obs"]))
        or not np.all(np.isfinite(data["action"]))
    ):
        raise DemosError(f"{path}: lengths do not add up to the {s} steps, or values are not finite")
    return Demos(**data, meta=meta)


def check_made_for(demos: Demos, env_config: Any, path: str | os.PathLike) -> Demos:
    """``demos``, refused (:class:`DemosError`) where its file names another scene or task than
    ``env_config``'s (a set that names none, made before they were recorded, is taken as it is)."""
    made = demos.meta.get("settings", {}).get("env", {})
    for part in ("scene", "task"):
        ours = json.loads(dumps(dataclasses.asdict(getattr(env_config, part))))
        theirs = made.get(part) or {}
        differ = sorted(k for k in theirs if k in ours and theirs[k] != ours[k])
        if differ:
            raise DemosError(
                f"{path} was made for another {part} ({', '.join(f'{k}={theirs[k]}' for k in differ)}; this run: "
                f"{', '.join(f'{k}={ours[k]}' for k in differ)}); accepted: demonstrations of this run's {part} "
                f"(python -m regrasp_mjx.demos --env {part}.KEY=VALUE), or none (the run builds its own)"
            )
    return demos
