"""Exported policies: plain arrays (``policy.npz``) plus a JSON contract (``policy.json``).

The npz holds the actor's parameters under their flax paths (``actor/params/hidden_0/kernel``) and
the observation normaliser (``normalizer/mean``, ``normalizer/std``); the JSON holds what a robot
integrator needs: the network (hidden sizes, activation, tanh output), the observation and action
layouts with units and frames, the action scales, the versions. No pickle anywhere: a policy file
is loaded with ``allow_pickle=False`` and checked against its contract.
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
from brax.training.acme import running_statistics
from flax import traverse_util

from regrasp_mjx.agents.ddpg_bc.networks import make_networks
from regrasp_mjx.planning.episodes import _atomic_write

POLICY_FORMAT = "regrasp_mjx.policy"
POLICY_VERSION = 1
OBS_LAYOUT = [
    "p_eg_n (3, m)",
    "q_eg_n (4, wxyz, w>=0)",
    "p_eg_er (3, m)",
    "q_eg_er (4, wxyz, w>=0)",
    "p_er_n (3, m)",
    "q_er_n (4, wxyz, w>=0)",
]
ACTION_LAYOUT = [
    "dp_x, dp_y, dp_z in the e_g frame, times max_dp_mm",
    "rotation vector x, y, z in the e_g frame, times max_drot_deg, applied as q_t = exp(w) q_{t-1}",
]


class PolicyError(ValueError):
    """A policy file that is missing, corrupt, or from an incompatible version."""


def save_policy(
    out_dir: str | os.PathLike,
    actor_params: Any,
    normalizer: Any,
    hidden: tuple[int, ...],
    env_config: Any,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Writes ``policy.npz`` and ``policy.json`` into ``out_dir`` atomically."""
    out = Path(out_dir)
    flat = {
        "actor/" + "/".join(k): np.asarray(v, np.float32)
        for k, v in traverse_util.flatten_dict(jax.device_get(actor_params)).items()
    }
    flat["normalizer/mean"] = np.asarray(normalizer.mean, np.float32)
    flat["normalizer/std"] = np.asarray(normalizer.std, np.float32)
    from regrasp_mjx.testset import versions

    contract = {
        "format": POLICY_FORMAT,
        "version": POLICY_VERSION,
        "network": {"hidden": list(hidden), "activation": "relu", "output": "tanh", "obs_clip_std": 5.0},
        "observation": {
            "size": 21,
            "layout": OBS_LAYOUT,
            "frames": "e_g: grasping end-effector; er: regrasping; n: needle",
        },
        "action": {
            "size": 6,
            "range": [-1.0, 1.0],
            "layout": ACTION_LAYOUT,
            "max_dp_mm": env_config.max_dp_mm,
            "max_drot_deg": env_config.max_drot_deg,
        },
        "env": dataclasses.asdict(env_config),
        "arrays": sorted(flat),
        "versions": versions(),
        **(extra or {}),
    }
    _atomic_write(out / "policy.npz", lambda f: np.savez(f, **flat))
    _atomic_write(out / "policy.json", lambda f: f.write(json.dumps(contract, indent=2).encode()))
    return out


@dataclasses.dataclass(frozen=True)
class Policy:
    """A loaded policy: ``act(obs[..., 21]) -> action[..., 6]`` (jitted, deterministic)."""

    contract: dict[str, Any]
    actor_params: Any
    normalizer: Any

    def __post_init__(self) -> None:
        nets = make_networks(6, tuple(self.contract["network"]["hidden"]))
        object.__setattr__(self, "_act", jax.jit(lambda obs: nets.policy(self.actor_params, self.normalizer, obs)))

    def act(self, obs: Any) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.shape[-1:] != (21,):
            raise ValueError(f"observation has shape {obs.shape}; accepted: (..., 21)")
        if not np.all(np.isfinite(obs)):
            raise ValueError("observation has NaN or inf; accepted: finite values")
        return np.asarray(self._act(jnp.asarray(obs)))


def load_policy(path: str | os.PathLike) -> Policy:
    """Reads a policy folder (or its ``policy.json``/``policy.npz``) and checks it against its contract."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    js, npz = folder / "policy.json", folder / "policy.npz"
    for f in (js, npz):
        if not f.is_file():
            raise PolicyError(f"policy file not found: {f}")
    try:
        contract = json.loads(js.read_text())
    except json.JSONDecodeError as err:
        raise PolicyError(f"{js} is not valid JSON: {err}") from err
    if contract.get("format") != POLICY_FORMAT or contract.get("version") != POLICY_VERSION:
        raise PolicyError(
            f"{js}: format {contract.get('format')!r} version {contract.get('version')!r}; "
            f"this package reads {POLICY_FORMAT!r} version {POLICY_VERSION}"
        )
    try:
        with np.load(npz, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as err:
        raise PolicyError(f"{npz} is not a readable policy array file: {err}") from err
    missing = sorted(set(contract.get("arrays", [])) - set(arrays))
    if missing or "normalizer/mean" not in arrays:
        raise PolicyError(f"{npz} lacks arrays {missing or ['normalizer/mean']}")
    hidden = contract["network"]["hidden"]
    expected = make_networks(6, tuple(hidden)).actor.init(jax.random.PRNGKey(0), jnp.zeros((1, 21)))
    params = {}
    for k, v in traverse_util.flatten_dict(expected).items():
        name = "actor/" + "/".join(k)
        if name not in arrays or arrays[name].shape != v.shape:
            raise PolicyError(
                f"{npz}: {name} has shape {arrays.get(name, np.zeros(0)).shape}, the contract's "
                f"network (hidden {hidden}) needs {v.shape}"
            )
        params[k] = jnp.asarray(arrays[name])
    norm = running_statistics.RunningStatisticsState(
        count=jnp.ones(()),
        mean=jnp.asarray(arrays["normalizer/mean"]),
        summed_variance=jnp.zeros(21),
        std=jnp.asarray(arrays["normalizer/std"]),
    )
    return Policy(contract, traverse_util.unflatten_dict(params), norm)
