"""What ``python -m regrasp_mjx.evaluate`` prints of a policy on a test set, as text: the numbers of
:func:`~regrasp_mjx.inference.testset_plans.evaluate`, one condition measured as the robustness table
measures it (:func:`~regrasp_mjx.inference.robustness.measure`), and the two engines compared
(:func:`~regrasp_mjx.inference.testset_plans.engine_agreement`, as one JSON-ready row and as text).
The measuring is :mod:`regrasp_mjx.inference.testset_plans`'s and :mod:`regrasp_mjx.inference.robustness`'s."""

from __future__ import annotations

from typing import Any

import numpy as np

from regrasp_mjx.inference.queries import START_WARN_MM


def agreement_row(r: dict[str, Any], policy: str, testset: str, shield: bool) -> dict[str, Any]:
    """:func:`~regrasp_mjx.inference.testset_plans.engine_agreement`'s answer ``r`` as one row: the
    verdicts that differ (their rows, the first 20) and the largest action and pose differences."""
    late = r["time_out"]
    rows = sorted({i for i, _ in r["differ"]})
    return {
        "policy": policy,
        "testset": testset,
        "shield": shield,
        "problems": len(late),
        "success_jax": float(np.mean(r["batch"].success)),
        "verdicts_differ": len(rows),
        "rows_differ": rows[:20],
        "max_action_diff": float(r["action_diff"][~late].max(initial=0.0)),
        "max_action_diff_time_out": float(r["action_diff"][late].max(initial=0.0)),
        "max_pose_diff": float(r["pose_diff"].max(initial=0.0)),
    }


def agreement_text(out: dict[str, Any]) -> str:
    """:func:`agreement_row`'s row as text."""
    rows = out["rows_differ"]
    return (
        f"{out['policy']} on {out['testset']}, shield {'on' if out['shield'] else 'off'}: each problem one at a time "
        f"on the lean path against one batch on the JAX path\n  verdicts that differ: {out['verdicts_differ']} of "
        f"{out['problems']}"
        + (f" (rows {rows})" if rows else "")
        + f"\n  largest action difference {out['max_action_diff']:.1e} (plans that end before the horizon), "
        f"{out['max_action_diff_time_out']:.1e} (time-outs); pose {out['max_pose_diff']:.1e}"
    )


def condition_text(r: dict[str, Any], mode: str, camera: str | None = None) -> str:
    """One condition's row of :func:`~regrasp_mjx.inference.robustness.measure` (with ``policy`` and
    ``testset`` added) as text; ``camera`` names a real camera's errors where they were measured."""
    return (
        f"{r['policy']} on {r['testset']} ({r['problems_valid']} of {r['problems']} problems keep the margin; {mode}, "
        f"needle noise {r['sigma_mm']:g} mm, bias {r['bias_mm']:g} mm, "
        f"clearance margin {r['clearance_mm']:g} mm, shield {'on' if r['shield'] else 'off'}; "
        f"calibration {r['calibration_mm']:g} mm / {r['calibration_deg']:g} deg, "
        f"joint offsets {r['joint_offset']:g}, tool noise {r['tool_noise_mm']:g} mm, "
        f"tools seen by the {r['observe']}"
        + (f"; the camera's errors {camera}" if camera else "")
        + "; judged on the true poses)\n"
        f"  success {r['success_rate']:.3f}  collision {r['collision_rate']:.3f}"
        f"  time-out {r['time_out_rate']:.3f}  stopped short of the true goal {r['wrong_stop_rate']:.3f}"
        + (
            f"\n  frames fused: median {r['frames_median']:g}, {r['looked_mean']:.1f} of them looked at while "
            "holding still (mean)"
            if r["frames_median"] is not None  # None: no problem keeps the margin
            else ""
        )
        + (
            f"\n  jaws opened before the first move: {r['opened_rate']:.3f} of the problems; opening sweeps "
            f"not clear on the truth: {r['opening_collision_rate']:.3f}"
            if r["opened_rate"]
            else ""
        )
    )


def evaluation_text(r: dict[str, Any], timed_batch: bool = True) -> str:
    """:func:`~regrasp_mjx.inference.testset_plans.evaluate`'s numbers (with ``policy``,
    ``clearance_mm`` and ``testset`` added) as text; ``timed_batch`` False: the batch was not timed."""
    path = "-" if r["path_length_mm"] is None else f"{r['path_length_mm']:.2f} mm"
    return (
        f"{r['policy']} on {r['testset']} ({r['problems']} problems, {r['backend']}: {r['device']}; "
        f"shield {'on' if r['shield'] else 'off'}, clearance margin {r['clearance_mm']:g} mm)\n"
        f"  success {r['success_rate']:.3f}  collision {r['collision_rate']:.3f}  time-out {r['time_out_rate']:.3f}\n"
        + (
            f"  planning time per query: mean {r['planning_time_ms_mean']:.3f} ms, median "
            f"{r['planning_time_ms_median']:.3f} ms ({r['timed_queries']} queries, one at a time, "
            f"{r['single_query_engine']} path)\n"
            if r["timed_queries"]
            else ""
        )
        + (
            f"  batched: {r['batch_plans_per_s']:,.0f} plans/s (batch {r['batch_size']}"
            + (f" in chunks of {r['batch_chunk']}" if r["batch_chunk"] < r["batch_size"] else "")
            + ")\n"
            if timed_batch
            else ""
        )
        + f"  path length {path}"
        + (
            f"\n  warning: {r['far_starts']} starts lie beyond {START_WARN_MM:g} mm of their needle "
            "(no start was trained there): check the test set's units (metres) and frame"
            if r["far_starts"]
            else ""
        )
    )
