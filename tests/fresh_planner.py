"""Planning in a process of its own, for tests that compare two planners' paths for one seed: OMPL
seeds its random numbers once per process (``RNG.setSeed`` after sampling has started does not
reset every generator), so a second planner in the same process would not repeat the first's draws."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np


def _plan(config, seed: int, problems) -> list[np.ndarray]:
    from regrasp_mjx.planning.ompl_planner import OmplPlanner

    planner = OmplPlanner(config, seed=seed)
    return [planner.plan(*problem).poses for problem in problems]


def plan_fresh(config, seed: int, problems) -> list[np.ndarray]:
    """The paths :class:`OmplPlanner` ``(config, seed)`` plans for ``problems`` (needle, start, goal
    triples), in a fresh process."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_plan, config, seed, problems).result()
