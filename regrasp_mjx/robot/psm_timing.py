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
ENGINES = ("compiled", "toppra")  # time_joints' TOPP-RA: regrasp_mjx.robot.topp, or the toppra library


@dataclasses.dataclass(frozen=True)
class TimedTrajectory:
    """Joint positions ``q``, velocities ``qd`` and accelerations ``qdd`` ``[N, 6]`` at times ``t``
    ``[N]`` (s, from 0, at ``rate_hz``; the last sample is the end), through ``waypoints`` ``[W, 6]``."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    waypoints: np.ndarray
    rate_hz: float

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
