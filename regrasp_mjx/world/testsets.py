"""Test sets drawn from the environment's own start distribution: row i is the problem that
``RegraspEnv.reset`` draws from key i of ``jax.random.split(PRNGKey(seed), n)`` (colliding starts and
goals redrawn), and the package versions a file records (``python -m regrasp_mjx.testset`` writes one)."""

from __future__ import annotations

import functools
from importlib import metadata

import jax
import numpy as np

from regrasp_mjx.core.config import ConfigError, EnvConfig
from regrasp_mjx.world.sampling import Episode, sample_episode
from regrasp_mjx.world.scene import load_scene


@functools.lru_cache(maxsize=8)
def _sampler(config: EnvConfig):
    """The jitted, batched problem sampler of an environment config, built once per config (a
    trainer draws its validation problems with it every run; tracing it takes seconds)."""
    radius, wire = config.scene.needle_radius_mm * 1e-3, config.scene.wire_radius_mm * 1e-3
    distances = load_scene(config.scene).distance_fn()
    return jax.jit(jax.vmap(lambda k: sample_episode(k, config.task, radius, distances, wire)))


# the most problems one test set holds (about 0.3 GB in memory as it is made); more is refused before any work
MAX_PROBLEMS = 1_000_000


def make_testset(n: int, seed: int, config: EnvConfig = EnvConfig(), batch: int = 1024) -> Episode:
    """``n`` problems from the paper's distributions; raises if any could not be made collision-free."""
    if not isinstance(n, int) or not 1 <= n <= MAX_PROBLEMS:
        raise ConfigError(f"n={n!r} is not accepted: a positive number of problems, at most {MAX_PROBLEMS}")
    draw = _sampler(config)
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    parts, valid = [], []
    for i in range(0, n, batch):
        ep, ok = draw(keys[i : i + batch])
        parts.append(jax.tree.map(np.asarray, ep))
        valid.append(np.asarray(ok))
    valid = np.concatenate(valid)
    if not valid.all():
        raise RuntimeError(
            f"{int((~valid).sum())} of {n} problems stayed in collision after "
            f"{config.task.max_sample_tries} draws; raise task.max_sample_tries"
        )
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)


def versions() -> dict[str, str]:
    out = {}
    for pkg in ("regrasp_mjx", "jax", "mujoco", "mujoco-mjx"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    return out
