"""The compiled TOPP-RA (regrasp_mjx.robot.topp) against the library it replaces on the plan's path:
the clamped spline is scipy's (toppra's ``SplineInterpolator``), the path velocities are
``toppra.algorithm.TOPPRA(..., solver_wrapper="seidel")``'s, and a timed trajectory is the same
with either engine."""

from __future__ import annotations

import numpy as np
import pytest
import toppra
import toppra.algorithm

from regrasp_mjx.robot import psm_timing, topp
from regrasp_mjx.robot.psm_timing import A_MAX, V_MAX, knot_grid, time_joints


def _walks(count: int, seed: int):
    """Random joint walks of 2 to 11 waypoints, knots spaced as ``raw_timing`` spaces them."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        w = int(rng.integers(2, 12))
        q = 0.1 + np.cumsum(rng.normal(0, [0.05, 0.05, 0.01, 0.5, 0.5, 0.5], (w, 6)), axis=0)
        knots = np.r_[0.0, np.cumsum(np.max(np.abs(np.diff(q, axis=0)) / V_MAX, axis=1))]
        yield q, knots / knots[-1]


def test_the_spline_is_scipy_s_clamped_one_and_a_line_through_two_points():
    """Value and first two derivatives at the grid, at and between the knots, within 1e-12 of
    ``toppra.SplineInterpolator`` (clamped for 3+ waypoints, natural, a line, for 2); the hand-worked
    two-point case: the line's slope and no curvature."""
    for q, knots in _walks(40, seed=3):
        reference = toppra.SplineInterpolator(knots, q, bc_type="clamped" if len(q) > 2 else "natural")
        mine = topp.Spline(knots, q)
        s = np.r_[knot_grid(knots), 0.37]
        for order in range(3):
            np.testing.assert_allclose(mine(s, order), reference(s, order), rtol=0, atol=1e-12)
        np.testing.assert_allclose(mine(knots), q, rtol=0, atol=1e-14)
    line = topp.Spline(np.array([0.0, 0.5]), np.array([[1.0, 2.0], [2.0, 0.0]]))
    np.testing.assert_allclose(line(np.array([0.25]), 1), [[2.0, -4.0]])
    np.testing.assert_allclose(line(np.array([0.25]), 2), [[0.0, 0.0]])


def test_the_path_velocities_are_toppra_s_own():
    """On 40 random walks (2 to 11 waypoints, the default grid), the compiled passes give toppra's
    path velocities to 1e-9 of their largest: the same LP at every grid point (both acceleration
    rows of the interpolation scheme), the same forward shave (leaving either out moves them by
    about 1e-4)."""
    limits = psm_timing._constraints(tuple(V_MAX), tuple(A_MAX))
    for q, knots in _walks(40, seed=4):
        grid = knot_grid(knots)
        reference = toppra.SplineInterpolator(knots, q, bc_type="clamped" if len(q) > 2 else "natural")
        solver = toppra.algorithm.TOPPRA(limits, reference, gridpoints=grid, solver_wrapper="seidel")
        solver.compute_parameterization(0.0, 0.0)
        path = topp.Spline(knots, q)
        sd = topp.path_velocities(path(grid, 1), path(grid, 2), grid, V_MAX, A_MAX)
        expect = solver.problem_data.sd_vec
        assert np.max(np.abs(sd - expect)) <= 1e-9 * np.max(expect), len(q)


def test_either_engine_gives_the_same_timed_trajectory_and_others_are_refused():
    """``time_joints`` with the compiled passes and with toppra's: the same samples (1e-9) and
    duration; an unknown engine is refused by name."""
    rng = np.random.default_rng(7)
    q = np.cumsum(
        np.r_[[[0.1, -0.2, 0.15, 0.3, 0.1, -0.2]], rng.normal(0, [0.02, 0.02, 1e-3, 0.1, 0.1, 0.1], (7, 6))], 0
    )
    mine, reference = time_joints(q), time_joints(q, engine="toppra")
    assert mine.duration_s == pytest.approx(reference.duration_s, rel=1e-9) and len(mine.t) == len(reference.t)
    for a, b in ((mine.q, reference.q), (mine.qd, reference.qd), (mine.qdd, reference.qdd)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="engine='ruckig' is not accepted: one of 'compiled', 'toppra'"):
        time_joints(q, engine="ruckig")
