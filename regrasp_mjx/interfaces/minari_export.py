"""A demonstration set as a Minari dataset (issue 71; Minari is Farama's offline-RL format, d4rl's
successor): what ``python -m regrasp_mjx.export_minari`` writes.

Each demonstration of a set (:func:`regrasp_mjx.planning.episodes.load_demos`) is replayed through the
gymnasium environment, ``gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")`` for the paper's task and
``NeedleRegraspGeneral`` for a general one (with ``config_overrides`` for whatever else the set's
``EnvConfig`` changed), from its own problem (drawn again from the set's seed and the problem's index,
as :func:`regrasp_mjx.planning.demonstrations.problem_sampler` drew it) with its own actions. The
dataset holds what that environment returned, observations (goal dicts), rewards, terminations,
truncations and infos, with the environment's spaces and its spec (``dataset.recover_environment()``
makes it again). A demonstration whose replay does not end in success is left out and named.

Each episode's reset is stored with it (Minari's per-episode ``seed`` and ``options``: the problem
as arrays): ``env.reset(**reset_arguments(dataset, i))`` starts episode ``i`` where it started. The
dataset's metadata (``dataset.storage.metadata["regrasp_mjx"]``) names the demonstration file, its
planner, seed and environment, and the package's version.

Minari is an optional extra (``pip install -e ".[minari]"``): this module imports without it and
:func:`export` says how to install it. The dataset is written in a hidden folder beside its place and
moved there whole, so an interrupted export leaves nothing under its id.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.util
import json
import os
import re
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from tqdm import tqdm

from regrasp_mjx.core.atomic import dumps
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.core.config_text import env_config_from_dict
from regrasp_mjx.interfaces import registry
from regrasp_mjx.interfaces.gym_envs import gym_id
from regrasp_mjx.planning.demonstrations import problem_sampler
from regrasp_mjx.planning.episodes import Demos, DemosError, load_demos
from regrasp_mjx.world.sampling import Episode
from regrasp_mjx.world.testsets import versions

try:
    import minari
    from minari import namespace as minari_namespace
    from minari.data_collector import EpisodeBuffer
except ImportError:  # optional (the minari extra): export() says how to install it
    minari = minari_namespace = EpisodeBuffer = None

INSTALL = 'pip install -e ".[minari]" (minari==0.5.4 with h5py and pillow, what its default HDF5 storage needs)'
ID_FORM = "a Minari dataset id [NAMESPACE/]NAME-vVERSION, e.g. regrasp_mjx/paper-bitstar-v0"
# Minari's own id pattern (minari.dataset.minari_dataset.DATASET_ID_RE) with the version required:
# minari.load_dataset cannot read an id without one
ID_RE = re.compile(r"(?:(?P<namespace>[-_\w][-_\w/]*[-_\w]+)/)?(?P<dataset>[-_\w]+?)-v(?P<version>\d+)")
ENV_NAMES = {False: "NeedleRegrasp", True: "NeedleRegraspGeneral"}  # by TaskConfig.general
CHUNK = 256  # episodes held in memory before they are written
STAGING = ".regrasp_mjx-export-"  # hidden: Minari's listings skip folders starting with a dot


class ExportError(ValueError):
    """A dataset that cannot be written: Minari missing, an id not accepted or already taken."""


def missing_packages() -> list[str]:
    """The packages of the minari extra that are not installed (Minari's HDF5 storage imports h5py and
    PIL when it writes or reads, and its package does not require them)."""
    gone = [] if minari is not None else ["minari"]
    return gone + [
        name for module, name in (("h5py", "h5py"), ("PIL", "pillow")) if importlib.util.find_spec(module) is None
    ]


def datasets_root() -> Path:
    """Where Minari keeps its datasets: ``MINARI_DATASETS_PATH``, else ``~/.minari/datasets`` (Minari's
    rule, without its ``get_dataset_path``'s side effect of creating the folder)."""
    root = os.environ.get("MINARI_DATASETS_PATH")
    return Path(root) if root is not None else Path.home() / ".minari" / "datasets"


def name_problem(name: str, overwrite: bool = False) -> str | None:
    """Why ``name`` cannot be written (None when it can): checked before any work."""
    if not ID_RE.fullmatch(name):
        return f"--name {name!r} is not accepted: {ID_FORM}"
    root = datasets_root()
    if (root / name).exists() and not overwrite:
        return (
            f"--name {name}: a dataset of that id exists ({root / name}); accepted: another id (e.g. a higher -vN) "
            "or --overwrite to replace it"
        )
    parent = next(p for p in (root / name, *(root / name).parents) if p.exists())
    try:  # tried by writing: os.access says yes to root for folders no one can write, such as /proc
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".write_probe", suffix=".tmp")
    except OSError:
        return f"--name {name}: {parent} is not a writable folder; accepted: MINARI_DATASETS_PATH naming one"
    os.close(fd)
    os.unlink(probe)
    return None


@dataclasses.dataclass(frozen=True)
class Source:
    """A demonstration set and what its file says about how it was made."""

    demos: Demos
    path: Path
    seed: int
    planner: dict[str, Any]
    env_config: EnvConfig
    env_name: str  # registry / gymnasium name
    overrides: dict[str, Any]  # config_overrides of gymnasium.make

    @property
    def env_id(self) -> str:
        return gym_id(self.env_name)


def _flat(d: dict, prefix: str) -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def source(path: str | os.PathLike) -> Source:
    """The demonstration set at ``path`` (a ``demos.npz`` or its folder) and its environment."""
    demos = load_demos(path)
    path = Path(path) / "demos.npz" if Path(path).is_dir() else Path(path)
    settings = demos.meta.get("settings") or {}
    if not isinstance(settings.get("seed"), int) or not isinstance(settings.get("env"), dict):
        raise DemosError(
            f"{path} names no seed and environment (its meta's settings.seed and settings.env), so its problems "
            "cannot be drawn again; accepted: a set written by python -m regrasp_mjx.demos"
        )
    config = env_config_from_dict(settings["env"])
    name = ENV_NAMES[config.task.general]
    default = _flat(json.loads(dumps(registry.default_config(name).env.to_dict())), "env.")
    ours = _flat(json.loads(dumps(dataclasses.asdict(config))), "env.")
    overrides = {k: v for k, v in ours.items() if default.get(k) != v}
    return Source(demos, path, settings["seed"], settings.get("planner") or {}, config, name, overrides)


def make_env(src: Source) -> gymnasium.Env:
    """``gymnasium.make`` of the set's environment, refused where its config is not the set's."""
    env = gymnasium.make(src.env_id, config_overrides=src.overrides)
    made = env.unwrapped.registry_env.env_config
    if made != src.env_config:
        raise DemosError(
            f"{src.path}: {src.env_id} with config_overrides {src.overrides} is not the set's environment "
            f"({made} != {src.env_config}); accepted: a set of a registered environment's task"
        )
    return env


def _problem_arrays(problem: Episode) -> dict[str, np.ndarray]:
    return {f.name: np.asarray(v) for f in dataclasses.fields(problem) if (v := getattr(problem, f.name)) is not None}


def reset_arguments(dataset: Any, index: int) -> dict[str, Any]:
    """``env.reset(**reset_arguments(dataset, i))`` starts the dataset's episode ``i`` (of
    ``dataset.episode_indices``) where its recording started: its seed, and its problem as
    ``options={"episode": ...}`` (an :class:`~regrasp_mjx.world.sampling.Episode` of one row)."""
    meta = next(iter(dataset.storage.get_episode_metadata([int(dataset.episode_indices[index])])))
    arrays = {k: np.asarray(v) for k, v in meta["options"]["episode"].items()}
    return {"seed": int(meta["seed"]), "options": {"episode": Episode(**arrays)}}


def _stack(rows: list[dict]) -> dict[str, np.ndarray]:
    return {k: np.stack([np.asarray(r[k]) for r in rows]) for k in rows[0]}


def record(env: gymnasium.Env, problem: Episode, seed: int, actions: np.ndarray):
    """One demonstration replayed in ``env`` from ``problem``: ``(buffer, success, observations)``,
    its Minari episode, whether it ended in success, and the observations it saw ``[T + 1, O]``."""
    obs, info = env.reset(seed=seed, options={"episode": problem})
    observations, infos, rewards, terminated, truncated = [obs], [info], [], [], []
    for action in actions:
        obs, reward, term, trunc, info = env.step(action)
        observations.append(obs)
        infos.append(info)
        rewards.append(reward)
        terminated.append(term)
        truncated.append(trunc)
        if term or trunc:
            break
    buffer = EpisodeBuffer(
        seed=seed,
        options={"episode": _problem_arrays(problem)},
        observations=_stack(observations),
        actions=np.asarray(actions[: len(rewards)], np.float32),
        rewards=np.asarray(rewards, np.float64),
        terminations=np.asarray(terminated, bool),
        truncations=np.asarray(truncated, bool),
        infos=_stack(infos),
    )
    success = bool(terminated and terminated[-1] and info["is_success"])
    return buffer, success, buffer.observations["observation"]


@contextlib.contextmanager
def _minari_root(path: Path):
    """``MINARI_DATASETS_PATH`` set to ``path`` inside: Minari's writers take their folder from it."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _describe(src: Source, planner: str) -> str:
    task = "general" if src.env_config.task.general else "paper"
    return (
        f"Needle-regrasping demonstrations (regrasp_mjx): {planner} plans of the {task} task's problems (seed "
        f"{src.seed}), each replayed through gymnasium.make({src.env_id!r}) from its problem. Observations are "
        "goal dicts (observation, achieved_goal, desired_goal), actions 6 numbers in [-1, 1] (0.5 mm and 3 deg "
        "per unit and axis); the last step of each episode succeeds. "
        "env.reset(**regrasp_mjx.interfaces.minari_export.reset_arguments(dataset, i)) starts episode i's problem."
    )


def _create(stage: Path, name: str, env: gymnasium.Env, buffers: list, src: Source, planner: str):
    """The dataset made under the staging root, with Minari's metadata (its warnings for an author's
    e-mail and a code link, which a package has no use for, silenced)."""
    with _minari_root(stage), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"`(author_email|code_permalink)` is set to None")
        return minari.create_dataset_from_buffers(
            dataset_id=name,
            buffer=buffers,
            env=env,
            eval_env=env.spec,
            algorithm_name=planner,
            author="regrasp_mjx",
            description=_describe(src, planner),
            data_format="hdf5",
            requirements=[f"regrasp_mjx=={versions()['regrasp_mjx']}", f"gymnasium=={gymnasium.__version__}"],
        )


def _move_into_place(staged: Path, target: Path, namespace: str | None) -> None:
    """``staged`` (a finished dataset folder) renamed to ``target``; one there before is replaced."""
    if namespace is not None and namespace not in minari_namespace.list_local_namespaces():
        minari_namespace.create_namespace(namespace)
    target.parent.mkdir(parents=True, exist_ok=True)
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=STAGING + "old-", dir=datasets_root()))
        os.rename(target, old / "dataset")
    os.rename(staged, target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def export(demos: str | os.PathLike, name: str, *, overwrite: bool = False, quiet: bool = False) -> dict[str, Any]:
    """Writes the demonstration set ``demos`` as the Minari dataset ``name`` (under
    :func:`datasets_root`; an existing one replaced only with ``overwrite``); returns a summary."""
    if gone := missing_packages():
        raise ExportError(f"{', '.join(gone)} not installed, which a Minari export needs; accepted: {INSTALL}")
    if problem := name_problem(name, overwrite):
        raise ExportError(problem)
    t0 = time.perf_counter()
    src = source(demos)
    env = make_env(src)
    d = src.demos
    problems = problem_sampler(env.unwrapped.registry_env.env, src.seed)(d.problem_index)
    starts = np.concatenate([[0], np.cumsum(d.length)])
    p = src.planner
    planner = f"{p.get('planner', 'unknown planner')} ({p.get('direction', '?')}, {p.get('budget_s', '?')} s), OMPL"
    root = datasets_root()
    root.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=STAGING, dir=root))
    dataset, left_out, max_difference, metas = None, [], 0.0, []
    try:
        buffers: list = []
        for i in tqdm(range(d.num_episodes), desc="episodes", unit="episode", disable=quiet, file=sys.stdout):
            lo, hi = starts[i], starts[i + 1]
            buffer, success, seen = record(env, problems.row(slice(i, i + 1)), int(d.problem_index[i]), d.action[lo:hi])
            if not success:
                left_out.append(int(d.problem_index[i]))
            else:
                expected = np.concatenate([d.obs[lo:hi], d.next_obs[hi - 1 : hi]])
                n = min(len(seen), len(expected))
                max_difference = max(max_difference, float(np.abs(seen[:n] - expected[:n]).max()))
                buffers.append(buffer)
                metas.append(
                    {
                        "problem_index": int(d.problem_index[i]),
                        "plan_time_s": float(d.plan_time_s[i]),
                        "path_length_mm": float(d.path_length_mm[i]),
                    }
                )
            if buffers and (len(buffers) == CHUNK or i == d.num_episodes - 1):
                if dataset is None:
                    dataset = _create(stage, name, env, buffers, src, planner)
                else:
                    dataset.update_dataset_from_buffer(buffers)
                buffers = []
        if dataset is None:
            raise DemosError(
                f"{src.path}: none of its {d.num_episodes} demonstrations ends in success when replayed in "
                f"{src.env_id}; accepted: a set made for this package's environment (python -m regrasp_mjx.demos)"
            )
        dataset.storage.update_episode_metadata(metas, range(len(metas)))
        summary = {
            "dataset_id": name,
            "path": str(root / name),
            "env_id": src.env_id,
            "config_overrides": src.overrides,
            "episodes": len(metas),
            "steps": int(dataset.total_steps),
            "left_out": left_out,
            "max_obs_difference": max_difference,
        }
        dataset.storage.update_metadata(
            {
                "regrasp_mjx": {
                    **summary,
                    "demonstrations": str(src.path.resolve()),
                    "demonstrations_sha256": _sha256(src.path),
                    "planner": src.planner,
                    "seed": src.seed,
                    "env": json.loads(dumps(dataclasses.asdict(src.env_config))),
                    "version": versions()["regrasp_mjx"],
                    "versions": versions(),
                    "demonstrations_versions": d.meta.get("versions"),
                }
            }
        )
        _move_into_place(stage / name, root / name, ID_RE.fullmatch(name).group("namespace"))
    finally:
        env.close()
        shutil.rmtree(stage, ignore_errors=True)
    return {**summary, "seconds": round(time.perf_counter() - t0, 2)}
