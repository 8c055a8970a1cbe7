"""How long a regrasp takes on the dVRK: every paper300 plan of a policy (the shipped default)
timed at the PSM's own joint limits and re-checked along its executed motion (``regrasp_mjx.robot.psm_timing``,
``regrasp_mjx.robot.executed_motion``).

    python experiments/execution_time.py --out experiments/results/psm_timing

One fixed port, as a lab sets its arm up once: the regrasping PSM's base 0.12 m behind the average
start (``dvrk.base_behind``), the camera at the grasping tool (poses in e_g). The paper's real dVRK
took 5.15 s to execute a regrasp (2.88 s with the needle pose known), at speeds it does not state.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from regrasp_mjx.core.atomic import write_results
from regrasp_mjx.envs.camera_errors import FPS, PRESETS
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.robot import dvrk
from regrasp_mjx.robot.executed_motion import MotionRefused, time_executed, time_plan, tool_poses
from regrasp_mjx.robot.psm_timing import time_joints
from regrasp_mjx.world.sampling import episode_poses, load_testset
from regrasp_mjx.world.scene import load_scene


def _off_path(points: np.ndarray, path: np.ndarray) -> float:
    """The farthest any of ``points`` [N, 3] lies from the polyline ``path`` [K, 3] (m)."""
    if len(path) == 1:
        return float(np.linalg.norm(points - path[0], axis=1).max())
    a, b = path[:-1], path[1:]
    ab = b - a
    s = np.clip(np.einsum("nkd,kd->nk", points[:, None] - a, ab) / np.maximum((ab * ab).sum(1), 1e-18), 0.0, 1.0)
    nearest = a + s[..., None] * ab
    return float(np.linalg.norm(points[:, None] - nearest, axis=2).min(1).max())


def closed_loop_motion(
    policy, needle, start, goal, depth, base, checker, noise_mm: float, seed: int, **options
) -> dict:
    """The closed loop's executed steps as the arm's motion (``executed_motion.time_executed``): every row
    of ``policy.execute`` (fused, the policy's own settings, needle noise sigma ``noise_mm``, or
    ``options``' camera errors and look budget) that succeeded, timed and re-checked against the
    true needle; MuJoCo's clearance at every sample. ``total_s``: the motion and the frames taken
    holding still (the warm-up, the looks) at the endoscope's 30 frames per second."""
    noise = None if options.get("camera") else NeedleNoise(noise_mm, 0.0)
    out = policy.execute(needle, start, goal, noise=noise, seed=seed, goal_depth_mm=depth, **options)
    durations, inserted, refused, clearance, seconds, still = [], [], {}, [], [], []
    for i in np.flatnonzero(out["success"]):
        t0 = time.perf_counter()
        try:
            r = time_executed(policy, out["poses"][i][: out["steps"][i] + 1], needle[i], base)
        except MotionRefused as why:
            refused[int(i)] = str(why)
            continue
        finally:
            seconds.append(time.perf_counter() - t0)
        durations.append(r.trajectory.duration_s)
        still.append((out["frames"][i] - out["steps"][i]) / FPS)
        inserted.append(r.inserted)
        poses = tool_poses(base, r.trajectory.q)
        clearance.append(min(checker.clearance(needle[i, :3], needle[i, 3:], p[:3], p[3:]) for p in poses))
    d = np.array(durations)
    total = d + np.array(still)
    return {
        "options": {k: str(v) for k, v in options.items()},
        "total_s": {
            "median": float(np.median(total)),
            "p95": float(np.percentile(total, 95)),
            "max": float(total.max()),
        },
        "noise_mm": noise_mm,
        "succeeded": int(np.sum(out["success"])),
        "timed": len(d),
        "refused": len(refused),
        "refused_why": {str(k): v for k, v in refused.items()},
        "with_inserted_waypoints": int(np.sum(np.array(inserted) > 0)),
        "steps_median": float(np.median(out["steps"][out["success"]])),
        "duration_s": {"median": float(np.median(d)), "p95": float(np.percentile(d, 95)), "max": float(d.max())},
        "timing_call_ms": {"median": 1e3 * float(np.median(seconds)), "max": 1e3 * float(np.max(seconds))},
        "clearance_um_min": 1e6 * float(np.min(clearance)),
        "penetrations": int(np.sum(np.array(clearance) < 0.0)),
    }


STATS = {"mean": np.mean, "median": np.median, "p95": lambda x: np.percentile(x, 95), "max": np.max}


def _spread(x, names: tuple[str, ...] = ("median", "max"), scale: float = 1.0) -> dict[str, float]:
    """``names`` of :data:`STATS` of ``x``, times ``scale``, as floats."""
    return {n: scale * float(STATS[n](np.asarray(x))) for n in names}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", default=None, help="policy folder or shipped name (default: the shipped one)")
    p.add_argument("--testset", default="paper300")
    p.add_argument("--out", default=None)
    p.add_argument(
        "--closed-loop-noise-mm",
        type=float,
        default=0.25,
        help="also time the fused closed loop's executed steps under this needle noise (negative: skip)",
    )
    p.add_argument("--camera", default=None, choices=tuple(PRESETS), help="the closed loop under a camera preset")
    p.add_argument("--look-frames", type=int, default=None, help="the closed loop's look budget (default: its own)")
    p.add_argument("--name", default="paper300")
    args = p.parse_args()
    policy = load_policy(args.policy)
    episodes, _ = load_testset(args.testset)
    needle, start, _ = episode_poses(episodes)
    depth = np.asarray(episodes.goal_depth) * 1e3
    psm = {"regrasping_base": dvrk.base_behind(dvrk.average_pose(start))}
    identity = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (len(start), 1))
    plan = policy.plan_from_camera(identity, start, needle, goal_depth_mm=depth, check_grasp=False, psm=psm)
    checker = HostChecker(load_scene(policy.env_config.scene))  # MuJoCo's distances: an independent measure
    base = dvrk.as_matrix(psm["regrasping_base"])
    durations, inserted, refused, seconds, timing_ms, deviation, clearance = [], [], {}, [], [], [], []
    for i in range(len(start)):
        t0 = time.perf_counter()
        try:
            r = time_plan(policy, plan, identity, needle, psm, query=i)
        except MotionRefused as why:
            refused[i] = str(why)
            continue
        finally:
            seconds.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        time_joints(r.trajectory.waypoints)  # the time-parameterisation alone
        timing_ms.append(1e3 * (time.perf_counter() - t0))
        durations.append(r.trajectory.duration_s)
        inserted.append(r.inserted)
        poses = tool_poses(base, r.trajectory.q)
        deviation.append(_off_path(poses[:, :3], plan.trajectory("eg", i)[:, :3]))
        clearance.append(min(checker.clearance(needle[i, :3], needle[i, 3:], p[:3], p[3:]) for p in poses))
    d = np.array(durations)
    row = {
        "policy": args.policy or "default",
        "testset": args.testset,
        "problems": len(start),
        "timed": len(d),
        "refused": len(refused),
        "refused_why": {str(k): v for k, v in refused.items()},
        "with_inserted_waypoints": int(np.sum(np.array(inserted) > 0)),
        "duration_s": _spread(d, ("mean", "median", "p95", "max")),
        "timing_call_ms": _spread(seconds, scale=1e3),
        "time_joints_ms": _spread(timing_ms),
        "deviation_mm": _spread(deviation, scale=1e3),
        "clearance_um_min": 1e6 * float(np.min(clearance)),
        "penetrations": int(np.sum(np.array(clearance) < 0.0)),
    }
    lines = [
        f"Policy `{row['policy']}` on {args.testset} ({row['problems']} problems), one fixed port; timed at the dVRK "
        "PSM's joint limits, 1 kHz, every 1-ms piece re-checked (`regrasp_mjx.robot.executed_motion`).",
        "",
        "| timed | refused | with inserted waypoints | duration mean / median / p95 / max (s) | off the checked path, "
        "median / max (mm) | smallest clearance at a sample (um) | penetrations | time_joints alone, median / max (ms) | "
        "timing and re-check, median / max (ms) |",
        "| ---: | ---: | ---: | --- | --- | ---: | ---: | --- | --- |",
        f"| {row['timed']} | {row['refused']} | {row['with_inserted_waypoints']} | "
        + " / ".join(f"{row['duration_s'][k]:.3f}" for k in ("mean", "median", "p95", "max"))
        + f" | {row['deviation_mm']['median']:.3f} / {row['deviation_mm']['max']:.3f} | {row['clearance_um_min']:.1f} | "
        f"{row['penetrations']} | {row['time_joints_ms']['median']:.2f} / {row['time_joints_ms']['max']:.2f} | "
        f"{row['timing_call_ms']['median']:.1f} / {row['timing_call_ms']['max']:.1f} |",
    ]
    if args.closed_loop_noise_mm >= 0:
        options = {k: v for k, v in (("camera", args.camera), ("look_frames", args.look_frames)) if v is not None}
        loop = closed_loop_motion(
            policy, needle, start, None, depth, base, checker, args.closed_loop_noise_mm, 0, **options
        )
        row["closed_loop"] = loop
        lines += [
            "",
            "The fused closed loop's executed steps ("
            + (f"the camera's errors {args.camera}" if args.camera else f"needle noise sigma {loop['noise_mm']:g} mm")
            + ", the policy's own settings"
            + (f" but {args.look_frames} look frames" if args.look_frames is not None else "")
            + ", seed 0), each succeeded row's motion timed and re-checked the same way "
            "(`executed_motion.time_executed`; the warm-up frames, the tool still, not counted):",
            "",
            "| succeeded | timed | refused | with inserted waypoints | steps, median | duration median / p95 / max (s) "
            "| smallest clearance at a sample (um) | penetrations | timing and re-check, median (ms) |",
            "| ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |",
            f"| {loop['succeeded']} | {loop['timed']} | {loop['refused']} | {loop['with_inserted_waypoints']} | "
            f"{loop['steps_median']:g} | "
            + " / ".join(f"{loop['duration_s'][k]:.3f}" for k in ("median", "p95", "max"))
            + f" | {loop['clearance_um_min']:.1f} | {loop['penetrations']} | {loop['timing_call_ms']['median']:.1f} |",
            "",
            f"With the frames taken holding still (warm-up and looks, 30 per second; {loop['options'] or 'no options'}): "
            "median / p95 / max " + " / ".join(f"{loop['total_s'][k]:.3f}" for k in ("median", "p95", "max")) + " s.",
        ]
    print("\n".join(lines))
    for k, v in refused.items():
        print(f"refused {k}: {v}")
    write_results(args.out, args.name, lines, row)


if __name__ == "__main__":
    main()
