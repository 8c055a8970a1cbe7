"""The estimator's keypoints: the labelled frames' own (the needle's arc from tip to tail, each tool's jaw
pivot and jaw tips; :func:`regrasp_mjx.world.endoscope.keypoints`) and each tool's wrist pitch axis.

Why the wrist: the pivot and the two jaw tips of a tool lie within 10 mm of each other, so the jaw's
direction rests on points 10 mm apart; the wrist's axis point, 9.1 mm behind the pivot along the
tool's axis (the end of the wrist capsule, ``{tool}_wrist``), doubles that lever. It lies inside the
2 mm wrist, like the pivot: the network learns it from the wrist's outline. Nothing on a tool shows
its roll but the jaws, so the jaw tips stay the only roll cue.
"""

from __future__ import annotations

import numpy as np

from regrasp_mjx.core.config import JAW_MAX_DEG
from regrasp_mjx.vision.stereo import CAUCHY_PX, ITERATIONS, PoseFit, rectified
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.endoscope import OBJECTS, REGRASP_JAW_PREFIX, Keypoints
from regrasp_mjx.world.scene import Scene

TOOLS = (("grasp", 1, "grasp_capsules"), ("regrasp", 2, "regrasp_capsules"))
# the regrasping jaws' opening of every estimator file and frame dataset written before the jaws could open
# (they name none): the scene's of that time, a number of its own so that a later default scene does not
# reinterpret them
JAW_DEG_BEFORE_OPENING = 20.0


def layout(scene: Scene, n_arc: int = endoscope.N_ARC) -> Keypoints:
    """The estimator's keypoints of ``scene`` (its needle's radius, its tools' jaws at its opening)."""
    base = endoscope.keypoints(scene, n_arc)
    names, obj, local, slack = list(base.names), list(base.obj), list(base.local), list(base.depth_slack)
    for prefix, o, capsules in TOOLS:
        wrist = {c.name: c for c in getattr(scene, capsules)}[f"{prefix}_wrist"]
        far = max((wrist.p0, wrist.p1), key=np.linalg.norm)  # the pitch axis, behind the pivot
        names.append(f"{prefix}_wrist")
        obj.append(o)
        local.append(np.asarray(far, np.float64))
        slack.append(wrist.radius)
    return Keypoints(tuple(names), np.array(obj), np.stack(local), np.array(slack))


def object_rows(kp: Keypoints) -> tuple[tuple[int, ...], ...]:
    """The keypoints' indices of each object of :data:`~regrasp_mjx.world.endoscope.OBJECTS`."""
    return tuple(tuple(int(i) for i in np.nonzero(kp.obj == o)[0]) for o in range(len(OBJECTS)))


def jaw_tips(kp: Keypoints) -> tuple[int, ...]:
    """The indices of the keypoints fixed on the regrasping jaws (they turn as the jaws open)."""
    return tuple(i for i, n in enumerate(kp.names) if n.startswith(REGRASP_JAW_PREFIX))


def jaw_turns(jaw_deg, n: int, layout_deg: float) -> np.ndarray:
    """``[n]`` turns (rad) of the jaw tips beyond a layout made at ``layout_deg`` for openings ``jaw_deg``
    (None: the layout's; one number or ``[n]``, degrees in (0, JAW_MAX_DEG]): half the opening's change,
    as the environment turns each jaw. ``ValueError`` says what is wrong with others."""
    if jaw_deg is None:
        return np.zeros(n)
    try:
        deg = np.broadcast_to(np.asarray(jaw_deg, np.float64), (n,))
    except (TypeError, ValueError):
        raise ValueError(
            f"jaw_deg of shape {np.shape(jaw_deg)} is not accepted: one opening or one per row ({n})"
        ) from None
    if not np.all((deg > 0.0) & (deg <= JAW_MAX_DEG)):
        raise ValueError(f"jaw_deg is not accepted: openings in (0, {JAW_MAX_DEG:g}] degrees")
    return np.radians(deg - layout_deg) / 2.0


def pose_fit(
    kp: Keypoints, intrinsics: np.ndarray, baseline_m: float, iterations: int = ITERATIONS, scale_px: float = CAUCHY_PX
) -> PoseFit:
    """The pose fit of ``kp`` seen by a rectified stereo pair (``intrinsics``, ``baseline_m`` apart)."""
    rows = object_rows(kp)
    return PoseFit(kp.local, rows, intrinsics, rectified(baseline_m), iterations, scale_px, jaw_tips(kp))


def to_json(kp: Keypoints) -> dict:
    """A layout as plain JSON (metres)."""
    return {
        "names": list(kp.names),
        "object": [OBJECTS[int(o)] for o in kp.obj],
        "local_m": np.asarray(kp.local, np.float64).tolist(),
        "depth_slack_m": np.asarray(kp.depth_slack, np.float64).tolist(),
    }


def from_json(data: dict) -> Keypoints:
    """The layout :func:`to_json` wrote; ``ValueError`` says what is wrong with another."""
    try:
        names = tuple(str(n) for n in data["names"])
        obj = np.array([OBJECTS.index(o) for o in data["object"]])
        local = np.asarray(data["local_m"], np.float64)
        slack = np.asarray(data["depth_slack_m"], np.float64)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(
            f"a keypoint layout needs names, object (one of {OBJECTS}), local_m and depth_slack_m: {err}"
        ) from err
    k = len(names)
    if k == 0 or obj.shape != (k,) or local.shape != (k, 3) or slack.shape != (k,) or not np.all(np.isfinite(local)):
        raise ValueError(
            f"a keypoint layout of {k} names needs {k} objects, {k} finite local points (3) and {k} slacks"
        )
    if any(np.sum(obj == o) < 3 for o in range(len(OBJECTS))):
        raise ValueError("a keypoint layout needs at least 3 keypoints on each object (a pose from its points)")
    return Keypoints(names, obj, local, slack)
