"""Typed, frozen configs of the scene and the task, validated when built.

Field names carry their unit (``_mm``, ``_deg``; grasp coordinates are radians and say so) because
these are the numbers a user types; the code converts to metres and radians once, when an
environment is built. Defaults are SPEC's; docs/choices.md lists which of them are our choices.
Building them from ``--set`` text, dotted names and saved dicts: :mod:`regrasp_mjx.core.config_text`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any


class ConfigError(ValueError):
    """A config value out of its accepted range; the message names the field and the range."""


# The one form of every config check in the package: ``require(ok, field, value, accepted)`` raises
# ConfigError("FIELD=VALUE is not accepted: ACCEPTED"); the helpers below apply it to fields by name.
def require(ok: bool, field: str, value: Any, accepted: str) -> None:
    if not ok:
        raise ConfigError(f"{field}={value!r} is not accepted: {accepted}")


def is_number(x: Any) -> bool:
    """A finite real number (not a bool)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def is_integer(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def require_numbers(owner: Any, names: tuple[str, ...], ok, accepted: str, prefix: str = "") -> None:
    """Each field ``names`` of ``owner`` a finite number for which ``ok(value)`` holds."""
    for name in names:
        v = getattr(owner, name)
        require(is_number(v) and ok(v), prefix + name, v, accepted)


def require_integers(owner: Any, names: tuple[str, ...], lo: int, prefix: str = "") -> None:
    """Each field ``names`` of ``owner`` an integer >= ``lo``."""
    for name in names:
        v = getattr(owner, name)
        require(is_integer(v) and v >= lo, prefix + name, v, f"an integer >= {lo}")


def require_flags(owner: Any, names: tuple[str, ...], prefix: str = "") -> None:
    for name in names:
        v = getattr(owner, name)
        require(isinstance(v, bool), prefix + name, v, "True or False")


def _require_range(field: str, rng: tuple[float, float], lo: float, hi: float, unit: str) -> None:
    require(
        isinstance(rng, tuple) and len(rng) == 2 and all(is_number(v) for v in rng),
        field,
        rng,
        f"a pair (low, high) of finite numbers in {unit}",
    )
    require(lo <= rng[0] <= rng[1] <= hi, field, rng, f"low <= high within [{lo:g}, {hi:g}] {unit}")


# the Large Needle Driver's widest jaw opening [deg] (jhu-dvrk/sawIntuitiveResearchKit,
# share/tool/LARGE_NEEDLE_DRIVER_400006.json: jaw qmax 1.39626 rad)
JAW_MAX_DEG = 80.0


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Geometry that varies from the MJCF defaults (``regrasp_mjx/models/regrasp_scene.xml``).

    Attributes:
      jaw_angle_deg: angle between the two open jaws of the regrasping tool (SPEC: 20, ours).
      needle_radius_mm: needle radius R (paper: 5.4).
      wire_radius_mm: needle wire radius (SPEC: 0.25, ours).
      conservative_needle: the needle's 56 straight capsule chords are moved out from the arc and
        grown (ends at R k, k = 2 / (1 + cos h), radius wire + R tan^2(h/2), see
        ``regrasp_mjx.world.scene.chord_placement``) so that they contain the true wire: the model never
        reports more clearance than there is and at most 2.12 um less for R = 5.4 mm, 4.72 um for
        12 mm (ours; False = the chords' ends on the arc and the wire radius alone, which
        under-reports contact by up to the sagitta, 4.7 um for R = 12 mm).
    """

    jaw_angle_deg: float = 20.0
    needle_radius_mm: float = 5.4
    wire_radius_mm: float = 0.25
    conservative_needle: bool = True

    def __post_init__(self) -> None:
        require(
            is_number(self.jaw_angle_deg) and 0.0 < self.jaw_angle_deg < 90.0,
            "jaw_angle_deg",
            self.jaw_angle_deg,
            "a number of degrees in (0, 90)",
        )
        require(
            is_number(self.needle_radius_mm) and 1.0 <= self.needle_radius_mm <= 20.0,
            "needle_radius_mm",
            self.needle_radius_mm,
            "a number of millimetres in [1, 20]",
        )
        require(
            is_number(self.wire_radius_mm) and 0.05 <= self.wire_radius_mm <= 1.0,
            "wire_radius_mm",
            self.wire_radius_mm,
            "a number of millimetres in [0.05, 1]",
        )
        require(
            isinstance(self.conservative_needle, bool), "conservative_needle", self.conservative_needle, "True or False"
        )


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """The paper's goal and start distributions (§IV; SPEC "Distributions"), and optional ranges of
    the goal grasp and the needle that make the task general (ours, issue 15).

    Grasp coordinates (alpha, theta, phi) are radians, depths millimetres. ``goal_*_rad`` are the
    paper's goal grasp; ``goal_*_range_rad``, when given, are drawn from uniformly instead (the
    fixed value then is only the default goal a plan asks for). ``needle_radius_range_mm`` and
    ``wire_radius_range_mm`` draw the needle of each problem (None: the scene's one needle). With a
    needle-radius range the start keeps the meaning SPEC gives it for the paper's needle: on the
    ray from the needle centre through the goal end-effector position, as far beyond the goal as
    ``start_distance_mm`` puts it for a needle of ``geometry.NEEDLE_RADIUS`` (5.4 mm) with the same
    goal grasp. A task with any range observes the goal and the needle (``EnvConfig``'s
    observation grows to :data:`regrasp_mjx.core.geometry.OBS_SIZE_GENERAL`).
    """

    goal_alpha_rad: float = 4.0 * math.pi / 3.0
    goal_theta_rad: float = 0.0
    goal_phi_rad: float = math.pi
    goal_depth_mm: tuple[float, float] = (6.5, 8.0)
    init_alpha_rad: tuple[float, float] = (11.0 * math.pi / 18.0, 13.0 * math.pi / 18.0)
    init_depth_mm: tuple[float, float] = (6.5, 8.0)
    init_theta_rad: tuple[float, float] = (0.0, 2.0 * math.pi)
    init_phi_rad: tuple[float, float] = (0.0, 0.4 * math.pi)
    start_distance_mm: float = 13.0
    start_pos_noise_mm: float = 1.0
    start_rot_noise_deg: float = 5.0
    max_sample_tries: int = 64
    goal_alpha_range_rad: tuple[float, float] | None = None
    goal_theta_range_rad: tuple[float, float] | None = None
    goal_phi_range_rad: tuple[float, float] | None = None
    needle_radius_range_mm: tuple[float, float] | None = None
    wire_radius_range_mm: tuple[float, float] | None = None

    @property
    def varies_needle(self) -> bool:
        """Each problem draws its own needle (radius or wire radius)."""
        return self.needle_radius_range_mm is not None or self.wire_radius_range_mm is not None

    @property
    def general(self) -> bool:
        """Any range of the goal grasp or the needle is set: problems differ in what the policy
        must be told, so the observation holds the goal and the needle."""
        return self.varies_needle or any(
            r is not None for r in (self.goal_alpha_range_rad, self.goal_theta_range_rad, self.goal_phi_range_rad)
        )

    def span(self, name: str, fixed: float) -> tuple[float, float]:
        """``(low, high)`` of ``name`` (a ``*_range_*`` field); ``(fixed, fixed)`` when it is None."""
        rng = getattr(self, name)
        return (float(fixed), float(fixed)) if rng is None else (float(rng[0]), float(rng[1]))

    def __post_init__(self) -> None:
        for name in ("goal_alpha_rad", "goal_theta_rad", "goal_phi_rad"):
            require(is_number(getattr(self, name)), name, getattr(self, name), "a finite number of radians")
        require(
            math.pi / 2 <= self.goal_alpha_rad <= 3 * math.pi / 2,
            "goal_alpha_rad",
            self.goal_alpha_rad,
            "an angle on the needle in [pi/2, 3pi/2]",
        )
        _require_range("goal_depth_mm", self.goal_depth_mm, 0.5, 20.0, "mm")
        _require_range("init_alpha_rad", self.init_alpha_rad, math.pi / 2, 3 * math.pi / 2, "rad")
        _require_range("init_depth_mm", self.init_depth_mm, 0.5, 20.0, "mm")
        _require_range("init_theta_rad", self.init_theta_rad, -2 * math.pi, 4 * math.pi, "rad")
        _require_range("init_phi_rad", self.init_phi_rad, 0.0, math.pi, "rad")
        require(
            is_number(self.start_distance_mm) and 0.0 < self.start_distance_mm <= 100.0,
            "start_distance_mm",
            self.start_distance_mm,
            "a distance in (0, 100] mm",
        )
        require(
            is_number(self.start_pos_noise_mm) and 0.0 <= self.start_pos_noise_mm <= 10.0,
            "start_pos_noise_mm",
            self.start_pos_noise_mm,
            "a half-width in [0, 10] mm",
        )
        require(
            is_number(self.start_rot_noise_deg) and 0.0 <= self.start_rot_noise_deg <= 180.0,
            "start_rot_noise_deg",
            self.start_rot_noise_deg,
            "a half-width in [0, 180] degrees",
        )
        require(
            isinstance(self.max_sample_tries, int) and 1 <= self.max_sample_tries <= 4096,
            "max_sample_tries",
            self.max_sample_tries,
            "an integer in [1, 4096]",
        )
        for name, fixed, lo, hi, unit in (
            ("goal_alpha_range_rad", self.goal_alpha_rad, math.pi / 2, 3 * math.pi / 2, "rad"),
            ("goal_theta_range_rad", self.goal_theta_rad, -2 * math.pi, 4 * math.pi, "rad"),
            ("goal_phi_range_rad", self.goal_phi_rad, 0.0, math.pi, "rad"),
        ):
            rng = getattr(self, name)
            if rng is None:
                continue
            _require_range(name, rng, lo, hi, unit)
            require(
                rng[0] - 1e-9 <= fixed <= rng[1] + 1e-9,
                name,
                rng,
                f"a range that holds the default goal {name.replace('_range', '')}={fixed:.6g}",
            )
        if self.needle_radius_range_mm is not None:
            _require_range("needle_radius_range_mm", self.needle_radius_range_mm, 1.0, 20.0, "mm")
        if self.wire_radius_range_mm is not None:
            _require_range("wire_radius_range_mm", self.wire_radius_range_mm, 0.05, 1.0, "mm")


# The general task of issue 15 (ours): any goal grasp in these ranges, half-circle needles of 4 to 12 mm
# radius and 0.15 to 0.35 mm wire radius; the paper's goal grasp and needle lie inside them.
GENERAL_TASK = TaskConfig(
    goal_alpha_range_rad=(10.0 * math.pi / 9.0, 13.0 * math.pi / 9.0),
    goal_theta_range_rad=(0.0, 2.0 * math.pi),
    goal_phi_range_rad=(3.0 * math.pi / 4.0, math.pi),
    needle_radius_range_mm=(4.0, 12.0),
    wire_radius_range_mm=(0.15, 0.35),
)
TASKS = {"paper": TaskConfig(), "general": GENERAL_TASK}


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """The MDP (paper §III-B/C, §IV; SPEC "MDP").

    Attributes:
      scene: geometry.
      task: start and goal distributions.
      max_dp_mm: translation per action unit and axis (SPEC: 0.5, ours).
      max_drot_deg: rotation-vector component per action unit (SPEC: 3, ours).
      horizon: steps before a time-out (truncation, not a terminal state).
      step_reward: beta, the reward of a step that neither collides nor succeeds.
      collision_reward, success_reward: terminal rewards.
      success_pos_mm, success_rot_deg: the success tolerances of eqs. (8) and (9).
      clearance_mm: a step collides when any counted pair comes closer than this anywhere along
        its motion (ours; 0 = only penetration, SPEC): the continuous test of
        :mod:`regrasp_mjx.world.continuous`, the whole motion and not sampled poses.
      check_actions: raise a runtime error on a non-finite action (costs a little speed; the
        learner, whose actions are tanh outputs, turns it off).
      jaw_open_deg: the opening the regrasping jaws open to on the way (ours, issue 67; None: they
        stay at the scene's): at the first step whose start leaves room for the whole opening sweep
        (``jaw_open_margin_mm`` at every opening, the tool holding still), before its motion.
      jaw_open_margin_mm: that room [mm], at least ``clearance_mm`` where the jaws open.
    """

    scene: SceneConfig = SceneConfig()
    task: TaskConfig = TaskConfig()
    max_dp_mm: float = 0.5
    max_drot_deg: float = 3.0
    horizon: int = 100
    step_reward: float = -0.02
    collision_reward: float = -1.0
    success_reward: float = 1.0
    success_pos_mm: float = 1.0
    success_rot_deg: float = 5.0
    clearance_mm: float = 0.0
    check_actions: bool = True
    jaw_open_deg: float | None = None
    jaw_open_margin_mm: float = 0.5

    def __post_init__(self) -> None:
        require(isinstance(self.scene, SceneConfig), "scene", self.scene, "a SceneConfig")
        require(isinstance(self.task, TaskConfig), "task", self.task, "a TaskConfig")
        require(
            is_number(self.max_dp_mm) and 0.0 < self.max_dp_mm <= 5.0,
            "max_dp_mm",
            self.max_dp_mm,
            "a step in (0, 5] mm",
        )
        require(
            is_number(self.max_drot_deg) and 0.0 < self.max_drot_deg <= 30.0,
            "max_drot_deg",
            self.max_drot_deg,
            "a step in (0, 30] degrees",
        )
        require(
            isinstance(self.horizon, int) and not isinstance(self.horizon, bool) and 1 <= self.horizon <= 100_000,
            "horizon",
            self.horizon,
            "an integer number of steps in [1, 100000]",
        )
        require(
            is_number(self.step_reward) and self.step_reward <= 0.0,
            "step_reward",
            self.step_reward,
            "a finite number <= 0 (beta < 0 in the paper)",
        )
        for name in ("collision_reward", "success_reward"):
            require(is_number(getattr(self, name)), name, getattr(self, name), "a finite number")
        require(
            is_number(self.success_pos_mm) and self.success_pos_mm > 0.0,
            "success_pos_mm",
            self.success_pos_mm,
            "a tolerance > 0 mm",
        )
        require(
            is_number(self.success_rot_deg) and 0.0 < self.success_rot_deg <= 180.0,
            "success_rot_deg",
            self.success_rot_deg,
            "a tolerance in (0, 180] degrees",
        )
        require(
            is_number(self.clearance_mm) and 0.0 <= self.clearance_mm <= 1.0,
            "clearance_mm",
            self.clearance_mm,
            "a margin in [0, 1] mm",
        )
        require(isinstance(self.check_actions, bool), "check_actions", self.check_actions, "True or False")
        require(
            self.jaw_open_deg is None
            or (is_number(self.jaw_open_deg) and self.scene.jaw_angle_deg < self.jaw_open_deg <= JAW_MAX_DEG),
            "jaw_open_deg",
            self.jaw_open_deg,
            f"None or degrees wider than the scene's jaw_angle_deg ({self.scene.jaw_angle_deg}) up to the "
            f"Large Needle Driver's {JAW_MAX_DEG:g}",
        )
        # the room the jaws open with keeps the pose's own margin (only where they open)
        least = self.clearance_mm if self.jaw_open_deg is not None else 0.0
        require(
            is_number(self.jaw_open_margin_mm) and least <= self.jaw_open_margin_mm <= 5.0,
            "jaw_open_margin_mm",
            self.jaw_open_margin_mm,
            f"a room in [{least}, 5] mm" + (" (at least clearance_mm where the jaws open)" if least else ""),
        )
        for field, value, rng in (
            ("needle_radius_mm", self.scene.needle_radius_mm, self.task.needle_radius_range_mm),
            ("wire_radius_mm", self.scene.wire_radius_mm, self.task.wire_radius_range_mm),
        ):
            require(
                rng is None or rng[0] - 1e-9 <= value <= rng[1] + 1e-9,
                f"scene.{field}",
                value,
                f"a value within task's range {rng} (the scene's needle is the default one a plan takes)",
            )
