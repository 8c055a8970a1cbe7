"""A joint path timed for a dVRK PSM: the time-optimal trajectory through joint waypoints at the
arm's own velocity and acceleration limits, sampled at the controller's rate (the motion the arm
then makes is checked and repaired in :mod:`regrasp_mjx.robot.executed_motion`).

:func:`time_joints` fits one C2 spline through the waypoints in joint space (knots spaced by the
time each segment needs at the velocity limits) and times it with TOPP-RA (the time-optimal
parameterisation of a given path under joint velocity and acceleration limits, Pham and Pham
2018), compiled in :mod:`regrasp_mjx.robot.topp` (the ``toppra`` library's results in a tenth of
its time; ``engine="toppra"`` uses the library). TOPP-RA, not Ruckig: the motion must pass through
every waypoint of a checked plan, and Ruckig's community edition plans to one target state (its
waypoints are a paid feature); the path is fixed first and only its timing is optimised, which is
what the re-check needs.

Limits (:data:`V_MAX`, :data:`A_MAX`): the dVRK's own for the PSM's joint trajectories,
``jhu-dvrk/sawIntuitiveResearchKit`` ``core/components/code/mtsIntuitiveResearchKitPSM.cpp``
(commit 9e535e6, 2026-04-17, lines 726-731): 90 deg/s and 90 deg/s^2 for the outer yaw and pitch,
0.2 m/s and 0.2 m/s^2 for the insertion, 1080 deg/s and 720 deg/s^2 for the roll and the wrist.

The jaw (issue 67), the PSM's seventh joint, the angle between the two jaws: a policy whose jaws open on
the way (:class:`~regrasp_mjx.robot.psm_joints.JawTrack`) has the arm come to rest at the pose where they
open, the jaw open there alone, and the arm go on (:func:`join`: TOPP-RA times the arm's two parts, the
jaw's move is the time-optimal rest-to-rest one, :func:`sample_move`). Its limits are the same source's
for joints 4 to 7, the jaw the last of them: 1080 deg/s and 720 deg/s^2 (:data:`JAW_V_MAX`,
:data:`JAW_A_MAX`: ``v_max.Ref(4, 3)``, ``a_max.Ref(4, 3)`` of the PSM's 7 joints, which ``jaw_move_jp``
moves index 6 with, line 1380), so 20 degrees of opening take 1/3 s (never at the speed limit:
``2 sqrt(d / a)``). Teleoperation follows the surgeon's gripper at up to 720 deg/s
(``TeleOperationPSM::JawRate``, ``mtsIntuitiveResearchKit.h``), a rate for following a hand with no
acceleration limit, not a trajectory's. The closing on the wire is not timed: the environment declares
the goal reached with the jaws as they arrive and never closes them (for any policy, at 20 degrees
too); :func:`move_time_s` says what it would add (20 degrees to 0: 0.333 s, 40 to 0: 0.471 s).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math

import numpy as np
import toppra
import toppra.algorithm
import toppra.constraint
import toppra.solverwrapper

from regrasp_mjx.robot import topp

V_MAX = np.array([math.pi / 2, math.pi / 2, 0.2, 6 * math.pi, 6 * math.pi, 6 * math.pi])  # rad/s, m/s
A_MAX = np.array([math.pi / 2, math.pi / 2, 0.2, 4 * math.pi, 4 * math.pi, 4 * math.pi])  # rad/s^2, m/s^2
RATE_HZ = 1000.0  # the dVRK's servo rate
# TOPP-RA's grid along the path: every waypoint (a knot of the spline) and this many points inside
# each segment between two, Chebyshev-spaced (densest next to the knots, where the spline's curvature,
# and with it how fast the joints move for a path velocity, changes most). Against a uniform grid of
# max(200, 40 W) points: about 5x fewer points, the motion a few percent longer (experiments/RESULTS.md,
# issue 48: TOPP-RA's time grows with its points, its motion shrinks with them)
GRID_PER_SEGMENT = 8
MAX_RESCALES = 4  # uniform slow-downs of a timing whose samples pass a limit (one is the rule)
# the share of each limit TOPP-RA is given: all of it, since the motion between its grid points is
# slowed to the limits afterwards (path_ratio); below 1 it leaves room and motion time
HEADROOM = 1.0
# the jaw joint's (rad/s, rad/s^2): 1080 deg/s and 720 deg/s^2, as the roll and the wrist (the docstring)
JAW_V_MAX = 6.0 * math.pi
JAW_A_MAX = 4.0 * math.pi
ENGINES = ("compiled", "toppra")  # time_joints' TOPP-RA: regrasp_mjx.robot.topp, or the toppra library


@dataclasses.dataclass(frozen=True)
class TimedTrajectory:
    """Joint positions ``q``, velocities ``qd`` and accelerations ``qdd`` ``[N, 6]`` at times ``t``
    ``[N]`` (s, from 0, at ``rate_hz``; the last sample is the end), through ``waypoints`` ``[W, 6]``;
    for a policy whose jaws open on the way, the jaw joint's ``jaw``, ``jaw_d``, ``jaw_dd`` ``[N]``
    (rad, rad/s, rad/s^2: :mod:`regrasp_mjx.robot.psm_jaw`), else None (the scene's fixed opening)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    waypoints: np.ndarray
    rate_hz: float
    jaw: np.ndarray | None = None
    jaw_d: np.ndarray | None = None
    jaw_dd: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])


def time_joints(
    waypoints,
    rate_hz: float = RATE_HZ,
    v_max=V_MAX,
    a_max=A_MAX,
    gridpoints: int | None = None,
    engine: str = "compiled",
) -> TimedTrajectory:
    """The time-optimal trajectory through joint ``waypoints`` ``[W, 6]`` (at rest at both ends) under
    ``v_max`` and ``a_max`` (6 each), sampled at ``rate_hz`` (see the module's docstring): TOPP-RA's
    timing (:func:`raw_timing`, at :data:`HEADROOM` of the limits) slowed uniformly by the largest
    excess anywhere between its grid points (:func:`path_ratio`), so that every sample keeps the
    limits. ``gridpoints``: TOPP-RA's grid along the path, that many points spaced evenly (default:
    the knots and :data:`GRID_PER_SEGMENT` points between two, :func:`knot_grid`; a coarser grid is
    faster to compute and gives longer motion, experiments/RESULTS.md). ``engine``: ``"compiled"``
    (:mod:`regrasp_mjx.robot.topp`, toppra's algorithm and results in about a tenth of its time) or
    ``"toppra"`` (the library itself, the reference)."""
    if engine not in ENGINES:
        raise ValueError(f"engine={engine!r} is not accepted: one of {', '.join(map(repr, ENGINES))}")
    q = np.asarray(waypoints, np.float64)
    if q.ndim != 2 or q.shape[1] != 6 or len(q) < 1 or not np.all(np.isfinite(q)):
        raise ValueError(f"waypoints of shape {q.shape} are not accepted: [W, 6] finite joint vectors, W >= 1")
    v_max, a_max = np.asarray(v_max, np.float64), np.asarray(a_max, np.float64)
    if v_max.shape != (6,) or a_max.shape != (6,) or np.any(~(v_max > 0)) or np.any(~(a_max > 0)):
        raise ValueError("v_max and a_max are not accepted: 6 positive numbers each")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz={rate_hz!r} is not accepted: a positive number (the controller's rate)")
    # knots spaced by the time each segment takes at the velocity limits; a repeated waypoint is dropped
    span = np.max(np.abs(np.diff(q, axis=0)) / v_max, axis=1) if len(q) > 1 else np.zeros(0)
    keep = np.r_[True, span > 1e-12]
    q, span = q[keep], span[keep[1:]]
    if len(q) == 1:
        zero = np.zeros((1, 6))
        return TimedTrajectory(np.zeros(1), q.copy(), zero, zero.copy(), q.copy(), float(rate_hz))
    if gridpoints is not None and not (isinstance(gridpoints, int) and gridpoints >= 2):
        raise ValueError(f"gridpoints={gridpoints!r} is not accepted: an integer >= 2")
    path, grid, sd = raw_timing(q, gridpoints, v_max, a_max, engine)
    # TOPP-RA holds the limits at its grid points; between them the motion can pass one (the path's
    # curvature changes within an interval): the whole motion is slowed uniformly by the largest
    # excess anywhere along it (velocities / r, accelerations / r^2), then sampled
    sd = sd / max(1.0, path_ratio(path, grid, sd, v_max, a_max))
    for _ in range(MAX_RESCALES):
        t, position, velocity, acceleration = sample_const_accel(path, grid, sd, rate_hz)
        over = limit_ratio(velocity, acceleration, v_max, a_max)
        if over <= 1.0:
            return TimedTrajectory(t, position, velocity, acceleration, q, float(rate_hz))
        sd = sd / (over * (1.0 + 1e-3))  # a sample past path_ratio's points (rare): slowed again
    raise ValueError(f"no timing within the limits after {MAX_RESCALES} uniform slow-downs (last excess {over:.6f})")


def raw_timing(q: np.ndarray, gridpoints: int | None = None, v_max=V_MAX, a_max=A_MAX, engine: str = "compiled"):
    """TOPP-RA's own timing of distinct waypoints ``q`` ``[W >= 2, 6]``: ``(path, gridpoints, sd)``,
    the C2 spline through them (knots spaced by the time each segment takes at the velocity limits)
    and the path velocities at the grid's points, at :data:`HEADROOM` of the limits; ``gridpoints``
    None: :func:`knot_grid`, else that many points spaced evenly; ``engine`` as :func:`time_joints`."""
    v_max, a_max = np.asarray(v_max, np.float64), np.asarray(a_max, np.float64)
    span = np.max(np.abs(np.diff(q, axis=0)) / v_max, axis=1)
    ss = np.r_[0.0, np.cumsum(span)]
    ss /= ss[-1]
    grid = np.linspace(0.0, 1.0, gridpoints) if gridpoints else knot_grid(ss)
    path = topp.Spline(ss, q)
    if engine == "toppra":  # the library's spline (scipy's, the same to 1e-15) and passes
        reference = toppra.SplineInterpolator(ss, q, bc_type="clamped" if len(q) > 2 else "natural")
        with _solvers_looked_up_once():
            solver = toppra.algorithm.TOPPRA(
                _constraints(tuple(v_max * HEADROOM), tuple(a_max * HEADROOM)),
                reference,
                gridpoints=grid,
                solver_wrapper="seidel",
            )
        solver.compute_parameterization(0.0, 0.0)
        ok = solver.problem_data.return_code == toppra.algorithm.ParameterizationReturnCode.Ok
        sd = solver.problem_data.sd_vec if ok else None
    else:
        sd = topp.path_velocities(path(grid, 1), path(grid, 2), grid, v_max * HEADROOM, a_max * HEADROOM)
    if sd is not None and np.all(np.isfinite(sd)) and len(grid) > 2 and np.all(sd[1:-1] > 0):
        return path, grid, sd  # (2 points at rest: no motion at all)
    raise ValueError("TOPP-RA found no trajectory through these waypoints at these limits")


def knot_grid(knots: np.ndarray, per_segment: int = GRID_PER_SEGMENT) -> np.ndarray:
    """The path's grid: the spline's ``knots`` (increasing, 0 to 1) and ``per_segment`` points inside
    each segment at the Chebyshev points' spacing, ``(1 - cos(pi k / (n + 1))) / 2``."""
    inner = (1.0 - np.cos(np.pi * np.arange(1, per_segment + 1) / (per_segment + 1))) / 2.0
    knots = np.asarray(knots, np.float64)
    points = knots[:-1, None] + inner[None, :] * np.diff(knots)[:, None]
    return np.sort(np.r_[knots, points.ravel()])


def path_ratio(path, gridpoints: np.ndarray, sd: np.ndarray, v_max, a_max, points: int = 2000) -> float:
    """:func:`limit_ratio` of the motion TOPP-RA's ``sd`` makes (the path acceleration constant between
    grid points, :func:`sample_const_accel`) at both ends of every grid interval and points inside
    it, about ``points`` in all (at least 2 inside each), where the samples at the controller's rate
    fall anywhere (a coarse grid's intervals need the most: its curvature changes within them);
    ``path`` a :class:`~regrasp_mjx.robot.topp.Spline` (compiled, :func:`~regrasp_mjx.robot.topp.motion_ratio`)."""
    ss, sd = np.asarray(gridpoints, np.float64), np.asarray(sd, np.float64)
    v_max, a_max = np.asarray(v_max, np.float64), np.asarray(a_max, np.float64)
    return topp.motion_ratio(path.knots, path.coef, ss, sd, max(2, points // len(ss)), v_max, a_max)


def limit_ratio(qd: np.ndarray, qdd: np.ndarray, v_max=V_MAX, a_max=A_MAX) -> float:
    """The uniform slow-down ``r`` (time x r) that brings samples ``qd``, ``qdd`` ``[N, 6]`` within the
    limits: ``max(|qd| / v_max, sqrt(|qdd| / a_max))`` over every sample and joint (<= 1: within)."""
    v = float(np.max(np.abs(qd) / v_max)) if len(qd) else 0.0
    a = float(np.max(np.abs(qdd) / a_max)) if len(qdd) else 0.0
    return max(v, math.sqrt(a))


@functools.cache
def _solvers_found() -> tuple:
    """``toppra.solverwrapper.available_solvers(output_msg=False)``, looked up once: the optional solvers
    it searches sys.path for cannot appear while a process runs."""
    return toppra.solverwrapper.available_solvers(output_msg=False)


@contextlib.contextmanager
def _solvers_looked_up_once():
    """Inside the block, toppra's ``available_solvers`` answers from :func:`_solvers_found`; restored on
    leaving. Why: every ``toppra.algorithm.TOPPRA(...)`` calls it to pick a default solver, even when
    given ``solver_wrapper="seidel"`` (no argument skips it), and its search of sys.path is 0.1 ms of a
    plan's timing (profiled). The module attribute is what toppra reads, so it is swapped for the
    constructor's call only, not for the process (threads interleaving the swap may leave the cached
    answer in place: the same answer)."""
    found = _solvers_found()  # before the swap: the lookup itself calls the attribute
    search = toppra.solverwrapper.available_solvers
    toppra.solverwrapper.available_solvers = lambda output_msg=True: found
    try:
        yield
    finally:
        toppra.solverwrapper.available_solvers = search


@functools.lru_cache(maxsize=8)
def _constraints(v: tuple[float, ...], a: tuple[float, ...]) -> list:
    """TOPP-RA's joint velocity and acceleration constraints, made once per limits: toppra formats
    every limit into a string as it makes a constraint (0.4 ms of a plan's 1.5 ms, profiled)."""
    v, a = np.asarray(v), np.asarray(a)
    return [
        toppra.constraint.JointVelocityConstraint(np.stack([-v, v], 1)),
        toppra.constraint.JointAccelerationConstraint(np.stack([-a, a], 1)),
    ]


def sample_const_accel(path, gridpoints: np.ndarray, sd: np.ndarray, rate_hz: float):
    """Times and joint positions, velocities and accelerations at ``rate_hz`` along ``path`` (a
    :class:`~regrasp_mjx.robot.topp.Spline`) timed by TOPP-RA's path velocities ``sd`` at
    ``gridpoints``, the path acceleration constant between grid points:
    ``toppra.parametrizer.ParametrizeConstAccel``'s trajectory, compiled (:func:`~regrasp_mjx.robot.topp.sample`;
    toppra's own loop over samples took two thirds of a plan's timing, experiments/RESULTS.md)."""
    ss, sd = np.asarray(gridpoints, np.float64), np.asarray(sd, np.float64)
    return topp.sample(path.knots, path.coef, ss, sd, float(rate_hz))


# ---- the jaw joint (issue 67): its own limits, its opening with the arm at rest, and the three parts joined
def move_time_s(delta_rad: float, v_max: float = JAW_V_MAX, a_max: float = JAW_A_MAX) -> float:
    """The shortest time a joint takes from rest to rest over ``|delta_rad|`` at ``v_max`` and ``a_max``:
    ``2 sqrt(d / a)`` where it never reaches ``v_max`` (``d <= v^2 / a``, any jaw move at the dVRK's limits),
    else ``d / v + v / a``."""
    d = abs(float(delta_rad))
    if d <= v_max * v_max / a_max:
        return 2.0 * math.sqrt(d / a_max)
    return d / v_max + v_max / a_max


def sample_move(from_rad: float, to_rad: float, rate_hz: float, v_max: float = JAW_V_MAX, a_max: float = JAW_A_MAX):
    """``(t, position, velocity, acceleration)`` of the time-optimal move from rest at ``from_rad`` to
    rest at ``to_rad`` (:func:`move_time_s`: full acceleration, then cruise at ``v_max`` where reached,
    then full braking), sampled at ``rate_hz`` from 0; the last sample is the end."""
    d, sign = abs(to_rad - from_rad), math.copysign(1.0, to_rad - from_rad)
    total = move_time_s(d, v_max, a_max)
    t = np.arange(0.0, total, 1.0 / rate_hz) if total > 0.0 else np.zeros(1)
    t = np.r_[t, total] if total - t[-1] > 1e-12 else t
    ramp = min(v_max / a_max, total / 2.0)  # time spent accelerating (and braking)
    peak = a_max * ramp
    early, late = t <= ramp, t >= total - ramp
    back = total - t
    s = np.where(
        early, 0.5 * a_max * t * t, np.where(late, d - 0.5 * a_max * back * back, 0.5 * peak * ramp + peak * (t - ramp))
    )
    v = np.where(early, a_max * t, np.where(late, a_max * back, peak))
    a = np.where(early, a_max, np.where(late, -a_max, 0.0))
    position = from_rad + sign * s
    position[-1], v[-1] = to_rad, 0.0  # the end exactly (the opening kept after it compares equal)
    return t, position, sign * v, sign * a


def hold(timed: TimedTrajectory, deg: float) -> TimedTrajectory:
    """``timed`` with the jaw held at ``deg`` the whole time."""
    n = len(timed.t)
    return dataclasses.replace(timed, jaw=np.full(n, math.radians(deg)), jaw_d=np.zeros(n), jaw_dd=np.zeros(n))


def join(before: TimedTrajectory, after: TimedTrajectory, track) -> TimedTrajectory:
    """One trajectory of the arm's motion ``before`` (to the opening pose, at rest there), the jaw's
    opening (:func:`sample_move`, the arm held at ``before``'s last sample) and the arm's motion
    ``after`` (from the opening pose); the jaw at ``track.from_deg``, moving, then at ``track.to_deg``
    (``track`` a :class:`~regrasp_mjx.robot.psm_joints.JawTrack` that opens).
    ``waypoints``: both parts', the opening pose in each."""
    if not track.opens:
        raise ValueError("join is for a track whose jaws open (opens_at >= 0); hold() keeps them")
    if before.rate_hz != after.rate_hz:
        raise ValueError(f"the parts' rates differ ({before.rate_hz} and {after.rate_hz} Hz): time both at one rate")
    lo, hi = math.radians(track.from_deg), math.radians(track.to_deg)
    t, s, sd, sdd = sample_move(lo, hi, before.rate_hz)
    n_move = len(t) - 1  # its first sample is before's last
    opening_end = before.t[-1] + t[-1]
    q_still = np.tile(before.q[-1], (n_move, 1))
    zeros = np.zeros((n_move, 6))
    n_after = len(after.t) - 1  # its first sample is the opening's last pose

    def cat(*parts):
        return np.concatenate(parts, axis=0)

    return TimedTrajectory(
        t=cat(before.t, before.t[-1] + t[1:], opening_end + after.t[1:]),
        q=cat(before.q, q_still, after.q[1:]),
        qd=cat(before.qd, zeros, after.qd[1:]),
        qdd=cat(before.qdd, zeros, after.qdd[1:]),
        waypoints=cat(before.waypoints, after.waypoints),
        rate_hz=before.rate_hz,
        jaw=cat(np.full(len(before.t), lo), s[1:], np.full(n_after, hi)),
        jaw_d=cat(np.zeros(len(before.t)), sd[1:], np.zeros(n_after)),
        jaw_dd=cat(np.zeros(len(before.t)), sdd[1:], np.zeros(n_after)),
    )


def time_with_jaw(waypoints, track, rate_hz: float = RATE_HZ, **options) -> TimedTrajectory:
    """:func:`time_joints` of the arm's ``waypoints`` ``[poses, 6]`` with the jaw's ``track`` (a
    :class:`~regrasp_mjx.robot.psm_joints.JawTrack`): where it opens, the arm timed to the opening pose
    and from it, at rest there, and the jaw's opening between (:func:`join`); else the jaw held at its
    opening (:func:`hold`). ``options``: :func:`time_joints`'s."""
    q = np.asarray(waypoints, np.float64)
    if q.ndim != 2 or len(q) != track.poses:
        raise ValueError(f"waypoints of shape {q.shape} are not accepted: one a pose of the jaw's track, {track.poses}")
    if not track.opens:
        return hold(time_joints(q, rate_hz, **options), track.from_deg)
    k = track.opens_at
    return join(time_joints(q[: k + 1], rate_hz, **options), time_joints(q[k:], rate_hz, **options), track)
