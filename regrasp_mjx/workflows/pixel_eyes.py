"""What the loop from pixels sees (:mod:`regrasp_mjx.workflows.pixel_loop`): each problem's randomisation
seed, the stereo pair an estimator takes, one frame of a batch's rows rendered at the true poses (or, for
the oracle, only the cameras' poses: it needs no images) and estimated, and the estimate's errors against
the truth.
"""

from __future__ import annotations

import numpy as np

from regrasp_mjx.vision.estimator_file import Estimator
from regrasp_mjx.vision.oracle import OracleEstimator
from regrasp_mjx.vision.pose_errors import rotvec
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world import endoscope

# the estimate's error columns: each object in the left camera's frame, then what the policy sees
ERROR_COLUMNS = ("needle", "grasping_tool", "regrasping_tool", "needle_in_e_g", "regrasping_tool_in_e_g")


class PixelLoopError(ValueError):
    """Bad input to the loop from pixels: a policy, an estimator or problems it cannot run."""


def episode_seeds(n: int, seed: int) -> np.ndarray:
    """The randomisation seed of each of ``n`` problems ``[n]`` of a loop seeded by ``seed``."""
    return np.random.default_rng([int(seed), 68, 5]).integers(0, 2**31 - 1, size=int(n))


def rig_of(estimator: Estimator | OracleEstimator) -> endoscope.Rig:
    """The stereo pair the loop renders for ``estimator``: the oracle's own; for a learned one the
    default rig at the image size it was trained at, its cameras checked against the estimator's."""
    if isinstance(estimator, OracleEstimator):
        return estimator.rig
    if not isinstance(estimator, Estimator):
        raise PixelLoopError(
            f"estimator {type(estimator).__name__} is not accepted: a loaded Estimator (load_estimator) or an "
            "OracleEstimator"
        )
    rig = endoscope.Rig(width=estimator.net.width, height=estimator.net.height)
    baseline = float(estimator.contract["camera"]["baseline_m"])
    if not (np.allclose(rig.intrinsics(), estimator.fit.intrinsics) and np.isclose(baseline, rig.baseline_m)):
        raise PixelLoopError(
            "the estimator's cameras are not the endoscope's (its intrinsics or baseline differ from "
            f"Rig(width={rig.width}, height={rig.height})): it was trained on other frames"
        )
    return rig


def matrices(poses: np.ndarray) -> np.ndarray:
    """4x4s ``[..., 4, 4]`` of 7-vectors ``[..., 7]``."""
    out = np.zeros(poses.shape[:-1] + (4, 4))
    out[..., :3, :3], out[..., :3, 3], out[..., 3, 3] = endoscope.quat_matrix(poses[..., 3:]), poses[..., :3], 1.0
    return out


def frame_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (mm) and orientation (deg) errors ``[n, 5]`` (:data:`ERROR_COLUMNS`) of estimated
    camera-frame poses ``[n, 3, 7]`` against the true ones ``[n, 3, 4, 4]``; NaN where no pose."""
    with np.errstate(invalid="ignore"):
        est = matrices(np.asarray(estimate, np.float64))
        rel = lambda m: endoscope.invert(m[:, 1])[:, None] @ m[:, [0, 2]]  # noqa: E731
        est, truth = np.concatenate([est, rel(est)], 1), np.concatenate([truth, rel(truth)], 1)
        pos = np.linalg.norm(est[..., :3, 3] - truth[..., :3, 3], axis=-1) * 1e3
        turn = est[..., :3, :3] @ np.swapaxes(truth[..., :3, :3], -1, -2)
        ok = np.all(np.isfinite(turn), axis=(-2, -1))
        deg = np.full(pos.shape, np.nan)
        deg[ok] = np.degrees(np.linalg.norm(rotvec(turn[ok]), axis=-1))
    return np.where(ok, pos, np.nan), deg


class Eyes:
    """What the loop sees of a batch's rows: rendered (or, for the oracle, only labelled) stereo pairs at
    the true poses, each episode's randomisation draw, each row's next frame's number, and the estimate."""

    def __init__(self, estimator, rig, renderer, seeds, needle, size):
        self.estimator, self.rig, self.renderer, self.size = estimator, rig, renderer, size
        self.seeds, self.needle = seeds, needle
        d = dr.draws(seeds)
        self.extrinsics = endoscope.invert(
            endoscope.camera_poses(rig, np.asarray(d.camera_shift), np.asarray(d.camera_rotvec))
        )
        self.next_frame = np.zeros(len(seeds), np.int64)
        self.pairs = 0

    def look(
        self, rows: np.ndarray, ee: np.ndarray, jaw_deg: np.ndarray | None = None
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The estimate of one frame of each of ``rows`` (the regrasping tool truly at ``ee`` ``[n, 7]``,
        its jaws drawn opened to ``jaw_deg`` ``[n]`` degrees; None: the scene's opening) and the true
        camera-frame poses ``[n, 3, 4, 4]``; each row's frame count advanced."""
        poses = endoscope.object_poses(self.needle[rows], ee)
        extrinsics = self.extrinsics[rows]
        rgb = None
        if self.renderer is not None:  # one row a call: one compiled randomisation for any count of rows
            rgb = np.empty((len(rows), 2, self.rig.height, self.rig.width, 3), np.uint8)
            for j, i in enumerate(rows):  # the image noise's draw: the episode's seed and the row's frame
                jaw = None if jaw_deg is None else jaw_deg[j]
                fr = self.renderer.render(
                    self.needle[i], ee[j], self.seeds[i], frame=int(self.next_frame[i]), jaw_deg=jaw
                )
                rgb[j], extrinsics[j] = fr.rgb[0], fr.extrinsics[0]
        self.next_frame[rows] += 1
        self.pairs += len(rows)
        truth = extrinsics[:, 0, None] @ matrices(poses)
        pad = lambda x: np.concatenate([x, np.repeat(x[-1:], self.size - len(x), 0)])  # noqa: E731
        # padded to the batch's size: one compiled program for every count of rows
        # the fit told the jaws' opening the loop commanded (what the robot knows), as the frames draw it
        jaws = None if jaw_deg is None else pad(np.asarray(jaw_deg, np.float64))
        if isinstance(self.estimator, OracleEstimator):  # its noise keyed by the episode and the frame
            keys = np.stack([self.seeds[rows], self.next_frame[rows] - 1], -1)
            out = self.estimator.estimate(pad(poses), pad(extrinsics), pad(keys), jaw_deg=jaws)
        else:
            out = self.estimator.poses(pad(rgb), batch=self.size, jaw_deg=jaws)
        return {k: v[: len(rows)] for k, v in out.items()}, truth
