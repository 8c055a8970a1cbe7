"""Shared fixtures: one environment and one set of jitted functions per test session (compiling
MJX programs on a 2-core CPU takes seconds; doing it once keeps the suite fast)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import pytest  # noqa: E402

from regrasp_mjx.config import EnvConfig  # noqa: E402
from regrasp_mjx.env import RegraspEnv  # noqa: E402
from regrasp_mjx.sampling import load_testset  # noqa: E402

# One persistent compilation cache per test session: tests that build the same programs anew (a
# run and its resumed copy, a learner per test) load them instead of compiling them again.
jax.config.update("jax_compilation_cache_dir", tempfile.mkdtemp(prefix="regrasp_mjx_test_jax_cache_"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

ROOT = Path(__file__).resolve().parent.parent
PAPER_TESTSET = ROOT / "regrasp_mjx" / "data" / "paper300.npz"


@pytest.fixture(scope="session")
def env() -> RegraspEnv:
    return RegraspEnv(EnvConfig())


@pytest.fixture(scope="session")
def jit_env(env):
    """``(reset, reset_from, step)`` jitted and vmapped once."""
    return jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.reset_from)), jax.jit(jax.vmap(env.step))


@pytest.fixture(scope="session")
def paper_testset():
    return load_testset(PAPER_TESTSET)


@pytest.fixture(scope="session")
def distance_fn(env):
    return jax.jit(jax.vmap(env.distances))
