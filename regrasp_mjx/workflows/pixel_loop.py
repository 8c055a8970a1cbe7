"""The closed loop from pixels (issue 68, step 5): each step the endoscope's stereo pair is rendered at the
true poses, an estimator turns it into the needle's and both tools' poses in the camera's frame,
:class:`~regrasp_mjx.inference.camera_loop.CameraLoop` fuses them and takes the policy's step, and the
commanded motion moves the true regrasping tool; success and collision are judged on the true poses.

    from regrasp_mjx.workflows.pixel_loop import execute_from_pixels
    out = execute_from_pixels(policy, estimator, needle, start, goal, seed=0)  # [B, 7] true poses in e_g
    out["success"], out["collision"], out["steps"], out["frames"], out["estimate_error_mm"]

``estimator``: a learned one (:func:`regrasp_mjx.vision.estimator_file.load_estimator`, which sees the
rendered images) or the oracle (:class:`regrasp_mjx.vision.oracle.OracleEstimator`, keypoints projected
from the true poses, then the same fit; it needs no images, so ``render=False`` skips drawing them).

Each problem is one episode of the endoscope's domain randomisation (its draw seeded by the loop's
``seed`` and the problem's row: :func:`episode_seeds`): the rig's pose jitter, lights, materials and
the image's blur and gain fixed per episode, the image noise drawn anew each frame. The loop takes the
policy's own closed-loop settings (``Policy.closed_loop_defaults``: the warm-up frames fused before the
first step, the stop tolerance, the frames a look may take; the fused view is :class:`CameraLoop`'s).
Looking (holding still to fuse more frames before the last moves while the fused view is too uncertain)
and the jaws' margin are decided by the camera's known error sizes, which the loop cannot read off its
estimator: the caller names them (``camera``: a :class:`~regrasp_mjx.envs.camera_errors.CameraErrors`
or a preset's name, such as ``rendered``, fitted to the learned estimator's errors); without them the
loop knows of no error, as :class:`CameraLoop` and ``Policy.execute`` without errors, so it never looks
(a warning says so where the policy would). A policy whose jaws open on the way opens them as
:class:`CameraLoop` commands, and the judge carries the opening out (its sweep proved on the true poses,
the motions tested with the jaws where they are). The frames draw each row's regrasping jaws where its
loop last commanded them (:meth:`FrameRenderer.render`'s ``jaw_deg``: the scene's opening until they open),
what the robot holds, and the estimator's fit is told that opening (its jaw tips' model points turned
there); a learned estimator whose training frames never drew the jaws that open gets a warning.
The oracle reads the true poses (its keypoints the estimator's model's, the jaw tips turned to the
opening drawn).

The judge is the environment's: each commanded motion is carried out on the true state by
:meth:`regrasp_mjx.envs.env.RegraspEnv.move` (the continuous collision test along the whole motion,
against the true needle and grasping tool), the rows a stop ends are judged at the goal by
:func:`regrasp_mjx.inference.closed_loop._at_goal` on the true needle (the success tolerances), and
the rows are ended as :func:`regrasp_mjx.envs.rollout.rollout` ends them under a stopping rule (the
simulated closed loop's, ``Policy.execute``): a stop before the step at ``t`` (a success where the
true poses are at the goal), a collision after a step, a time-out when no stop came by the horizon.

A frame the loop refuses (an estimate that is not a pose, or a needle that jumped:
:meth:`CameraLoop.update` raises ``PoseError``) is left out and the next frame taken at once, the tool
holding still; after :data:`MAX_REFUSED` refused frames in a row the tool holds still for a step.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.host_loop import eta
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.inference.closed_loop import _at_goal  # the simulated loop's judge of a stop, on the truth
from regrasp_mjx.inference.plans import checked_goals
from regrasp_mjx.inference.queries import PoseError, TaskSpec, batch_poses
from regrasp_mjx.vision.estimator_file import Estimator
from regrasp_mjx.vision.oracle import OracleEstimator
from regrasp_mjx.vision.pose_errors import rotvec
from regrasp_mjx.workflows.frames import FrameRenderer
from regrasp_mjx.workflows.pixel_eyes import (
    ERROR_COLUMNS,
    Eyes,
    PixelLoopError,
    episode_seeds,
    frame_errors,
    matrices,
    rig_of,
)
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.sampling import Episode

MAX_REFUSED = 30  # refused frames in a row after which the tool holds still for a step (1 s at 30 fps)
PROGRESS_STEPS = 10  # a progress line every this many steps of a batch


def _judge(policy: Any) -> Callable:
    """The environment's judge of the true state, jitted once per environment (the policy's program
    cache): ``("reset", needle, start, goal)`` the batch's true states; ``("at_goal", state, needle)``
    whether each is at its goal on the true needle; ``("move", state, dp, rotvec, live, jaw_deg)`` the
    live rows moved by ``dp`` [m] and ``rotvec`` [rad] (e_g) with :meth:`RegraspEnv.move` (the others
    held), the jaws first opened to ``jaw_deg`` [deg] where it is wider than they are (a sweep the true
    poses do not prove clear is a collision), and whether each collided. A policy whose jaws stay takes
    ``jaw_deg`` None: the environment's own step."""

    def build():
        env = RegraspEnv(policy.env_config)
        reset = jax.jit(lambda n, s, g: jax.vmap(env.reset_from)(Episode.from_poses(n, s, g)))
        at_goal = jax.jit(lambda state, needle: _at_goal(env, state, needle))

        @jax.jit
        def move(state, dp, rv, live, jaw_deg=None):
            # the loop's opening (the environment's own rule would decide on the truth, not on the view)
            opening = () if jaw_deg is None else (jaw_deg,)
            nxt = jax.vmap(env.move)(state, dp, rv, *opening)
            held = jax.tree.map(lambda x, y: jnp.where(live.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), nxt, state)
            return held, live & (nxt.metrics["collision"] > 0)

        ops = {"reset": reset, "at_goal": at_goal, "move": move}
        return lambda _weights, op, *args: ops[op](*args)

    return policy.program(("pixel_loop_judge",), build)


def _check(policy: Any, needle: Any, start: Any, goal: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        (needle, start), _ = batch_poses(needle=needle, start=start)
    except ValueError as err:
        raise PixelLoopError(str(err)) from None
    grasp, radii = policy.task_ranges.resolve(len(needle), TaskSpec.of({}))
    return needle, start, checked_goals(needle, goal, grasp, radii)


def _motion_in_eg(ee: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The translation ``[n, 3]`` (m) and rotation vector ``[n, 3]`` (rad), in e_g, that carry tools at
    ``ee`` ``[n, 7]`` by tool-frame motions ``[n, 4, 4]`` (``ee @ motion``), as :meth:`RegraspEnv.move`
    takes them (the rotation applied on the left: ``R_ee R_m R_ee^T``)."""
    rot = endoscope.quat_matrix(ee[:, 3:])
    dp = np.einsum("nij,nj->ni", rot, motion[:, :3, 3])
    return dp, rotvec(rot @ motion[:, :3, :3] @ np.swapaxes(rot, -1, -2))


class _Batch:
    """One batch of rows through the loop (see :func:`execute_from_pixels`)."""

    def __init__(self, policy, eyes: Eyes, problems, settings: dict, judge, log, label, real: int):
        self.policy, self.eyes, self.judge, self.log, self.label = policy, eyes, judge, log, label
        self.needle, self.start, self.goal = problems  # the first `real` rows; the rest pad the batch
        self.real = real
        b = len(self.needle)
        inv = endoscope.invert(matrices(self.needle))
        self.loops = [policy.camera_loop(goal_in_needle=inv[i] @ matrices(self.goal[i]), **settings) for i in range(b)]
        self.refused = np.zeros(b, np.int32)
        self.seen: list[list] = [[] for _ in range(b)]  # each frame's errors (mm, deg)
        self.view = np.full((b, 2), np.nan)  # the fused view's position errors at the last decision

    def decide(self, ee: np.ndarray, live: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames of the ``live`` rows (tools truly at ``ee`` ``[B, 7]``) until each has a decision (a frame
        a look holds still for is taken like a warm-up frame: the next one at once): which stop (the view
        says the goal is reached) and the others' tool-frame motions ``[B, 4, 4]``; the jaws' opening each
        row commands before its motion in :attr:`jaw_deg`."""
        b = len(ee)
        need, tries = live.copy(), np.zeros(b, np.int64)
        stopping, motion = np.zeros(b, bool), np.tile(np.eye(4), (b, 1, 1))
        self.jaw_deg = np.array([loop.jaw_deg for loop in self.loops])  # the opening each row commands
        # the frames draw each row's jaws where its loop last commanded them (carried out by the judge before
        # that motion: the true jaws); a policy whose jaws stay, at the scene's opening
        drawn = self.jaw_deg.copy() if self.policy.env_config.jaw_open_deg is not None else None
        g_true = matrices(ee)
        while need.any():
            rows = np.nonzero(need)[0]
            est, truth = self.eyes.look(rows, ee[rows], None if drawn is None else drawn[rows])
            mm, deg = frame_errors(est["poses"], truth)
            for j, i in enumerate(rows):
                self.seen[i].append((mm[j], deg[j]))
                p = est["poses"][j]
                try:
                    command = self.loops[i].update(p[1], p[2], p[0])
                except PoseError:
                    self.refused[i] += 1
                    tries[i] += 1
                    need[i] = tries[i] < MAX_REFUSED  # else it holds still for this step
                    continue
                tries[i] = 0
                if not command.ready:
                    continue
                need[i] = False
                stopping[i], motion[i], self.jaw_deg[i] = command.at_goal, command.motion, command.jaw_deg
                truth_n = matrices(self.needle[i])
                self.view[i] = (
                    np.linalg.norm(command.needle[:3] - truth_n[:3, 3]) * 1e3,
                    np.linalg.norm(command.ee[:3] - g_true[i, :3, 3]) * 1e3,
                )
        return stopping, motion

    def run(self, horizon: int, t0: float) -> dict[str, np.ndarray]:
        """The batch's rows to their ends, judged on the truth (as :func:`rollout` under a stopping rule)."""
        f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
        b, judge, needle = len(self.needle), self.judge, f32(self.needle)
        state = judge("reset", needle, f32(self.start), f32(self.goal))
        valid = np.asarray(state.metrics["reset_valid"]) > 0
        collision = ~valid  # a start that collides: a collision after 0 steps
        ended = ~valid | (np.arange(b) >= self.real)  # the rows that pad the batch end before they begin
        success, time_out, stopped = (np.zeros(b, bool) for _ in range(3))
        steps = np.zeros(b, np.int32)
        poses = np.repeat(self.start[:, None], horizon + 1, axis=1)
        for t in range(horizon + 1):
            live = ~ended
            if not live.any():
                break
            es = state.pipeline_state
            ee = np.concatenate([np.asarray(es.ee_pos, np.float64), np.asarray(es.ee_quat, np.float64)], -1)
            ee[:, 3:] /= np.linalg.norm(ee[:, 3:], axis=-1, keepdims=True)
            stopping, motion = self.decide(ee, live)
            stopping &= live
            success |= stopping & np.asarray(judge("at_goal", state, needle))
            stopped |= stopping
            late = live & ~stopping & (t >= horizon)
            time_out |= late
            ended |= stopping | late
            live = ~ended
            if t >= horizon or not live.any():
                break
            dp, rv = _motion_in_eg(ee, motion)
            jaws = (f32(self.jaw_deg),) if self.policy.env_config.jaw_open_deg is not None else ()
            state, hit = judge("move", state, f32(dp * live[:, None]), f32(rv * live[:, None]), live, *jaws)
            hit = np.asarray(hit)
            collision |= hit
            ended |= hit
            steps += live
            es = state.pipeline_state
            poses[live, t + 1 :] = np.concatenate([np.asarray(es.ee_pos), np.asarray(es.ee_quat)], -1)[live, None]
            if (t + 1) % PROGRESS_STEPS == 0:
                seconds = time.perf_counter() - t0
                self.log(
                    f"  {self.label} step {t + 1}: {int((~ended).sum())} of {self.real} rows live, "
                    f"{self.eyes.pairs} stereo pairs ({self.eyes.pairs / seconds:.1f}/s)"
                )
        frames = np.array([len(s) for s in self.seen], np.int32)
        errors = np.full((b, max(frames.max(initial=0), 1), 2, len(ERROR_COLUMNS)), np.nan)
        for i, s in enumerate(self.seen):
            if s:
                errors[i, : len(s)] = np.stack([np.stack(pair) for pair in s])
        out = {
            "success": success,
            "collision": collision,
            "time_out": time_out,
            "stopped": stopped,
            "start_valid": valid,
            "steps": steps,
            "frames": frames,
            "refused": self.refused,
            "looked": np.array([loop.looked for loop in self.loops], np.int32),
            "jaw_deg": np.array([loop.jaw_deg for loop in self.loops], np.float32),
            "opened_at": np.array([loop.opened_at for loop in self.loops], np.int32),
            "view_error_mm": self.view,
            "estimate_error_mm": errors[:, :, 0],
            "estimate_error_deg": errors[:, :, 1],
            "poses": poses,
        }
        return {k: v[: self.real] for k, v in out.items()}


def _padded(x: np.ndarray, size: int) -> np.ndarray:
    """``x`` ``[m, ...]`` with copies of its last row to ``size`` rows."""
    return np.concatenate([x, np.repeat(x[-1:], size - len(x), 0)])


def _joined(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Batches' outputs joined row-wise; the per-frame errors padded with NaN to the longest."""
    longest = max(p["estimate_error_mm"].shape[1] for p in parts)
    out = {}
    for k in parts[0]:
        if k.startswith("estimate_error"):
            pad = lambda x: np.pad(x, ((0, 0), (0, longest - x.shape[1]), (0, 0)), constant_values=np.nan)  # noqa: E731
            out[k] = np.concatenate([pad(p[k]) for p in parts])
        else:
            out[k] = np.concatenate([p[k] for p in parts])
    return out


def execute_from_pixels(
    policy: Any,
    estimator: Estimator | OracleEstimator,
    needle: Any,
    start: Any,
    goal: Any = None,
    seed: int = 0,
    batch: int = 32,
    render: bool = True,
    renderer: FrameRenderer | None = None,
    log: Callable[[str], None] | None = None,
    seeds: Any = None,
    warmup_frames: int | None = None,
    stop_tolerance: float | None = None,
    look_frames: int | None = None,
    camera: Any = None,
) -> dict[str, np.ndarray]:
    """The closed loop from pixels (see the module docstring) on true needle, start and goal poses
    ``[B, 7]`` (e_g; ``goal`` None: the task's goal grasp on each needle), ``batch`` rows at a time
    (the last batch padded to as many: one compiled program for every batch; a few problems run best
    with ``batch`` no larger than their number).

    Args:
      policy: a loaded policy (its own closed-loop settings, jaws that open on the way carried).
      estimator: a loaded :class:`~regrasp_mjx.vision.estimator_file.Estimator` or an
        :class:`~regrasp_mjx.vision.oracle.OracleEstimator`.
      seed: the episodes' randomisation draws (:func:`episode_seeds`) and so each frame's image noise.
      render: False draws no images (the oracle only: it reads the true poses).
      renderer: a :class:`~regrasp_mjx.workflows.frames.FrameRenderer` of the estimator's rig to use
        (None: one is made, and closed at the end).
      log: progress lines (None: none).
      seeds: each problem's randomisation seed ``[B]`` (None: :func:`episode_seeds` of ``seed``), so
        that a part of a set of problems sees what it would see in the whole.
      warmup_frames, stop_tolerance, look_frames: :class:`CameraLoop`'s (None: the policy's own).
      camera: the camera's known error sizes the loop looks by and keeps the jaws' margin by
        (:class:`CameraLoop`'s: a :class:`~regrasp_mjx.envs.camera_errors.CameraErrors` or a preset's
        name); None: none known, so it never looks (a warning where the policy would).

    Returns:
      numpy arrays per row: ``success`` (stopped at the true goal, no collision), ``collision`` (on
      the true poses, along every motion and the jaws' opening), ``time_out``, ``stopped`` (the view
      said the goal was reached), ``start_valid``, ``steps``, ``frames`` (every frame taken: the
      warm-up, one a step, the looked, the refused), ``refused``, ``looked``, ``jaw_deg`` (the jaws'
      last opening), ``opened_at`` (the step they opened before, -1: never), ``view_error_mm`` ``[B, 2]`` (the fused needle and regrasping tool in
      the seen e_g against the truth at the last decision), ``estimate_error_mm`` and
      ``estimate_error_deg`` ``[B, F, 5]`` (each frame's estimate against the truth:
      :data:`ERROR_COLUMNS`; NaN past a row's frames or where the fit gave no pose), ``poses``
      ``[B, horizon + 1, 7]`` (the true regrasping tool, held after its end) and ``seeds``.

    Raises:
      PixelLoopError: a policy, estimator or settings the loop cannot run.
      RenderUnavailable: no OpenGL context can be made here (with ``render``).
    """
    needle, start, goal = _check(policy, needle, start, goal)
    rig = rig_of(estimator)
    if not render and not isinstance(estimator, OracleEstimator):
        raise PixelLoopError("render=False is not accepted with a learned estimator: it sees the images")
    if not (isinstance(batch, int) and batch >= 1):
        raise PixelLoopError(f"batch={batch!r} is not accepted: a positive number of rows")
    if renderer is not None and renderer.rig != rig:
        raise PixelLoopError(f"the renderer's rig {renderer.rig} is not the estimator's {rig}")
    log = log or (lambda _line: None)
    n, horizon = len(needle), policy.env_config.horizon
    seeds = episode_seeds(n, seed) if seeds is None else np.asarray(seeds)
    if seeds.shape != (n,) or seeds.dtype.kind not in "iu" or (seeds < 0).any():
        raise PixelLoopError(f"seeds of shape {seeds.shape} are not accepted: one integer >= 0 per problem ({n})")
    settings = {
        "warmup_frames": warmup_frames,
        "stop_tolerance": stop_tolerance,
        "look_frames": look_frames,
        "camera": camera,
    }
    try:
        loop = policy.camera_loop(**settings)
    except ValueError as err:
        raise PixelLoopError(str(err)) from None
    # No error sizes named: the loop knows of none and does not look, as CameraLoop and Policy.execute do
    # without errors (refusing instead would leave the `loop` command, which names none, and every caller of
    # a policy that looks, the shipped default among them, unable to run it). Said, not silent:
    if loop.look and camera is None:
        warnings.warn(
            f"this policy looks before its last moves (look_frames {loop.look}) by the camera's known error "
            "sizes, and none were named: the loop from pixels will not look; pass camera= (a CameraErrors or a "
            "preset's name, e.g. 'rendered', fitted to the estimator's errors) to look by them",
            stacklevel=2,
        )
    if loop.open_deg is not None and isinstance(estimator, Estimator):
        lo, hi = estimator.trained_jaw_deg
        if not lo <= loop.open_deg <= hi:
            warnings.warn(
                f"this policy opens its jaws on the way (to {loop.open_deg:g} deg), and this estimator's training "
                f"frames drew them at {lo:g}-{hi:g} deg: its fit is told the opening, but its network never saw "
                "jaws like these, so its errors with them open are not the ones it was measured at (render its "
                "frames with `estimator render --jaw-open LO HI`)",
                stacklevel=2,
            )
    judge = _judge(policy)
    own = render and renderer is None
    renderer = FrameRenderer(rig=rig) if own else (renderer if render else None)
    parts, t0 = [], time.perf_counter()
    try:
        for a in range(0, n, batch):
            rows = slice(a, min(a + batch, n))
            real = rows.stop - a
            # every batch padded to `batch` rows (copies of its last, ended before they begin): one compiled
            # judge and estimator for every batch
            needle_b, start_b, goal_b, seeds_b = (_padded(x[rows], batch) for x in (needle, start, goal, seeds))
            eyes = Eyes(estimator, rig, renderer, seeds_b, needle_b, batch)
            label = f"rows {a}-{rows.stop - 1} of {n}"
            problems = (needle_b, start_b, goal_b)
            part = _Batch(policy, eyes, problems, settings, judge, log, label, real).run(horizon, t0)
            parts.append(part)
            if n > batch:  # a line a batch
                done, seconds = rows.stop, time.perf_counter() - t0
                won = sum(int(p["success"].sum()) for p in parts)
                log(f"pixels: {done} of {n} problems, success {won}/{done}, {seconds:.0f} s, {eta(done, n, seconds)}")
    finally:
        if own:
            renderer.close()
    return _joined(parts) | {"seeds": seeds}
