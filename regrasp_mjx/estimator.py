"""``python -m regrasp_mjx.estimator``: render labelled stereo frames, train the keypoint estimator, measure it.

Six subcommands (each with ``--help``):

- ``render``: N episodes x F frames of one seed to an npz (MuJoCo's OpenGL renderer; ``MUJOCO_GL=egl``
  headless), in worker processes, resumable;
- ``train``: the estimator on rendered frames, validated each epoch on frames of another seed;
  checkpoints, resume (the same command again), the best epoch exported to ``OUT/estimator``;
- ``evaluate``: its pose errors on held-out frames, ``OUT/estimator_errors.json`` and ``.md`` (and every
  frame's, ``OUT/estimator_errors_frames.npz``);
- ``fit``: the camera-error model fitted to those per-frame errors, a strict JSON file (the ``rendered``
  preset's, ``regrasp_mjx/data/camera_rendered.json``);
- ``bench``: its milliseconds per stereo pair on this machine's default device;
- ``loop``: the closed loop from pixels (a policy driven by the estimator's view of rendered frames, judged
  on the true poses) on a test set or held-out problems, ``OUT/pixel_loop.json`` and ``.md``, resumable.
"""

from __future__ import annotations

import argparse
import sys

from regrasp_mjx.core.atomic import dumps, output_file_problem, output_folder_problem, write_json
from regrasp_mjx.core.config import TASKS, ConfigError
from regrasp_mjx.core.host_loop import FolderInUse, run_command
from regrasp_mjx.envs import camera_presets
from regrasp_mjx.envs.camera_presets import PRESETS
from regrasp_mjx.inference.policy import PolicyError, load_policy
from regrasp_mjx.vision import error_fit
from regrasp_mjx.vision.error_fit import FitError
from regrasp_mjx.vision.estimator_file import EstimatorError
from regrasp_mjx.vision.network import WIDTHS
from regrasp_mjx.vision.oracle import OracleError
from regrasp_mjx.vision.training import CheckpointError
from regrasp_mjx.workflows import estimator_report, pixel_report
from regrasp_mjx.workflows.estimator_training import Settings, deterministic_gpu, train
from regrasp_mjx.workflows.frame_dataset import MAX_PAIRS, DatasetError, render_dataset
from regrasp_mjx.workflows.pixel_eyes import PixelLoopError
from regrasp_mjx.workflows.render import RenderUnavailable
from regrasp_mjx.world.endoscope import RESOLUTION, Rig
from regrasp_mjx.world.sampling import TestsetError

NO_CAMERA = "none"  # loop --camera: no error sizes known (the loop never looks)
DEFAULT_CAMERA = "rendered"  # loop --camera with a learned estimator: the preset fitted to its errors


def _widths(text: str) -> tuple[int, ...]:
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        widths = ()
    if len(widths) != 4 or min(widths) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: accepted four positive channel counts, such as 24,48,64,96")
    return widths


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: accepted a positive integer")
    return value


def _heldout(text: str) -> tuple[int, int]:
    try:
        n, seed = (int(x) for x in text.split(":"))
    except ValueError:
        n = seed = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: accepted N:SEED, N >= 1 problems drawn from the integer SEED")
    return n, seed


def _camera(text: str) -> str:
    """A camera preset's name, ``none``, or a fit file (``.json``)."""
    if text in (*PRESETS, NO_CAMERA) or text.endswith(".json"):
        return text
    raise argparse.ArgumentTypeError(f"{text!r} is not accepted: one of {(*PRESETS, NO_CAMERA)} or a fit file (.json)")


def _shard(text: str) -> tuple[int, int]:
    """``I/N``: shard I of N (0 <= I < N)."""
    try:
        i, n = (int(x) for x in text.split("/"))
        if 0 <= i < n:
            return i, n
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"{text!r} is not accepted: I/N with 0 <= I < N, e.g. 0/4")


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="python -m regrasp_mjx.estimator",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = top.add_subparsers(dest="command", required=True, metavar="{render,train,evaluate,fit,bench,loop}")
    r = sub.add_parser("render", help="render labelled stereo frames to an npz")
    r.add_argument("--out", required=True, help="output .npz (written atomically; chunks in OUT.parts/ until done)")
    r.add_argument("--episodes", type=_positive, required=True, help="episodes (problems, each its own randomisation)")
    r.add_argument(
        "--frames", type=_positive, default=8, help="frames per episode (default 8; the tool moves start to goal)"
    )
    r.add_argument("--seed", type=int, default=0, help="the problems' and randomisation's seed (default 0)")
    r.add_argument("--width", type=int, default=RESOLUTION[0], help=f"image width in pixels (default {RESOLUTION[0]})")
    r.add_argument(
        "--height", type=int, default=RESOLUTION[1], help=f"image height in pixels (default {RESOLUTION[1]})"
    )
    r.add_argument("--task", choices=sorted(TASKS), default="paper", help="problem distribution (default paper)")
    r.add_argument(
        "--workers", type=_positive, default=1, help="rendering processes (default 1; one OpenGL context each)"
    )
    r.add_argument(
        "--jaw-open",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="the regrasping jaws open on the way: each episode draws an opening in [LO, HI] degrees and its "
        "second half of frames draws the jaws there (default: they stay at the scene's 20; the shipped default "
        "opens them to 40)",
    )
    t = sub.add_parser("train", help="train the estimator; resumes from OUT's checkpoint")
    t.add_argument("--data", required=True, help="training frames (an npz from render)")
    t.add_argument("--val", required=True, help="validation frames of another seed")
    t.add_argument("--out", required=True, help="run folder: checkpoint.npz, log.jsonl, estimator/")
    t.add_argument("--epochs", type=_positive, default=Settings.epochs, help=f"epochs (default {Settings.epochs})")
    t.add_argument(
        "--batch", type=_positive, default=Settings.batch, help=f"stereo pairs per update (default {Settings.batch})"
    )
    t.add_argument(
        "--lr",
        type=float,
        default=Settings.learning_rate,
        help=f"peak learning rate (default {Settings.learning_rate})",
    )
    t.add_argument(
        "--widths",
        type=_widths,
        default=WIDTHS,
        help=f"channels at strides 2,4,8,16 (default {','.join(map(str, WIDTHS))})",
    )
    t.add_argument("--seed", type=int, default=0, help="initial weights and epoch order (default 0)")
    t.add_argument("--quiet", action="store_true", help="no progress lines")
    e = sub.add_parser("evaluate", help="pose errors on held-out frames")
    e.add_argument("--estimator", required=True, help="an estimator folder (train's OUT/estimator)")
    e.add_argument("--data", required=True, help="held-out frames (an npz from render, another seed)")
    e.add_argument("--out", help="folder for estimator_errors.json and .md (default: print only)")
    e.add_argument("--batch", type=_positive, default=64, help="stereo pairs per call (default 64)")
    f = sub.add_parser("fit", help="the camera-error model fitted to evaluate's per-frame errors")
    f.add_argument(
        "--errors", required=True, help=f"evaluate's --out folder (its {error_fit.FRAMES_FILE}), or that file"
    )
    f.add_argument(
        "--out",
        required=True,
        help="the fit file (.json, strict; the rendered preset's: regrasp_mjx/data/camera_rendered.json)",
    )
    f.add_argument(
        "--motion-frames",
        type=float,
        default=error_fit.MOTION_FRAMES,
        help="the closed loop's frames from start to goal, which an episode's frames span "
        f"(default {error_fit.MOTION_FRAMES:g})",
    )
    f.add_argument("--max-lag", type=_positive, help="the variogram's largest lag in frames (default: all, frames - 1)")
    f.add_argument(
        "--bootstrap",
        type=int,
        default=error_fit.BOOTSTRAP,
        help=f"resamples of the episodes for the sizes' 90 %% intervals (default {error_fit.BOOTSTRAP}; 0: none)",
    )
    b = sub.add_parser("bench", help="milliseconds per stereo pair on the default device")
    b.add_argument("--estimator", required=True, help="an estimator folder")
    b.add_argument("--repeats", type=_positive, default=50, help="timed calls (default 50)")
    b.add_argument("--batch", type=_positive, default=1, help="stereo pairs per call (default 1)")
    lp = sub.add_parser("loop", help="the closed loop from pixels, judged on the true poses")
    lp.add_argument(
        "--estimator", required=True, help="an estimator folder, or 'oracle' (keypoints from the true poses)"
    )
    lp.add_argument("--policy", default="default", help="a shipped policy's name or a policy folder (default: default)")
    lp.add_argument("--out", required=True, help="folder for pixel_loop.json, .md and pixel_loop_rows.npz")
    lp.add_argument("--testset", default="paper300", help="a shipped test set's name or an .npz (default paper300)")
    lp.add_argument("--heldout", type=_heldout, metavar="N:SEED", help="N problems drawn from SEED instead")
    lp.add_argument("--n", type=_positive, help="only the first N problems")
    lp.add_argument(
        "--seed", type=int, default=0, help="the episodes' randomisation and the oracle's noise (default 0)"
    )
    lp.add_argument("--batch", type=_positive, default=32, help="problems run side by side (default 32)")
    lp.add_argument("--width", type=int, help=f"the oracle's image width (default {RESOLUTION[0]})")
    lp.add_argument("--height", type=int, help=f"the oracle's image height (default {RESOLUTION[1]})")
    lp.add_argument("--noise-px", type=float, default=0.0, help="the oracle's pixel noise, sd (default 0)")
    lp.add_argument("--no-render", action="store_true", help="the oracle without images (it reads the true poses)")
    lp.add_argument(
        "--camera",
        type=_camera,
        metavar="{" + ",".join((*PRESETS, NO_CAMERA)) + "} or FIT.json",
        help="the camera's known error sizes by name (or a fit file `estimator fit` wrote), which the loop looks by before its last moves and keeps the "
        "jaws' margin by (a policy's closed_loop look_frames; docs/inference.md); none: no error known, it never "
        "looks. Default: rendered with a learned estimator (fitted to the learned estimator's own errors on "
        "held-out rendered frames, regrasp_mjx/data/camera_rendered.json: refit it for an estimator of your own), "
        "none with the oracle (its errors are --noise-px's, which no preset describes)",
    )
    lp.add_argument(
        "--shard",
        type=_shard,
        metavar="I/N",
        help="run only every N-th batch from the I-th (N processes side by side, e.g. 0/4 .. 3/4: the renderer "
        "draws one picture at a time), then the same command without --shard writes the report",
    )
    lp.add_argument("--quiet", action="store_true", help="no progress lines")
    lines = ["options of each subcommand:"]
    for name, p in sub.choices.items():
        opts = [a.option_strings[0] for a in p._actions if a.option_strings and a.option_strings[0] != "-h"]
        lines.append(f"  {name}: {' '.join(opts)}")
    top.epilog = "\n".join(lines)
    return top


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    settings = None
    if args.command == "render":
        problem = output_file_problem(args.out, ".npz")
        if problem or args.episodes * args.frames > MAX_PAIRS:
            p.error(
                problem or f"--episodes x --frames is {args.episodes * args.frames}: accepted at most {MAX_PAIRS} pairs"
            )
        try:
            Rig(width=args.width, height=args.height)
        except ValueError as err:
            p.error(f"--width {args.width} --height {args.height}: {err}")
    elif args.command == "loop":
        oracle = args.estimator == pixel_report.ORACLE
        problem = output_folder_problem(args.out)
        if not problem and not oracle and (args.noise_px or args.no_render or args.width or args.height):
            problem = (
                "--noise-px, --no-render, --width and --height are the oracle's: accepted only with --estimator "
                "oracle (a learned estimator renders at the size it was trained at)"
            )
        args.width, args.height = args.width or RESOLUTION[0], args.height or RESOLUTION[1]
        if not problem and not (0.0 <= args.noise_px <= 100.0):
            problem = f"--noise-px {args.noise_px}: accepted pixels in [0, 100]"
        if problem:
            p.error(problem)
        try:
            Rig(width=args.width, height=args.height)
        except ValueError as err:
            p.error(f"--width {args.width} --height {args.height}: {err}")
        if args.camera is None:
            args.camera = NO_CAMERA if oracle else DEFAULT_CAMERA
        if args.camera != NO_CAMERA:  # a fitted preset's file read now: a missing one says how to make it
            try:
                camera_presets.named(args.camera)
            except ConfigError as err:
                p.error(f"--camera {args.camera}: {err}")
    elif args.command in ("train", "evaluate") and args.out is not None:
        problem = output_folder_problem(args.out)
        if problem:
            p.error(problem)
    elif args.command == "fit":
        problem = output_file_problem(args.out, ".json")
        if not problem and not (0.0 < args.motion_frames <= 1000.0):
            problem = f"--motion-frames {args.motion_frames}: accepted a number of frames in (0, 1000]"
        if not problem and not (0 <= args.bootstrap <= 10_000):
            problem = f"--bootstrap {args.bootstrap}: accepted an integer in [0, 10000]"
        if problem:
            p.error(problem)
    if args.command == "train":
        try:
            settings = Settings(args.epochs, args.batch, args.lr, widths=args.widths, seed=args.seed)
        except ValueError as err:
            p.error(str(err))
    try:
        if args.command == "render":
            path = render_dataset(
                args.out,
                args.episodes,
                args.frames,
                args.seed,
                args.width,
                args.height,
                args.task,
                args.workers,
                jaw_open=args.jaw_open,
            )
            print(dumps({"out": str(path), "pairs": args.episodes * args.frames, "seed": args.seed}))
        elif args.command == "train":
            deterministic_gpu()  # before JAX starts its backend: the same seed, the same numbers on a GPU
            log = (lambda *_: None) if args.quiet else (lambda line: print(line, flush=True))
            print(dumps(train(args.data, args.val, args.out, settings, log=log)))
        elif args.command == "evaluate":
            rep = estimator_report.evaluate(args.estimator, args.data, args.out, args.batch)
            print(dumps(estimator_report.headline(rep)))
        elif args.command == "fit":
            errors = error_fit.load_frame_errors(args.errors)
            result = error_fit.fit(errors, args.motion_frames, args.max_lag, args.bootstrap, source=args.errors)
            write_json(args.out, result)
            print("\n".join(error_fit.markdown(result)))
            print(dumps({"out": args.out, "preset": result["preset"]}))
        elif args.command == "bench":
            print(dumps(estimator_report.bench(args.estimator, args.repeats, args.batch)))
        else:
            loop_args = pixel_report.LoopArgs(
                args.policy,
                args.estimator,
                None if args.heldout else args.testset,
                args.heldout,
                args.n,
                args.seed,
                args.batch,
                args.width,
                args.height,
                args.noise_px,
                not args.no_render,
                None if args.camera == NO_CAMERA else args.camera,
            )
            log = (lambda *_: None) if args.quiet else (lambda line: print(line, flush=True))
            shard = args.shard or (0, 1)
            rep = pixel_report.run(loop_args, args.out, load_policy(args.policy), log=log, shard=shard)
            if rep is None:
                print(dumps({"out": args.out, "shard": list(shard), "done": True}))
                return 0
            s = rep["summary"]
            rates = ("success_rate", "collision_rate", "time_out_rate", "stopped_short_rate")
            needle = s["estimate_per_frame"]["needle_in_e_g"]
            print(
                dumps(
                    {
                        "out": args.out,
                        "problems": rep["problems"],
                        "camera": args.camera,
                        **{k: s[k] for k in rates},
                        "needle_in_e_g": needle,
                    }
                )
            )
    except (
        DatasetError,
        EstimatorError,
        CheckpointError,
        FolderInUse,
        RenderUnavailable,
        PixelLoopError,
        OracleError,
        FitError,
        PolicyError,
        TestsetError,
        ConfigError,
    ) as err:
        print(f"python -m regrasp_mjx.estimator {args.command}: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "run the same command again: render, train and loop go on from where they stopped"))
