"""``python -m regrasp_mjx.testset``: writes a test set of regrasping problems.

Row i is the problem that ``RegraspEnv.reset`` draws from key i of ``jax.random.split(PRNGKey(seed),
n)``, so a test set is the environment's own start distribution, colliding starts and goals
redrawn. The file's keys, shapes and units are listed in docs/environment.md and in its ``meta`` JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time
from importlib import metadata

import jax
import numpy as np

from regrasp_mjx.atomic import dumps, output_file_problem
from regrasp_mjx.config import TASKS, ConfigError, EnvConfig, SceneConfig
from regrasp_mjx.sampling import Episode, load_testset, sample_episode, save_testset
from regrasp_mjx.scene import load_scene


@functools.lru_cache(maxsize=8)
def _sampler(config: EnvConfig):
    """The jitted, batched problem sampler of an environment config, built once per config (a
    trainer draws its validation problems with it every run; tracing it takes seconds)."""
    radius, wire = config.scene.needle_radius_mm * 1e-3, config.scene.wire_radius_mm * 1e-3
    distances = load_scene(config.scene).distance_fn()
    return jax.jit(jax.vmap(lambda k: sample_episode(k, config.task, radius, distances, wire)))


def make_testset(n: int, seed: int, config: EnvConfig = EnvConfig(), batch: int = 1024) -> Episode:
    """``n`` problems from the paper's distributions; raises if any could not be made collision-free."""
    if not isinstance(n, int) or n < 1:
        raise ConfigError(f"n={n!r} is not accepted: a positive number of problems")
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m regrasp_mjx.testset", description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=300, help="number of problems (default 300)")
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed (default 0)")
    parser.add_argument("--out", required=True, help="output .npz path (written atomically)")
    parser.add_argument(
        "--jaw-angle-deg",
        type=float,
        default=SceneConfig.jaw_angle_deg,
        help="angle between the open regrasping jaws, degrees (default 20)",
    )
    parser.add_argument(
        "--task",
        default="paper",
        choices=sorted(TASKS),
        help="problem distribution: paper (default) or general (any goal grasp in range, needles of 4-12 mm)",
    )
    args = parser.parse_args(argv)
    if args.n < 1:
        parser.error(f"--n {args.n} is not accepted: an integer >= 1")
    problem = output_file_problem(args.out, ".npz")
    if problem:
        parser.error(problem)
    try:
        config = EnvConfig(scene=SceneConfig(jaw_angle_deg=args.jaw_angle_deg), task=TASKS[args.task])
        t0 = time.perf_counter()
        episodes = make_testset(args.n, args.seed, config)
    except ConfigError as err:
        parser.error(str(err))
    meta = {
        "seed": args.seed,
        "scene": dataclasses.asdict(config.scene),
        "task": dataclasses.asdict(config.task),
        "versions": versions(),
        "units": "metres, radians, quaternions wxyz; every pose in the grasping end-effector frame",
    }
    path = save_testset(args.out, episodes, meta)
    load_testset(path)  # read back: what we wrote must pass our own validation
    gap = np.linalg.norm(episodes.goal_pos - episodes.start_pos, axis=-1) * 1e3
    print(
        dumps(
            {
                "out": str(path),
                "n": args.n,
                "seed": args.seed,
                "seconds": round(time.perf_counter() - t0, 2),
                "start_to_goal_mm": {
                    "mean": round(float(gap.mean()), 3),
                    "min": round(float(gap.min()), 3),
                    "max": round(float(gap.max()), 3),
                },
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
