"""What the analysis notebooks compute: training logs as arrays, the funnel of the paper's Fig. 5,
and Table II gathered from the shipped result files. Plotting stays in the notebooks.
"""

from __future__ import annotations

import csv
import functools
import json
import math
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core import geometry
from regrasp_mjx.core.atomic import write_figure
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.workflows.render import write_gif
from regrasp_mjx.world.sampling import Episode

FIGURES_ENV = "REGRASP_FIGURES"  # a folder: notebooks save the README's figures there when it is set


class ResultsError(ValueError):
    """A results or log file is missing or not what it should be."""


def repo_root(start: str | os.PathLike | None = None) -> Path:
    """The checkout holding ``experiments/results`` (the shipped results), from ``start`` (default
    the working directory, e.g. ``notebooks/``) upwards."""
    here = Path(start or Path.cwd()).resolve()
    for p in (here, *here.parents):
        if (p / "experiments" / "results").is_dir():
            return p
    raise ResultsError(
        f"no experiments/results above {here}: the notebooks read the results a checkout of the repository ships"
    )


def save_figure(figure: Any, name: str) -> Path | None:
    """Saves a matplotlib figure (PNG) or frames ``[F, H, W, 3]`` (GIF) as ``name`` under the
    folder ``$REGRASP_FIGURES`` (relative to the repository root), only when that is set; returns
    the path written or None."""
    folder = os.environ.get(FIGURES_ENV)
    if not folder:
        return None
    path = Path(folder)
    path = (path if path.is_absolute() else repo_root() / path) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(figure, np.ndarray):
        return write_gif(path, figure)
    write_figure(path, figure, dpi=110, bbox_inches="tight")
    return path


# ----------------------------------------------------------------------------------------------
# Training logs.
# ----------------------------------------------------------------------------------------------
def _flatten(row: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in row.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def read_log(path: str | os.PathLike, setting: str | None = None) -> dict[int, dict[str, np.ndarray]]:
    """A training run's ``log.jsonl`` as ``{seed: {column: array over epochs}}``; for a run of
    several Table I settings, the rows of ``setting`` (``settings_in_log`` lists them).

    Nested fields are flattened with dots (``test.success_rate``); rows are sorted by epoch; a
    column some rows lack is NaN there. Raises :class:`ResultsError` for a missing file, a line
    that is not a JSON object with ``epoch``, or a file with no rows (of that setting).
    """
    path = Path(path)
    if not path.is_file():
        raise ResultsError(f"training log not found: {path} (a run writes <out>/log.jsonl)")
    rows: dict[int, list[dict[str, Any]]] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as err:
            raise ResultsError(f"{path}:{n} is not JSON ({err})") from err
        if not isinstance(row, dict) or "epoch" not in row:
            raise ResultsError(f"{path}:{n} is not a log row (a JSON object with 'epoch')")
        if setting is not None and row.get("setting") != setting:
            continue
        rows.setdefault(int(row.get("seed", 0)), []).append(_flatten(row))
    if not rows:
        raise ResultsError(f"{path} has no rows" + (f" of setting {setting!r}" if setting is not None else ""))
    out = {}
    for seed, rs in sorted(rows.items()):
        rs.sort(key=lambda r: r["epoch"])
        names = sorted({k for r in rs for k in r if isinstance(r[k], (int, float, type(None)))})
        out[seed] = {k: np.array([np.nan if r.get(k) is None else r.get(k, np.nan) for r in rs], float) for k in names}
    return out


def settings_in_log(path: str | os.PathLike) -> list[str]:
    """The Table I settings a ``log.jsonl`` holds rows of, in order of appearance (``[]``: one)."""
    seen: dict[str, None] = {}
    for line in Path(path).read_text().splitlines():
        if line.strip():
            name = json.loads(line).get("setting")
            if name:
                seen.setdefault(name)
    return list(seen)


def seed_band(log: dict[int, dict[str, np.ndarray]], column: str) -> tuple[np.ndarray, np.ndarray]:
    """``(epochs, values [seeds, epochs])`` of one column over the epochs every seed logged."""
    missing = [s for s, cols in log.items() if column not in cols]
    if missing:
        raise ResultsError(f"column {column!r} is not in the log of seeds {missing}; it has {sorted(log[missing[0]])}")
    n = min(len(cols["epoch"]) for cols in log.values())
    epochs = next(iter(log.values()))["epoch"][:n]
    return epochs, np.stack([cols[column][:n] for cols in log.values()])


def mean_std(xs) -> str:
    """``mean ± std`` of the finite values to three decimals (``-`` for none, the value for one)."""
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    if not xs:
        return "-"
    return f"{np.mean(xs):.3f} ± {np.std(xs):.3f}" if len(xs) > 1 else f"{xs[0]:.3f}"


def summarize_setting(log: dict[int, dict[str, np.ndarray]], exported: list[dict]) -> dict:
    """Per-seed numbers of one setting from its log rows and its exported policies' final evaluation.

    Without the final evaluation (a run stopped after its last epoch), the exported policy's bare
    success is read off the log: the test row of the epoch it was exported at (the last epoch of
    best validation success), the same network and rollout."""
    epochs, test = seed_band(log, "test.success_rate")
    if not exported:
        _, val = seed_band(log, "validation.success_rate")
        at = [len(v) - 1 - int(np.argmax(v[::-1])) for v in val]  # the last epoch of the best
        exported = [
            {
                "test": {"bare": {"success_rate": float(t[i])}, "shielded": {"success_rate": None}},
                "best_epoch": int(epochs[i]),
            }
            for t, i in zip(test, at)
        ]
    _, coll = seed_band(log, "test.collision_rate")
    _, path = seed_band(log, "test.path_length_mm")
    return {
        "seeds": sorted(log),
        "epochs": int(next(iter(log.values()))["epoch"][-1]),
        "last": test[:, -1].tolist(),
        "last10": test[:, -10:].mean(1).tolist(),
        "best": test.max(1).tolist(),
        "collision_last": coll[:, -1].tolist(),
        "path_last": path[:, -1].tolist(),
        "exported": [m["test"]["bare"]["success_rate"] for m in exported],
        "exported_shielded": [m["test"]["shielded"]["success_rate"] for m in exported],
        "best_epoch": [m["best_epoch"] for m in exported],
        "wall_s": float(max(cols["wall_s"].max() for cols in log.values())),
    }


def in_needle_frame_mm(needle: Any, points: Any) -> np.ndarray:
    """Points ``[N, 3]`` (m, in e_g) in the needle frame n, in mm; ``needle`` is one pose ``[7]``
    for all of them or one per point ``[N, 7]``."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    needle = np.broadcast_to(np.asarray(needle, np.float64), (len(points), 7))
    one = jnp.array([1.0, 0.0, 0.0, 0.0])
    rel = jax.vmap(lambda n, p: geometry.relative((n[:3], n[3:]), (p, one))[0])
    return np.asarray(rel(jnp.asarray(needle, jnp.float32), jnp.asarray(points, jnp.float32)), np.float64) * 1e3


# ----------------------------------------------------------------------------------------------
# Fig. 5: how the collision-free space narrows near the goal.
# ----------------------------------------------------------------------------------------------
def free_fraction(
    env: RegraspEnv,
    episodes: Episode,
    distances_mm: Any,
    samples: int = 64,
    rot_deg: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """The probability that a pose ``d`` mm from the goal is collision-free (the paper's Fig. 5).

    For every problem of ``episodes`` and every distance, ``samples`` poses: the goal end-effector
    moved by ``d`` along a uniformly random direction and turned by an angle ``U(-rot_deg,
    rot_deg)`` about a uniformly random axis (in its own frame); a pose is free when no counted
    pair of capsules overlaps (the environment's exact distances). Returns ``[len(distances)]``
    fractions over all problems and samples.
    """
    d = np.asarray(distances_mm, np.float64)
    if d.ndim != 1 or len(d) == 0 or not np.all(np.isfinite(d)) or np.any(d < 0):
        raise ValueError(f"distances_mm must be a non-empty list of finite distances >= 0, got {distances_mm!r}")
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    if not (math.isfinite(rot_deg) and 0 <= rot_deg <= 180):
        raise ValueError(f"rot_deg must be within [0, 180], got {rot_deg}")
    fractions = _free_fraction_fn(env, int(samples))  # compiled once per environment and sample count
    f32 = lambda x, k: jnp.asarray(np.reshape(x, (-1, k)), jnp.float32)  # noqa: E731  (one problem or a batch)
    out = fractions(
        jax.random.PRNGKey(seed),
        jnp.asarray(d, jnp.float32),
        jnp.float32(math.radians(rot_deg)),
        f32(episodes.needle_pos, 3),
        f32(episodes.needle_quat, 4),
        f32(episodes.goal_pos, 3),
        f32(episodes.goal_quat, 4),
    )
    return np.asarray(out, np.float64)


@functools.lru_cache(maxsize=8)
def _free_fraction_fn(env: RegraspEnv, samples: int):
    def one(key, dist_mm, rot, needle_pos, needle_quat, goal_pos, goal_quat):
        k_dir, k_axis, k_angle = jax.random.split(key, 3)
        u = jax.random.normal(k_dir, (3,))
        axis = jax.random.normal(k_axis, (3,))
        angle = jax.random.uniform(k_angle, (), minval=-rot, maxval=rot)
        pos = goal_pos + dist_mm * 1e-3 * u / jnp.linalg.norm(u)
        quat = geometry.quat_mul(goal_quat, geometry.quat_from_rotvec(angle * axis / jnp.linalg.norm(axis)))
        return jnp.min(env.distances(needle_pos, needle_quat, pos, quat)) > 0.0

    per_sample = jax.vmap(one, in_axes=(0, None, None, None, None, None, None))
    per_problem = jax.vmap(per_sample, in_axes=(0, None, None, 0, 0, 0, 0))
    per_distance = jax.vmap(per_problem, in_axes=(0, 0, None, None, None, None, None))

    @jax.jit
    def fractions(key, dist_mm, rot, needle_pos, needle_quat, goal_pos, goal_quat):
        keys = jax.random.split(key, (dist_mm.shape[0], needle_pos.shape[0], samples))
        free = per_distance(keys, dist_mm, rot, needle_pos, needle_quat, goal_pos, goal_quat)
        return jnp.mean(free.astype(jnp.float32), axis=(1, 2))

    return fractions


# ----------------------------------------------------------------------------------------------
# Table II from the shipped result files.
# ----------------------------------------------------------------------------------------------
PAPER_TABLE2 = [  # the paper's Table II: success, mean planning time (s there, ms here), path (mm)
    {"method": f"paper: {m}", "success": s, "median_ms": None, "mean_ms": t, "path_mm": p}
    for m, s, t, p in [
        ("PRM* (F)", 0.66, 103342.0, 5.2),
        ("PRM* (R)", 0.72, 89985.6, 5.0),
        ("RRT* (F)", 0.18, 186279.0, 5.1),
        ("RRT* (R)", 0.2, 147657.4, 4.7),
        ("BFMT* (F)", 0.0, None, None),
        ("BFMT* (R)", 0.0, None, None),
        ("BIT* (F)", 0.66, 3837.7, 5.2),
        ("BIT* (R)", 0.72, 2590.5, 5.0),
        ("DDPG+BC (mixed)", 0.97, 21.2, 4.2),
    ]
]
POLICY_ROWS = {  # file under results/inference -> row name
    "eval_cpu1_single.json": "policy, one 3x512 network (paper's learner), bare",
    "eval_cpu1_ensemble3.json": "policy, 3-network ensemble (earlier default), bare",
    "eval_cpu1_ensemble3_shield.json": "policy, 3-network ensemble + shield (earlier default)",
    "eval_cpu1_student3x256_bare.json": "policy, distilled 3x256 network, bare",
    "eval_cpu1_shipped.json": "policy, shipped (distilled 2x256 network + shield)",
}


def _json(path: Path) -> Any:
    if not path.is_file():
        raise ResultsError(f"result file not found: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ResultsError(f"{path} is not JSON ({err})") from err


def table2(results: str | os.PathLike, jaw_angle_deg: float = 20.0) -> list[dict[str, Any]]:
    """Table II rows from ``results`` (``experiments/results``): every planner of ``planners.csv`` at
    this jaw angle, the policy rows of ``inference/`` (one CPU core), and the paper's two rows.

    Each row: ``method``, ``success``, ``median_ms``, ``mean_ms`` (over successes), ``path_mm``
    (over successes), ``kind`` (``planner``, ``policy`` or ``paper``).
    """
    results = Path(results)
    path = results / "planners.csv"
    if not path.is_file():
        raise ResultsError(f"planner results not found: {path} (experiments/planners.py writes it)")
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            try:
                if float(r["jaw_angle_deg"]) != jaw_angle_deg:
                    continue
                rows.append(
                    {
                        "method": r["algorithm"],
                        "success": float(r["success_rate"]),
                        "median_ms": 1e3 * float(r["plan_time_median_s"]),
                        "mean_ms": 1e3 * float(r["plan_time_mean_s"]),
                        "path_mm": float(r["path_length_mm"]),
                        "kind": "planner",
                    }
                )
            except (KeyError, ValueError) as err:
                raise ResultsError(f"{path}: row {r} lacks a number ({err})") from err
    if not rows:
        raise ResultsError(f"{path} has no rows for a jaw angle of {jaw_angle_deg} deg")
    for name, label in POLICY_ROWS.items():
        d = _json(results / "inference" / name)
        rows.append(
            {
                "method": label,
                "success": float(d["success_rate"]),
                "median_ms": float(d["planning_time_ms_median"]),
                "mean_ms": float(d["planning_time_ms_mean"]),
                "path_mm": float(d["path_length_mm"]),
                "kind": "policy",
            }
        )
    rows += [{**r, "kind": "paper"} for r in PAPER_TABLE2]
    return rows


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    """A markdown table of ``rows``; ``columns`` are ``(key, header, format)``; None prints as -."""
    lines = ["| " + " | ".join(h for _, h, _ in columns) + " |", "|" + " --- |" * len(columns)]
    for r in rows:
        cells = ["-" if r.get(k) is None else format(r[k], fmt) for k, _, fmt in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
