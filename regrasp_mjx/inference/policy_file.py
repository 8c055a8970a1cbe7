"""Policy files: plain arrays (``policy.npz``) plus a JSON contract (``policy.json``), and the shipped ones.

The npz holds the actor's parameters under their flax paths (``actor/params/hidden_0/kernel``) and
the observation normaliser (``normalizer/mean``, ``normalizer/std``), each with a leading member
axis of size ``network.ensemble`` (1 for one network; K for the mean-action ensemble of K
independently trained actors, ours). The JSON holds what a robot integrator needs: the network
(hidden sizes, activation, tanh output, ensemble size), the observation and action layouts with
units and frames, the action scales, the environment, the versions. No pickle anywhere: a policy
file is loaded with ``allow_pickle=False`` and checked against its contract.
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
from regrasp_mjx.core.atomic import atomic_write, write_json
from regrasp_mjx.core.config_text import env_config_from_dict
from regrasp_mjx.core.geometry import OBS_SIZE, OBS_SIZE_GENERAL
from regrasp_mjx.world.testsets import versions

POLICY_FORMAT = "regrasp_mjx.policy"
POLICY_VERSION = 2
SHIPPED = Path(__file__).resolve().parents[1] / "policies"
DEFAULT_POLICY = SHIPPED / "default"
OBS_LAYOUT = [
    "p_eg_n (3, m)",
    "q_eg_n (4, wxyz, w>=0)",
    "p_eg_er (3, m)",
    "q_eg_er (4, wxyz, w>=0)",
    "p_er_n (3, m)",
    "q_er_n (4, wxyz, w>=0)",
]
# what a general task's policy (37 inputs) observes after the 21 (geometry.task_observation)
TASK_OBS_LAYOUT = [
    "p_er*_n (3, m): the needle in the goal end-effector frame",
    "q_er*_n (4, wxyz, w>=0)",
    "p_er_er* (3, m): the goal end-effector in the current one",
    "q_er_er* (4, wxyz, w>=0)",
    "needle radius R (1, m)",
    "wire radius (1, m)",
]


def obs_size(env_config: Any) -> int:
    """Observation width of a policy trained in ``env_config``: 21, or 37 for a general task."""

    return OBS_SIZE_GENERAL if env_config.task.general else OBS_SIZE


ACTION_LAYOUT = [
    "dp_x, dp_y, dp_z in the e_g frame, times max_dp_mm",
    "rotation vector x, y, z in the e_g frame, times max_drot_deg, applied as q_t = exp(w) q_{t-1}",
]

WEIGHT_DTYPES = ("float32", "float16")


class PolicyError(ValueError):
    """A policy file that is missing, corrupt, or from an incompatible version."""


def save_policy(
    out_dir: str | os.PathLike,
    actor_params: Any,
    normalizer: Any,
    hidden: tuple[int, ...],
    env_config: Any,
    extra: dict[str, Any] | None = None,
    ensemble: int | None = None,
    weights_dtype: str = "float32",
) -> Path:
    """Writes ``policy.npz`` and ``policy.json`` into ``out_dir`` atomically.

    ``actor_params`` and ``normalizer`` are one learner's, or, with ``ensemble=K``, K learners'
    stacked on a leading axis. ``weights_dtype="float16"`` stores the actor's weights at half the
    size (they are computed in float32 after loading); the normaliser stays float32."""
    if weights_dtype not in WEIGHT_DTYPES:
        raise PolicyError(f"weights_dtype={weights_dtype!r} is not accepted: one of {WEIGHT_DTYPES}")
    out = Path(out_dir)
    lead = (lambda x: np.asarray(x, np.float32)) if ensemble else (lambda x: np.asarray(x, np.float32)[None])
    flat = {
        "actor/" + "/".join(k): lead(v).astype(weights_dtype)
        for k, v in traverse_util.flatten_dict(jax.device_get(actor_params)).items()
    }
    flat["normalizer/mean"] = lead(normalizer.mean)
    flat["normalizer/std"] = lead(normalizer.std)

    contract = {
        "format": POLICY_FORMAT,
        "version": POLICY_VERSION,
        "network": {
            "hidden": list(hidden),
            "activation": "relu",
            "output": "tanh",
            "obs_clip_std": 5.0,
            "ensemble": int(ensemble or 1),
            "weights_dtype": weights_dtype,
            "combine": "mean of the members' actions",
        },
        "observation": {
            "size": obs_size(env_config),
            "layout": OBS_LAYOUT + (TASK_OBS_LAYOUT if env_config.task.general else []),
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
    atomic_write(out / "policy.npz", lambda f: np.savez(f, **flat))
    write_json(out / "policy.json", contract)
    return out


def untrained_policy(
    out_dir: str | os.PathLike,
    hidden: tuple[int, ...],
    env_config: Any,
    seed: int = 0,
    note: str = "",
    closed_loop: dict[str, Any] | None = None,
) -> Path:
    """Writes an untrained network of ``hidden`` layers for ``env_config``'s task as
    :func:`save_policy` writes a trained one: the same arrays, shapes and contract, so every program
    that runs it is the program a trained policy of that shape runs (its weights are arguments,
    never constants). What it is for: compiling those programs before any policy is trained
    (``python -m regrasp_mjx.recipe`` fills the compilation cache with one while its teachers train);
    its actions mean nothing. Numpy only: writing it starts no JAX backend, so a process that must
    leave the GPU to its jobs can. ``closed_loop``: its file's closed-loop settings (the warm-up and
    look frames are constants of the closed loop's programs)."""
    rng = np.random.default_rng(seed)
    sizes = (obs_size(env_config), *(int(h) for h in hidden), 6)
    params = {
        "params": {
            f"hidden_{i}": {
                "bias": np.zeros(b, np.float32),
                "kernel": (rng.standard_normal((a, b)) / np.sqrt(a)).astype(np.float32),
            }
            for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True))
        }
    }
    normalizer = running_statistics.RunningStatisticsState(
        count=np.zeros((), np.float32),
        mean=np.zeros(sizes[0], np.float32),
        summed_variance=np.zeros(sizes[0], np.float32),
        std=np.ones(sizes[0], np.float32),
    )
    training = {"untrained": True, "seed": seed, "note": note or "untrained: its actions mean nothing"}
    extra = {"training": training} | ({"closed_loop": dict(closed_loop)} if closed_loop else {})
    return save_policy(out_dir, params, normalizer, tuple(hidden), env_config, extra=extra)


# a closed loop's settings where a policy file names none (regrasp_mjx.inference.closed_loop_host.execute)
DEFAULT_STOP, DEFAULT_WARMUP, DEFAULT_LOOK, DEFAULT_JAW_SIGMAS = 0.7, 10, 0, 2.0
# the margin in the view's errors where the jaws open on the way (env.jaw_open_deg): none beyond the
# environment's own jaw_open_margin_mm. Chosen on validation problems (seed 7000017) for the teacher
# trained so (experiments/results/jaw_on_the_way/open40_validation.json: 0 sd scored above 0.25 and
# 0.5 sd); at 2 sd the jaws of the jaws40 recipe's student opened in 0.2 % of the episodes at 1 mm of
# tool noise (experiments/results/jaw_on_the_way/recipe_jaws40/)
ON_THE_WAY_JAW_SIGMAS = 0.0


def closed_loop_settings(contract: dict[str, Any]) -> dict[str, Any]:
    """A policy's closed-loop settings: ``stop_tolerance``, ``warmup_frames``, ``look_frames``,
    ``jaw_deg`` and ``jaw_sigmas`` from its file's ``closed_loop`` entry (chosen for it on
    validation problems), else :data:`DEFAULT_STOP`, :data:`DEFAULT_WARMUP`, :data:`DEFAULT_LOOK` (no
    looking), None (the jaws kept at the scene's opening) and :data:`DEFAULT_JAW_SIGMAS`
    (:data:`ON_THE_WAY_JAW_SIGMAS` for a policy whose jaws open on the way)."""
    given = contract.get("closed_loop") or {}
    on_the_way = (contract.get("env") or {}).get("jaw_open_deg") is not None
    return {
        "stop_tolerance": float(given.get("stop_tolerance", DEFAULT_STOP)),
        "warmup_frames": int(given.get("warmup_frames", DEFAULT_WARMUP)),
        "look_frames": int(given.get("look_frames", DEFAULT_LOOK)),
        "jaw_deg": None if given.get("jaw_deg") is None else float(given["jaw_deg"]),
        "jaw_sigmas": float(given.get("jaw_sigmas", ON_THE_WAY_JAW_SIGMAS if on_the_way else DEFAULT_JAW_SIGMAS)),
    }


def shipped_policies() -> list[str]:
    """Names of the policies shipped in the package (``default``: one network; ``student_v1``: the
    earlier default, distilled before the conservative needle model; ``ensemble3``: the earlier
    three-network ensemble)."""
    return sorted(p.name for p in SHIPPED.iterdir() if (p / "policy.json").is_file())


def resolve(path: str | os.PathLike | None) -> Path:
    """The folder of a policy: the shipped default for None, a shipped policy for a bare name that
    is no existing path, else ``path`` (a folder, or a file in it)."""
    if path is None:
        return DEFAULT_POLICY
    if not isinstance(path, (str, os.PathLike)):
        raise PolicyError(
            f"policy {path!r} is not accepted: a folder path, its policy.json or policy.npz, or a shipped name "
            f"({', '.join(shipped_policies())})"
        )
    if isinstance(path, str) and path in shipped_policies() and not Path(path).exists():
        return SHIPPED / path
    path = Path(path)
    # a policy.json or policy.npz names its folder; anything else is taken as the folder itself
    return path.parent if path.name in ("policy.json", "policy.npz") else path


def read_policy(path: str | os.PathLike | None = None) -> tuple[dict[str, Any], Any, Any]:
    """``(contract, actor_params, normaliser)`` of a policy (a folder, its ``policy.json`` or
    ``policy.npz``, a shipped name, or None for the default), checked against the contract; a
    :class:`PolicyError` says what is wrong."""
    folder = resolve(path)
    js, npz = folder / "policy.json", folder / "policy.npz"
    if not folder.is_dir():
        given = str(path)
        named = os.sep not in given and "." not in given  # a bare word: meant as a shipped name
        what = f"no shipped policy is named {given!r}" if named else f"policy folder not found: {given}"
        raise PolicyError(f"{what}; accepted: a shipped name ({', '.join(shipped_policies())}) or a policy folder")
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
    try:
        hidden = tuple(int(h) for h in contract["network"]["hidden"])
        members = int(contract["network"].get("ensemble", 1))
        width = obs_size(env_config_from_dict(contract["env"]))
    except (KeyError, TypeError, ValueError) as err:
        raise PolicyError(f"{js}: incomplete contract ({err})") from err
    missing = sorted((set(contract.get("arrays", [])) | {"normalizer/mean", "normalizer/std"}) - set(arrays))
    if missing:
        raise PolicyError(f"{npz} lacks arrays {missing}")
    broken = sorted(k for k, v in arrays.items() if v.dtype.kind == "f" and not np.all(np.isfinite(v)))
    if broken:  # a diverged or damaged network would plan (and fail) without a word
        raise PolicyError(f"{npz}: arrays {broken} hold NaN or inf; accepted: finite weights")
    expected = make_networks(6, hidden).actor.init(jax.random.PRNGKey(0), jnp.zeros((1, width)))
    params = {}
    for k, v in traverse_util.flatten_dict(expected).items():
        name = "actor/" + "/".join(k)
        want = (members, *v.shape)
        if name not in arrays or arrays[name].shape != want:
            raise PolicyError(
                f"{npz}: {name} has shape {arrays.get(name, np.zeros(0)).shape}, the contract's "
                f"network (hidden {list(hidden)}, ensemble {members}) needs {want}"
            )
        params[k] = jnp.asarray(arrays[name], jnp.float32)  # stored float32 or float16
    for name in ("normalizer/mean", "normalizer/std"):
        if arrays[name].shape != (members, width):
            raise PolicyError(f"{npz}: {name} has shape {arrays[name].shape}, needs {(members, width)}")
        if not np.all(np.isfinite(arrays[name])) or (name.endswith("std") and np.any(arrays[name] <= 0)):
            raise PolicyError(f"{npz}: {name} has non-finite or non-positive values")
    norm = running_statistics.RunningStatisticsState(
        count=jnp.ones((members,)),
        mean=jnp.asarray(arrays["normalizer/mean"]),
        summed_variance=jnp.zeros((members, width)),
        std=jnp.asarray(arrays["normalizer/std"]),
    )
    return contract, traverse_util.unflatten_dict(params), norm
