"""The named camera models (:class:`~regrasp_mjx.envs.camera_errors.CameraErrors`): :data:`PRESETS`,
``lab-good`` and ``lab-typical`` (docs/inference.md, "A real camera's errors": sizes from the literature split
by our choice, :func:`split`) and ``rendered``, whose sizes a fit file holds (:func:`fitted`; the fit of the
model to the learned estimator's errors on held-out rendered frames, ``python -m regrasp_mjx.estimator fit``,
docs/rendering.md), read when it is asked for; :func:`named` takes a preset's name or a fit file's path.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterator, Mapping
from pathlib import Path

from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs.camera_errors import CameraErrors, Tracking


def split(
    rms_mm: float, bias: float, drift: float, drift_frames: float, deg_per_mm: float, depth_factor: float
) -> Tracking:
    """A :class:`Tracking` whose position error has root mean square ``rms_mm`` (3D, with the
    ``depth_factor`` stretch along the camera axis: :meth:`Tracking.rms_mm`), a share ``bias`` of
    its variance fixed per episode, ``drift`` correlated over ``drift_frames`` frames, the rest white."""
    if not (0.0 <= bias and 0.0 <= drift and bias + drift <= 1.0):
        raise ConfigError(f"bias={bias!r}, drift={drift!r} are not accepted: shares of the variance summing to <= 1")
    across = rms_mm / math.sqrt((2.0 + depth_factor**2) / 3.0)
    return Tracking(
        bias_mm=round(across * math.sqrt(bias), 4),
        drift_mm=round(across * math.sqrt(drift / 3.0), 4),
        drift_frames=drift_frames,
        white_mm=round(across * math.sqrt((1.0 - bias - drift) / 3.0), 4),
        deg_per_mm=deg_per_mm,
    )


# Our split of a reported error (docs/inference.md): half its variance fixed per episode (a hand-eye
# or model residual), 30 % a drift of half a second (15 frames: cable stretch, hysteresis), 20 % white;
# 2 degrees per mm (a stereo needle fit: about 1.5 mm / 1 degree); depth 2x the error across the axis,
# the reported size the whole error's root mean square.
DEPTH_FACTOR = 2.0
SHARES = {"bias": 0.5, "drift": 0.3, "drift_frames": 15.0, "deg_per_mm": 2.0, "depth_factor": DEPTH_FACTOR}
LITERATURE: dict[str, CameraErrors] = {
    # tools 0.65 mm (dVRK tool tracking after learned calibration), needle 1.0 mm (one camera)
    "lab-good": CameraErrors(split(1.0, **SHARES), split(0.65, **SHARES), DEPTH_FACTOR),
    # tools 1.0 mm, needle 1.5 mm (a stereo estimate in simulation)
    "lab-typical": CameraErrors(split(1.5, **SHARES), split(1.0, **SHARES), DEPTH_FACTOR),
}

# ---- presets fitted to measured errors -----------------------------------------------------------
# A fit file (strict JSON, written by ``python -m regrasp_mjx.estimator fit``: regrasp_mjx.vision.error_fit)
# holds the model's sizes under "preset" and how they were measured beside them; a preset of this kind
# is read from its file each time it is asked for, so that a missing or broken file refuses only the
# runs that name it.
FIT_FORMAT = "regrasp_mjx.camera_fit"
FIT_VERSION = 1
FIT_COMMAND = "python -m regrasp_mjx.estimator fit --errors EVAL --out {path}"
FITTED: dict[str, Path] = {"rendered": Path(__file__).resolve().parents[1] / "data" / "camera_rendered.json"}
TRACKING_FIELDS = tuple(f.name for f in dataclasses.fields(Tracking))


def _not_strict(constant: str) -> None:
    raise ValueError(f"{constant} is not a number of strict JSON")


def fitted(path: str | Path, name: str = "rendered") -> CameraErrors:
    """The :class:`CameraErrors` of a fit file (see above).

    Raises:
      ConfigError: no file at ``path`` (it says how to make one), or one that is not a fit of this
        format and version, or whose sizes a :class:`Tracking` refuses.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(
            f"camera errors {name!r}: no fitted file yet ({path}); make it from a trained estimator's errors on "
            f"held-out rendered frames: `{FIT_COMMAND.format(path=path)}` (docs/rendering.md)"
        )

    def refuse(why: str) -> ConfigError:
        return ConfigError(
            f"camera errors {name!r}: {path} is not a camera-error fit ({why}); accepted: a file that "
            f"`{FIT_COMMAND.format(path=path)}` wrote"
        )

    try:
        data = json.loads(path.read_text(), parse_constant=_not_strict)
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise refuse(f"not strict JSON: {type(err).__name__}: {err}") from None
    if not isinstance(data, dict) or data.get("format") != FIT_FORMAT:
        raise refuse(f"its format is not {FIT_FORMAT!r}")
    if data.get("version") != FIT_VERSION:
        raise refuse(f"version {data.get('version')!r}; this package reads version {FIT_VERSION}")
    sizes = data.get("preset")
    if not isinstance(sizes, dict) or set(sizes) != {"needle", "tools", "depth_factor"}:
        raise refuse("its 'preset' is not {'needle', 'tools', 'depth_factor'}")
    trackings = {}
    for part in ("needle", "tools"):
        fields = sizes[part]
        if not isinstance(fields, dict) or set(fields) != set(TRACKING_FIELDS):
            raise refuse(f"its preset's {part!r} does not hold exactly {TRACKING_FIELDS}")
        try:
            trackings[part] = Tracking(**fields)
        except ConfigError as err:
            raise refuse(f"its preset's {part}: {err}") from None
    try:
        return CameraErrors(trackings["needle"], trackings["tools"], sizes["depth_factor"])
    except ConfigError as err:
        raise refuse(str(err)) from None


class Presets(Mapping):
    """The named camera models: the literature's (:data:`LITERATURE`) and those a fit file holds
    (:data:`FITTED`, read by :func:`fitted` when asked for: a missing file refuses only its own name).
    Its names list both kinds; ``PRESETS[name]`` may raise :class:`ConfigError`."""

    def __getitem__(self, name: str) -> CameraErrors:
        if name in LITERATURE:
            return LITERATURE[name]
        if name in FITTED:
            return fitted(FITTED[name], name)
        raise KeyError(name)

    def __iter__(self) -> Iterator[str]:
        return iter((*LITERATURE, *FITTED))

    def __len__(self) -> int:
        return len(LITERATURE) + len(FITTED)

    def __contains__(self, name: object) -> bool:
        return name in LITERATURE or name in FITTED


PRESETS = Presets()


def preset(name: str) -> CameraErrors:
    """The preset ``name`` (:data:`PRESETS`); raises :class:`ConfigError` on an unknown name or, for a
    fitted one, a missing or malformed fit file."""
    if not isinstance(name, str) or name not in PRESETS:
        raise ConfigError(f"camera errors {name!r} are not accepted: one of {tuple(PRESETS)}")
    return PRESETS[name]


def named(name: str | Path) -> CameraErrors:
    """A preset by its name (:func:`preset`) or the sizes of a fit file (a path ending ``.json``, what
    ``estimator fit`` wrote: :func:`fitted`); raises :class:`ConfigError` as they do."""
    if str(name).endswith(".json"):
        return fitted(name, name=str(name))
    return preset(name)
