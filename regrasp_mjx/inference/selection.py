"""Choices made on validation problems of their own seed, never on a test set: which candidate
network ships (a score over rows of its robustness table) and its closed loop's settings (warm-up
frames and stop tolerance, the best mean success over frame-noise settings).

``python -m regrasp_mjx.recipe`` makes both choices for a recipe; ``experiments/closed_loop_select.py``
makes the second for any policy.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.robot.robot_errors import RobotErrors
from regrasp_mjx.world.sampling import episode_needles, episode_poses


def score(rows: list[dict[str, Any]], rule: Sequence[tuple[str, str]]) -> float:
    """The mean success rate over the robustness-table rows ``(mode, condition)`` of ``rule``
    (:func:`regrasp_mjx.inference.robustness.table`'s rows); a row the table lacks is an error."""
    found = {(r["mode"], r["condition"]): r["success_rate"] for r in rows}
    missing = [f"{m} / {c}" for m, c in rule if (m, c) not in found]
    if missing:
        raise ConfigError(f"the candidate's table lacks the rows {missing} its score needs")
    return float(np.mean([found[key] for key in rule]))


def parse_noises(text: str) -> list[tuple[NeedleNoise, RobotErrors]]:
    """``"0.1,0.25:0.25,..."``: frame noise ``SIGMA``, ``SIGMA:BIAS`` or ``SIGMA:BIAS:T:R:J:TOOL``
    (mm, deg; :class:`~regrasp_mjx.robot.robot_errors.RobotErrors`), comma-separated."""
    out = []
    for item in text.split(","):
        try:
            v = [float(x) for x in item.split(":")]
        except ValueError:
            v = []
        if not 1 <= len(v) <= 6:
            raise ConfigError(f"noise {item!r} is not accepted: SIGMA, SIGMA:BIAS or SIGMA:BIAS:T:R:J:TOOL numbers")
        out.append((NeedleNoise(*v[:2]), RobotErrors(*v[2:])))
    return out


def closed_loop_settings(
    policy,
    episodes,
    noises: list[tuple[NeedleNoise, RobotErrors]],
    warmups: Sequence[int],
    stops: Sequence[float],
    frames: str = "fused",
    observe: str = "camera",
    log: Callable[[dict[str, Any]], None] | None = None,
    looks: Sequence[int] = (0,),
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Every (warm-up frames, stop tolerance, look frames) of the closed loop on ``episodes`` under
    each of ``noises`` (shielded, seed 1); returns the rows and the best by mean success (the first
    of equals, so list the cheaper settings first). ``frames="each"`` has no warm-up and does not
    look: only 1 and 0 are tried."""
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes) if policy.general else {}
    fused = frames == "fused"
    rows = []
    for warmup, stop, look in itertools.product(warmups if fused else (1,), stops, looks if fused else (0,)):
        success = [
            float(
                policy.execute(
                    needle,
                    start,
                    goal,
                    noise,
                    frames=frames,
                    warmup_frames=warmup,
                    stop_tolerance=stop,
                    look_frames=look,
                    seed=1,
                    robot=robot,
                    observe=observe,
                    **needles,
                )["success"].mean()
            )
            for noise, robot in noises
        ]
        rows.append(
            {
                "warmup_frames": warmup,
                "stop_tolerance": stop,
                "look_frames": look,
                "success": success,
                "mean": float(np.mean(success)),
            }
        )
        if log is not None:
            log(rows[-1])
    return rows, max(rows, key=lambda r: r["mean"])


def _robot_text(r: RobotErrors) -> str:
    return (
        f", calibration {r.calibration_mm:g} mm {r.calibration_deg:g} deg, joints {r.joint_offset:g}, "
        f"tools {r.tool_noise_mm:g} mm"
    )


def closed_loop_markdown(rows: list[dict[str, Any]], best: dict[str, Any], noises) -> list[str]:
    """:func:`closed_loop_settings`'s rows as a table, the best mean in bold."""
    lines = [
        "| warm-up frames | stop tolerance | look frames | "
        + " | ".join(
            f"sigma {n.sigma_mm:g} bias {n.bias_mm:g}" + (_robot_text(r) if r != RobotErrors() else "")
            for n, r in noises
        )
        + " | mean |",
        "| ---: | ---: | ---: |" + " ---: |" * (len(noises) + 1),
    ]
    for r in rows:
        mark = "**" if r is best else ""
        lines.append(
            f"| {r['warmup_frames']} | {r['stop_tolerance']:g} | {r.get('look_frames', 0)} | "
            + " | ".join(f"{v:.3f}" for v in r["success"])
            + f" | {mark}{r['mean']:.3f}{mark} |"
        )
    return lines
