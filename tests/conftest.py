"""Shared fixtures: one environment and one set of jitted functions per test session (compiling
MJX programs on a 2-core CPU takes seconds; doing it once keeps the suite fast).

The suite runs on two pytest-xdist workers, one test file each (``-n 2 --dist loadfile`` in
pyproject.toml), sharing one persistent compilation cache. Tests marked ``alone`` run while no
other test runs (see :func:`pytest_runtest_protocol`).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import tempfile
from pathlib import Path

# One folder for the run, made by the first process that imports this file (xdist's controller, or
# a plain run's only process); the workers inherit its path through the environment.
_OWNER = "REGRASP_MJX_TEST_SHARED" not in os.environ
SHARED = Path(os.environ.setdefault("REGRASP_MJX_TEST_SHARED", tempfile.mkdtemp(prefix="regrasp_mjx_tests_")))

# One persistent compilation cache for the whole run, set in the environment so that the workers,
# the CLIs and training children the tests start, and the notebooks' kernels all read and write
# it: programs built anew (a run and its resumed copy, a learner per test, a notebook planning
# with a shipped policy) load instead of compiling again. A size limit turns on the cache's file
# lock, which makes writes from several processes at once safe.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(SHARED / "jax_cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(8 << 30))

import jax  # noqa: E402
import pytest  # noqa: E402

from regrasp_mjx.config import EnvConfig  # noqa: E402
from regrasp_mjx.env import RegraspEnv  # noqa: E402
from regrasp_mjx.sampling import load_testset  # noqa: E402


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "alone: runs while no other test runs (the other worker waits); for tests whose processes "
        "must meet within a timeout (gloo gives up connecting after 30 s)",
    )


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Every test (notebooks too) holds a shared lock on one file of the run while it runs, a test
    marked ``alone`` an exclusive one: it waits for the other worker's current test, which then
    waits for it. Without xdist the lock is this process's own and never waits."""
    alone = item.get_closest_marker("alone") is not None
    with open(SHARED / "alone.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        yield


def pytest_unconfigure(config):
    if _OWNER:
        shutil.rmtree(SHARED, ignore_errors=True)


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
