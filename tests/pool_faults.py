"""Plan functions for the pool tests; top-level so that spawned workers can import them."""

from __future__ import annotations

import os
import time


def faulty_plan(problem, options):
    kind = problem["kind"]
    if kind == "raise":
        raise RuntimeError("planner exploded")
    if kind == "hang":
        time.sleep(3600)
    if kind == "crash":
        os._exit(3)
    return {"solved": True, "value": problem["value"] * 2, "pid": os.getpid()}
