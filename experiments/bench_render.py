"""Labelled stereo frames per second: ``--n`` episode states of paper300 (repeated as needed) rendered as
one batch, ``--repeats`` times after a first, untimed batch (contexts, compiles, caches), by MuJoCo's
OpenGL renderer (``--backend mujoco``: one picture at a time; EGL on a GPU machine with
``MUJOCO_GL=egl``) or by MJX's batched MuJoCo Warp ray tracer (``--backend mjx``: one world per
state, one jitted program; needs ``pip install -e ".[render-gpu]"`` and, to be fast, a CUDA GPU). A
stereo pair is both cameras' RGB, depth and segmentation of one state, with its labels (poses, cameras,
keypoints, visibility) and its randomisation (draws, blur, gain, noise).

    python experiments/bench_render.py --backend mjx --n 4096 --width 320 --height 180

Prints the machine, the settings, the first batch's seconds and the stereo pairs per second (median
and best of the timed batches), then the same as one JSON line.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import numpy as np

from regrasp_mjx.workflows.frames import FrameRenderer
from regrasp_mjx.workflows.frames_mjx import MjxFrameRenderer
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world.endoscope import Rig
from regrasp_mjx.world.sampling import PAPER300, episode_poses, load_testset


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--backend", choices=("mujoco", "mjx"), default="mujoco", help="renderer (default mujoco)")
    p.add_argument("--n", type=int, default=64, help="episode states per batch (default 64)")
    p.add_argument("--width", type=int, default=Rig().width, help="image width in pixels (default 320)")
    p.add_argument("--height", type=int, default=Rig().height, help="image height in pixels (default 180)")
    p.add_argument("--repeats", type=int, default=5, help="timed batches after the first (default 5)")
    p.add_argument("--seed", type=int, default=0, help="the first state's randomisation seed (default 0)")
    p.add_argument(
        "--on-device",
        action="store_true",
        help="mjx only: time the pictures left on the device (no copy to the host, no labels): what a training "
        "step that reads frames where they are drawn pays",
    )
    p.add_argument(
        "--degrade-only",
        action="store_true",
        help="time only the image's blur, gain and noise (domain_randomisation.degrade) on random images of the "
        "batch's shape, on the default device: the part of --on-device that is not the ray tracer",
    )
    args = p.parse_args(argv)
    if args.n < 1 or args.repeats < 1:
        p.error("--n and --repeats must be >= 1")
    rig = Rig(width=args.width, height=args.height)
    needle, start, _ = (np.asarray(x) for x in episode_poses(load_testset(PAPER300)[0]))
    rows = np.arange(args.n) % len(needle)
    needle, start = needle[rows], start[rows]
    seeds = args.seed + np.arange(args.n)
    if args.degrade_only:
        return _degrade_only(args)
    if args.on_device and args.backend != "mjx":
        p.error("--on-device is mjx's: the OpenGL renderer draws on the host")
    renderer = MjxFrameRenderer(args.n, rig=rig, seed=args.seed) if args.backend == "mjx" else FrameRenderer(rig=rig)
    if args.on_device:  # the inputs made once: only the device's program is timed
        qpos = jax.device_put(np.stack([renderer.endo.qpos(n, e) for n, e in zip(needle, start)]).astype(np.float32))
        turn = jax.device_put(np.zeros(args.n, np.float32))

        def draw(frame):
            return jax.block_until_ready(renderer.pictures(qpos, turn, seeds, frame))
    else:

        def draw(frame):
            return renderer.render(needle, start, seeds, frame=frame)

    t0 = time.perf_counter()
    frames = draw(0)
    first = time.perf_counter() - t0
    times = []
    for frame in range(1, args.repeats + 1):
        t0 = time.perf_counter()
        frames = draw(frame)
        times.append(time.perf_counter() - t0)
    result = {
        "backend": args.backend,
        "n": args.n,
        "width": args.width,
        "height": args.height,
        "first_batch_s": round(first, 3),
        "pairs_per_s_median": round(args.n / float(np.median(times)), 1),
        "pairs_per_s_best": round(args.n / min(times), 1),
        "on_device": args.on_device,
        "visible_keypoints": None if args.on_device else round(float(frames.visible.mean()), 3),
        "device": str(jax.devices()[0]),
        "machine": platform.node(),
        "date": time.strftime("%Y-%m-%d"),
    }
    print(f"{args.backend} on {result['device']} ({result['machine']}), {args.width} x {args.height}, {args.n} states")
    print(
        f"first batch {first:.2f} s; {result['pairs_per_s_median']:.1f} stereo pairs/s (best {result['pairs_per_s_best']:.1f})"
    )
    print(json.dumps(result))
    return result


def _degrade_only(args) -> dict:
    """The seconds ``degrade`` takes on ``--n`` random stereo pairs (its draws from the seeds' own)."""
    seeds = args.seed + np.arange(args.n)
    d, keys = dr.draws(seeds), dr.noise_keys(seeds, 1)
    images = jax.random.randint(jax.random.key(0), (args.n, 2, args.height, args.width, 3), 0, 256).astype(np.uint8)
    jax.block_until_ready(dr.degrade(images, d.blur_px, d.noise, d.gain, keys))
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(dr.degrade(images, d.blur_px, d.noise, d.gain, keys))
        times.append(time.perf_counter() - t0)
    ms = 1e3 * float(np.median(times))
    result = {"degrade_only": True, "n": args.n, "width": args.width, "height": args.height, "ms_median": round(ms, 2)}
    result |= {
        "pairs_per_s": round(1e3 * args.n / ms, 1),
        "device": str(jax.devices()[0]),
        "date": time.strftime("%Y-%m-%d"),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
