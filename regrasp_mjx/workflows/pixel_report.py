"""The closed loop from pixels over a set of problems (``python -m regrasp_mjx.estimator loop``): the
problems (a test set, or held-out problems drawn from a seed), the estimator (a file, or the oracle),
the loop run a batch at a time with each finished batch written to ``OUT/pixel_loop.parts/`` (a killed
run goes on from where it stopped, with the same command), and its numbers: ``OUT/pixel_loop.json``
(strict JSON), ``OUT/pixel_loop.md`` (a table) and ``OUT/pixel_loop_rows.npz`` (every row's outcome,
each frame's estimate error, the true poses; plain arrays).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from regrasp_mjx.core.atomic import atomic_write, machine, write_json, write_results
from regrasp_mjx.core.host_loop import eta, folder_lock
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_errors import CameraErrors
from regrasp_mjx.inference.robustness import policy_hash
from regrasp_mjx.vision.estimator_file import Estimator, load_estimator
from regrasp_mjx.vision.oracle import OracleEstimator
from regrasp_mjx.vision.pose_errors import stats
from regrasp_mjx.workflows.frames import FrameRenderer
from regrasp_mjx.workflows.pixel_eyes import ERROR_COLUMNS, PixelLoopError, episode_seeds, rig_of
from regrasp_mjx.workflows.pixel_loop import MAX_REFUSED, execute_from_pixels
from regrasp_mjx.world.endoscope import Rig
from regrasp_mjx.world.sampling import episode_poses, load_testset
from regrasp_mjx.world.testsets import make_testset, versions

REPORT = "pixel_loop"
JAWS_DRAWN = {"as commanded": "drawn as commanded", "not drawn": "no images drawn"}  # the report's line
ORACLE = "oracle"  # the --estimator that names the oracle


@dataclasses.dataclass(frozen=True)
class LoopArgs:
    """What a run of the loop from pixels measures (what its parts folder must match to be resumed)."""

    policy: str
    estimator: str
    testset: str | None = "paper300"
    heldout: tuple[int, int] | None = None  # (problems, seed), instead of the test set
    n: int | None = None  # the first n problems (None: all)
    seed: int = 0
    batch: int = 32
    width: int = Rig().width  # the oracle's rig (a learned estimator's is the one it was trained at)
    height: int = Rig().height
    noise_px: float = 0.0  # the oracle's pixel noise
    render: bool = True
    camera: str | None = None  # the camera-error preset the loop looks by (None: none known, it never looks)


def problems(policy: Any, args: LoopArgs) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """The name and the needle, start and goal poses ``[N, 7]`` of the problems ``args`` names: a test
    set, or ``heldout`` problems drawn from its seed with the policy's task; the first ``n`` of them.
    Raises :class:`PixelLoopError` on needles the endoscope does not draw (other than the scene's)."""
    if args.heldout is not None:
        count, seed = args.heldout
        episodes, name = make_testset(int(count), int(seed), policy.env_config), f"held-out {count} (seed {seed})"
    else:
        episodes, name = load_testset(args.testset)[0], Path(str(args.testset)).stem
    scene = policy.env_config.scene
    for field, want in (("needle_radius", scene.needle_radius_mm), ("wire_radius", scene.wire_radius_mm)):
        radii = getattr(episodes, field)
        if radii is not None and not np.allclose(np.asarray(radii) * 1e3, want):
            raise PixelLoopError(
                f"{name}'s needles are not the scene's ({field} {want} mm): the endoscope draws the scene's needle"
            )
    needle, start, goal = (np.asarray(x, np.float64) for x in episode_poses(episodes))
    if args.n is not None:
        if not 1 <= args.n <= len(needle):
            raise PixelLoopError(f"n={args.n} is not accepted: 1 to the {len(needle)} problems of {name}")
        needle, start, goal, name = needle[: args.n], start[: args.n], goal[: args.n], f"{name}[:{args.n}]"
    return name, needle, start, goal


def camera_of(args: LoopArgs) -> CameraErrors | None:
    """The camera's known error sizes ``args`` names: a preset of :data:`camera_presets.PRESETS`, or a fit
    file (``.json``, what ``estimator fit`` wrote: an estimator of one's own); None: none. Raises
    :class:`ConfigError` on an unknown name or a missing or broken fit file (it says how to make one)."""
    return None if args.camera is None else camera_presets.named(args.camera)


def estimator_of(args: LoopArgs) -> Estimator | OracleEstimator:
    """The estimator ``args`` names: the oracle at ``width`` x ``height`` with ``noise_px``, or a file."""
    if args.estimator == ORACLE:
        return OracleEstimator.of(Rig(width=args.width, height=args.height), noise_px=args.noise_px, seed=args.seed)
    if args.noise_px or not args.render:
        raise PixelLoopError("noise_px and render=False are the oracle's: not accepted with an estimator file")
    return load_estimator(args.estimator)


def summary(rows: dict[str, np.ndarray]) -> dict[str, Any]:
    """A run's numbers from its rows: rates, steps and frames, and the estimate's errors over every frame
    (each column of :data:`ERROR_COLUMNS`; frames the fit gave no pose counted as failed)."""
    n = len(rows["success"])
    short = rows["stopped"] & ~rows["success"] & ~rows["collision"]
    taken = np.arange(rows["estimate_error_mm"].shape[1])[None] < rows["frames"][:, None]  # [N, F]
    estimate = {}
    for c, name in enumerate(ERROR_COLUMNS):
        mm, deg = rows["estimate_error_mm"][..., c][taken], rows["estimate_error_deg"][..., c][taken]
        estimate[name] = {
            "position_mm": stats(mm),
            "orientation_deg": stats(deg),
            "failed": int((~np.isfinite(mm)).sum()),
        }
    return {
        "problems": n,
        "success_rate": float(rows["success"].mean()),
        "collision_rate": float(rows["collision"].mean()),
        "time_out_rate": float(rows["time_out"].mean()),
        "stopped_short_rate": float(short.mean()),
        "invalid_starts": int((~rows["start_valid"]).sum()),
        "steps": stats(rows["steps"]),
        "frames": stats(rows["frames"]),
        "frames_total": int(rows["frames"].sum()),
        "refused_total": int(rows["refused"].sum()),
        "estimate_per_frame": estimate,
        "view_at_last_decision_mm": {
            "needle_in_e_g": stats(rows["view_error_mm"][:, 0]),
            "regrasping_tool_in_e_g": stats(rows["view_error_mm"][:, 1]),
        },
    }


def _cell(s: dict[str, float | None], f: str = ".3f") -> str:
    return "-" if s["median"] is None else f"{s['median']:{f}} / {s['p95']:{f}}"


def _looking(settings: dict[str, Any]) -> str:
    """What the report's line says of the looking and the jaws (reports written before either: nothing)."""
    out = ""
    if settings.get("look_frames"):
        out += (
            f"; it does not look: its file looks up to {settings['look_frames']} frames by a camera's known error "
            "sizes, and none were named"
            if settings.get("camera") is None
            else f"; looking up to {settings['look_frames']} frames by the camera errors {settings['camera']}"
        )
    if settings.get("jaw_open_deg") is not None:
        drawn = JAWS_DRAWN.get(settings.get("jaws_drawn"), "drawn at the scene's opening")  # earlier reports: there
        out += f"; its jaws open on the way to {settings['jaw_open_deg']:g} deg ({drawn})"
    return out


def markdown(rep: dict[str, Any]) -> list[str]:
    """The report as markdown lines."""
    s = rep["summary"]
    lines = [
        f"# The closed loop from pixels: `{rep['policy']}` on {rep['problems']}",
        "",
        f"Estimator: {rep['estimator']['name']} ({rep['estimator']['kind']}; frames {rep['frames']['width']} x "
        f"{rep['frames']['height']}{'' if rep['frames']['rendered'] else ', not rendered: the oracle reads the poses'}); "
        f"the policy's own closed loop (warm-up {rep['settings']['warmup_frames']} frames, stop tolerance "
        f"{rep['settings']['stop_tolerance']}{_looking(rep['settings'])}); seed {rep['seed']}; judged on the true "
        f"poses. {rep['machine']}; "
        f"{rep['seconds']:.0f} s over its batches, {rep['pairs_per_s']:.1f} stereo pairs/s in a process.",
        "",
        "| problems | success | collision | time-out | stopped short | steps median / p95 | frames median / p95 | refused frames |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        f"| {s['problems']} | {s['success_rate']:.3f} | {s['collision_rate']:.3f} | {s['time_out_rate']:.3f} | "
        f"{s['stopped_short_rate']:.3f} | {_cell(s['steps'], '.0f')} | {_cell(s['frames'], '.0f')} | "
        f"{s['refused_total']} of {s['frames_total']} |",
        "",
        "Each frame's estimate against the truth (median / p95; the first three in the left camera's frame, "
        "the last two as the policy sees them, in the grasping tool's frame):",
        "",
        "| object | position mm | orientation deg | failed frames |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name, e in s["estimate_per_frame"].items():
        lines.append(f"| {name} | {_cell(e['position_mm'])} | {_cell(e['orientation_deg'], '.2f')} | {e['failed']} |")
    v = s["view_at_last_decision_mm"]
    lines += [
        "",
        f"The fused view at each row's last decision, position error (mm, median / p95): needle "
        f"{_cell(v['needle_in_e_g'])}, regrasping tool {_cell(v['regrasping_tool_in_e_g'])}.",
    ]
    return lines


def _manifest(args: LoopArgs) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(args).items()}


def run(
    args: LoopArgs, out: str | Path, policy: Any, log=print, shard: tuple[int, int] = (0, 1)
) -> dict[str, Any] | None:
    """The loop from pixels on ``args``'s problems with ``policy`` (loaded from ``args.policy``),
    resumable by batches; writes the report and the rows into ``out`` and returns the report.

    ``shard`` ``(i, n)``: with ``n > 1`` this process runs only the batches ``k`` with ``k % n == i`` into
    ``out``'s parts (``n`` processes side by side: the renderer draws one picture at a time, so a GPU
    host's cores go further in several processes) and returns None; a run without one afterwards finds
    every batch done and writes the report (it refuses while a shard still runs).

    Raises:
      PixelLoopError: problems, an estimator or settings the loop cannot run; ``OUT``'s parts of another run.
      EstimatorError, TestsetError, ConfigError: an unreadable estimator or test set, bad problem counts, a
        camera preset that is not one (or a fitted one without its file).
      FolderInUse: another run (or, for the report, a shard) writes into ``out``.
      RenderUnavailable: no OpenGL context can be made here.
    """
    out = Path(out)
    i, n = shard
    if not (isinstance(i, int) and isinstance(n, int) and 0 <= i < n):
        raise PixelLoopError(f"shard={shard!r} is not accepted: (i, n) with 0 <= i < n")
    name, needle, start, goal = problems(policy, args)
    camera = camera_of(args)
    estimator = estimator_of(args)
    rig = rig_of(estimator)
    seeds = episode_seeds(len(needle), args.seed)
    parts = out / f"{REPORT}.parts"
    manifest = _manifest(args)
    # shards hold the folder together (a shared lock) and each its own shard's alone; the report's run holds
    # the folder alone, so it never runs beside a shard, starting or late, nor a shard beside it
    with contextlib.ExitStack() as held:
        held.enter_context(folder_lock(out, shared=n > 1))
        if (parts / "manifest.json").is_file() and json.loads((parts / "manifest.json").read_text()) != manifest:
            raise PixelLoopError(
                f"{parts} holds the batches of another run ({(parts / 'manifest.json').read_text().strip()}); "
                "accepted: the same arguments to resume it, or remove that folder"
            )
        if n > 1:  # shards of another N would run one another's batches
            others = {int(d.name.rsplit("_", 1)[1]) for d in parts.glob("shard_*_of_*") if d.is_dir()} - {n}
            if others:
                raise PixelLoopError(
                    f"{parts} holds shards of --shard I/{min(others)}; accepted: the same N, or the report's "
                    "run (without --shard), which runs what is left"
                )
            held.enter_context(folder_lock(parts / f"shard_{i}_of_{n}"))
        write_json(parts / "manifest.json", manifest)
        chunks = [(a, min(a + args.batch, len(needle))) for a in range(0, len(needle), args.batch)]
        mine = [c for k, c in enumerate(chunks) if k % n == i]
        todo = [(a, b) for a, b in mine if not (parts / f"rows_{a:06d}.npz").is_file()]
        log(
            f"pixels: {args.policy} on {name}, {len(needle)} problems in "
            f"{len(chunks)} batches{f' ({len(mine)} of them shard {i} of {n})' if n > 1 else ''} "
            f"({len(mine) - len(todo)} done before), estimator {args.estimator}, "
            f"{rig.width} x {rig.height}, seed {args.seed}, camera errors {args.camera or 'none'}"
        )
        renderer = FrameRenderer(rig=rig) if args.render else None
        t0, pairs = time.perf_counter(), 0
        try:
            for k, (a, b) in enumerate(todo):
                t_batch = time.perf_counter()
                rows = execute_from_pixels(
                    policy,
                    estimator,
                    needle[a:b],
                    start[a:b],
                    goal[a:b],
                    batch=args.batch,
                    render=args.render,
                    renderer=renderer,
                    log=log,
                    seeds=seeds[a:b],
                    camera=camera,
                )
                # each row's share of its batch's seconds: the report's time is the batches', whichever
                # process (or run) ran them
                rows["seconds"] = np.full(b - a, (time.perf_counter() - t_batch) / (b - a))
                atomic_write(parts / f"rows_{a:06d}.npz", lambda f, rows=rows: np.savez(f, **rows))
                pairs += int(rows["frames"].sum())
                seconds = time.perf_counter() - t0
                log(
                    f"pixels: batch {k + 1}/{len(todo)} (rows {a}-{b - 1}): success {int(rows['success'].sum())}/{b - a}, "
                    f"{pairs / seconds:.1f} stereo pairs/s, {eta(k + 1, len(todo), seconds)}"
                )
        finally:
            if renderer is not None:
                renderer.close()
        if n > 1:
            log(f"pixels: shard {i} of {n} done; the report: the same command without --shard once every shard is done")
            return None
        loaded = []
        for a, _ in chunks:
            with np.load(parts / f"rows_{a:06d}.npz", allow_pickle=False) as f:
                loaded.append({k: f[k] for k in f.files})
        longest = max(p["estimate_error_mm"].shape[1] for p in loaded)
        pad = lambda x: np.pad(x, ((0, 0), (0, longest - x.shape[1]), (0, 0)), constant_values=np.nan)  # noqa: E731
        keys = set.intersection(*(set(p) for p in loaded))  # batches written before "seconds" lack it
        rows = {
            k: np.concatenate([pad(p[k]) if k.startswith("estimate_error") else p[k] for p in loaded])
            for k in loaded[0]
            if k in keys
        }
        # the batches' own seconds (summed over the processes that ran them); this run's where they lack them
        seconds = float(rows.pop("seconds").sum()) if "seconds" in rows else time.perf_counter() - t0
        pairs = int(rows["frames"].sum()) if "seconds" in keys else pairs
        defaults = policy.closed_loop_defaults
        rep = {
            "policy": args.policy,
            "policy_hash": policy_hash(args.policy),
            "problems": name,
            "estimator": {
                "name": args.estimator,
                "kind": "oracle: keypoints projected from the true poses, the learned estimator's fit"
                if isinstance(estimator, OracleEstimator)
                else "learned",
                "noise_px": args.noise_px,
                "training": None if isinstance(estimator, OracleEstimator) else estimator.contract.get("training"),
            },
            "frames": {"width": rig.width, "height": rig.height, "rendered": args.render},
            "settings": {
                "warmup_frames": defaults["warmup_frames"],
                "stop_tolerance": defaults["stop_tolerance"],
                # the policy's looks, by the camera error sizes named (none: it does not look)
                "look_frames": defaults["look_frames"],
                "camera": args.camera,
                "camera_sizes": None if camera is None else dataclasses.asdict(camera),
                "jaw_open_deg": policy.env_config.jaw_open_deg,
                # the frames draw the regrasping jaws where the loop commanded them (none drawn without images)
                "jaws_drawn": "as commanded" if args.render else "not drawn",
                "max_refused": MAX_REFUSED,
                "batch": args.batch,
            },
            "seed": args.seed,
            "summary": summary(rows),
            "seconds": seconds,
            "pairs_per_s": pairs / seconds if pairs and seconds else 0.0,
            "machine": machine(),
            "versions": versions(),
            "date": time.strftime("%Y-%m-%d"),
        }
        atomic_write(out / f"{REPORT}_rows.npz", lambda f: np.savez(f, **rows))
        write_results(out, REPORT, markdown(rep), rep)
        shutil.rmtree(parts)
    return rep
