"""TOPP-RA for joint velocity and acceleration limits, compiled with numba: the clamped cubic spline
through a plan's joint waypoints and the time-optimal path velocities along it, what ``toppra``'s
``SplineInterpolator`` and ``TOPPRA(..., solver_wrapper="seidel")`` compute, in about a tenth of
their time.

Why not ``toppra`` itself: its passes over the grid are Python loops (about 30 microseconds a grid
point, a stage LP each) and its spline is scipy's, so one plan took 3.8-6 ms on one core against
issue 48's 1 ms (experiments/RESULTS.md). ``toppra`` stays the reference: ``time_joints(...,
engine="toppra")`` times with it, and tests/test_topp.py holds these functions to its results.

The algorithm (Pham and Pham 2018, "A new approach to time-optimal path parameterization based on
reachability analysis"), as ``toppra`` runs it for these constraints: the path velocity squared
``x = sd^2`` and acceleration ``u = sdd`` at grid point ``i``, ``x_{i+1} = x_i + 2 d_i u_i``;

- the joint velocity limits bound ``x_i <= min_j (v_j / |q'_j(s_i)|)^2``;
- the joint acceleration limits ``|q'_j u + q''_j x| <= a_j`` hold at ``s_i`` and, with ``(u_i,
  x_{i+1})``, at ``s_{i+1}`` (toppra's default "interpolation" discretisation);
- the backward pass finds each grid point's controllable interval ``K_i`` of ``x`` from ``K_{i+1}``
  (a two-variable LP: here solved exactly by eliminating ``u``, Fourier-Motzkin, every pair of an
  upper and a lower bound on ``u`` giving one bound on ``x``);
- the forward pass takes the largest ``u`` that keeps ``x_{i+1}`` in ``K_{i+1}``, with toppra's own
  safety shave (``x_{i+1}`` lowered by ``max(1e-8, 1e-4 x_{i+1})``) and its retries.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SD_CAP = 1e8  # toppra's JVEL_MAXSD: the path velocity bound where a joint does not move
TINY = 1e-8  # toppra's constants: the forward pass's shave and retry step
SMALL = 1e-5  # how far the start may lie outside K_0
MAX_TRIES = 10  # toppra's retries of a forward step with x reduced
SHAVE = 0.9999  # toppra's forward pass keeps x_{i+1} this far inside what the LP allows


@njit(cache=True)
def spline_coefficients(knots, q):
    """The C2 cubic spline through ``q`` ``[W, D]`` at increasing ``knots`` ``[W]``: clamped (zero
    slope at both ends) for W > 2, a straight line for W = 2 (scipy's ``CubicSpline`` with
    ``bc_type="clamped"`` / ``"natural"``, as ``toppra.SplineInterpolator`` makes it). Returns
    ``[W - 1, 4, D]``: each segment's ``(c0, c1, c2, c3)``, ``q = c0 + c1 t + c2 t^2 + c3 t^3`` with
    ``t`` from the segment's first knot."""
    w, d = q.shape
    h = knots[1:] - knots[:-1]
    m = np.empty((w - 1, d))
    for i in range(w - 1):
        for j in range(d):
            m[i, j] = (q[i + 1, j] - q[i, j]) / h[i]
    slope = np.zeros((w, d))
    if w == 2:
        for j in range(d):
            slope[0, j] = m[0, j]
            slope[1, j] = m[0, j]
    else:
        # interior slopes: h_i s_{i-1} + 2 (h_{i-1} + h_i) s_i + h_{i-1} s_{i+1} = 3 (h_i m_{i-1} + h_{i-1} m_i),
        # s_0 = s_{W-1} = 0, solved by the Thomas algorithm (diagonally dominant)
        n = w - 2
        diag = np.empty(n)
        rhs = np.empty((n, d))
        for k in range(n):
            i = k + 1
            diag[k] = 2.0 * (h[i - 1] + h[i])
            for j in range(d):
                rhs[k, j] = 3.0 * (h[i] * m[i - 1, j] + h[i - 1] * m[i, j])
        for k in range(1, n):
            f = h[k + 1] / diag[k - 1]  # row k's sub-diagonal (h_i) over the previous pivot
            diag[k] -= f * h[k - 1]  # the previous row's super-diagonal (h_{i-2})
            for j in range(d):
                rhs[k, j] -= f * rhs[k - 1, j]
        for j in range(d):
            slope[n, j] = rhs[n - 1, j] / diag[n - 1]
        for k in range(n - 2, -1, -1):
            for j in range(d):
                slope[k + 1, j] = (rhs[k, j] - h[k] * slope[k + 2, j]) / diag[k]
    coef = np.empty((w - 1, 4, d))
    for i in range(w - 1):
        for j in range(d):
            coef[i, 0, j] = q[i, j]
            coef[i, 1, j] = slope[i, j]
            coef[i, 2, j] = (3.0 * m[i, j] - 2.0 * slope[i, j] - slope[i + 1, j]) / h[i]
            coef[i, 3, j] = (slope[i, j] + slope[i + 1, j] - 2.0 * m[i, j]) / (h[i] * h[i])
    return coef


@njit(cache=True)
def _segment(knots, s):
    """The index ``i`` of the last of ``knots[:-1]`` at or below ``s`` (0 below the first): bisection."""
    lo, hi = 0, len(knots) - 2
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if knots[mid] <= s:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(cache=True)
def _eval_all(knots, coef, s, q, dq, ddq, row):
    """The spline's value and first two derivatives at ``s`` into row ``row`` of ``q``, ``dq``, ``ddq``."""
    i = _segment(knots, s)
    t = s - knots[i]
    for j in range(coef.shape[2]):
        q[row, j] = coef[i, 0, j] + t * (coef[i, 1, j] + t * (coef[i, 2, j] + t * coef[i, 3, j]))
        dq[row, j] = coef[i, 1, j] + t * (2.0 * coef[i, 2, j] + 3.0 * t * coef[i, 3, j])
        ddq[row, j] = 2.0 * coef[i, 2, j] + 6.0 * t * coef[i, 3, j]


@njit(cache=True)
def spline_eval(knots, coef, s, order):
    """The spline's ``order``-th derivative (0, 1 or 2) at points ``s`` ``[N]``: ``[N, D]`` (a point
    past the ends is on the end segment's polynomial, as scipy extrapolates)."""
    shape = (len(s), coef.shape[2])
    q, dq, ddq = np.empty(shape), np.empty(shape), np.empty(shape)
    for k in range(len(s)):
        _eval_all(knots, coef, s[k], q, dq, ddq, k)
    return q if order == 0 else dq if order == 1 else ddq


@njit(cache=True)
def motion_ratio(knots, coef, grid, sd, per_interval, v_max, a_max):
    """The uniform slow-down ``r`` (time x r) that keeps the limits everywhere the motion of path
    velocities ``sd`` at ``grid`` goes (the path acceleration constant between grid points, as
    sampled): ``max(|qd| / v_max, sqrt(|qdd| / a_max))`` at both ends of every grid interval and
    ``per_interval`` points evenly inside it, ``qd = q' v`` and ``qdd = q'' v^2 + q' u``."""
    d = coef.shape[2]
    q, dq, ddq = np.empty((1, d)), np.empty((1, d)), np.empty((1, d))
    rv, ra = 0.0, 0.0
    for i in range(len(grid) - 1):
        ds = grid[i + 1] - grid[i]
        u = 0.5 * (sd[i + 1] * sd[i + 1] - sd[i] * sd[i]) / ds
        for k in range(per_interval + 2):
            h = k / (per_interval + 1) * ds
            v = math.sqrt(max(sd[i] * sd[i] + 2.0 * u * h, 0.0))
            _eval_all(knots, coef, grid[i] + h, q, dq, ddq, 0)
            for j in range(d):
                rv = max(rv, abs(dq[0, j] * v) / v_max[j])
                ra = max(ra, abs(ddq[0, j] * v * v + dq[0, j] * u) / a_max[j])
    return max(rv, math.sqrt(ra))


@njit(cache=True)
def sample(knots, coef, grid, sd, rate_hz):
    """Times ``[N]`` and joint positions, velocities and accelerations ``[N, D]`` at ``rate_hz`` along
    the motion of path velocities ``sd`` at ``grid``, the path acceleration constant between grid
    points (``toppra.parametrizer.ParametrizeConstAccel``'s trajectory); the last sample at the end."""
    n = len(grid) - 1
    u = np.empty(n)
    at = np.zeros(n + 1)  # the time each grid point is reached
    for i in range(n):
        ds = grid[i + 1] - grid[i]
        u[i] = 0.5 * (sd[i + 1] * sd[i + 1] - sd[i] * sd[i]) / ds
        at[i + 1] = at[i] + 2.0 * ds / (sd[i] + sd[i + 1])
    step = 1.0 / rate_hz
    count = max(int(math.ceil(at[n] / step)), 0)  # np.arange(0, end, step)'s length
    end_is_sampled = count > 0 and at[n] - (count - 1) * step < 1e-9  # a sample within 1 ns stands for the end
    t = np.empty(count if end_is_sampled else count + 1)
    for k in range(count):
        t[k] = k * step
    if not end_is_sampled:
        t[count] = at[n]
    d = coef.shape[2]
    q, qd, qdd = np.empty((len(t), d)), np.empty((len(t), d)), np.empty((len(t), d))
    for k in range(len(t)):
        i = _segment(at, t[k])
        dt = t[k] - at[i]
        v = sd[i] + dt * u[i]
        _eval_all(knots, coef, grid[i] + dt * sd[i] + 0.5 * dt * dt * u[i], q, qd, qdd, k)
        for j in range(d):
            qdd[k, j] = qdd[k, j] * v * v + qd[k, j] * u[i]
            qd[k, j] = qd[k, j] * v
    return t, q, qd, qdd


@njit(cache=True)
def _stage_rows(dq, ddq, grid, i, a_max, k_lo, k_hi, alpha, beta, gamma):
    """The rows ``alpha u + beta x <= gamma`` of grid point ``i``'s LP written into the arrays, their
    count returned: the acceleration limits (both signs, at ``s_i`` and, for ``(u_i, x_{i+1})``, at
    ``s_{i+1}``) and ``x_{i+1} = x + 2 d u`` within ``[k_lo, k_hi]`` of grid point ``i + 1``."""
    d = dq.shape[1]
    delta = grid[i + 1] - grid[i]
    r = 0
    for at in range(2):
        j_at = i + at
        for j in range(d):
            a = dq[j_at, j] + (2.0 * delta * ddq[j_at, j] if at == 1 else 0.0)
            b = ddq[j_at, j]
            alpha[r], beta[r], gamma[r] = a, b, a_max[j]
            alpha[r + 1], beta[r + 1], gamma[r + 1] = -a, -b, a_max[j]
            r += 2
    alpha[r], beta[r], gamma[r] = 2.0 * delta, 1.0, k_hi[i + 1]
    alpha[r + 1], beta[r + 1], gamma[r + 1] = -2.0 * delta, -1.0, -k_lo[i + 1]
    return r + 2


@njit(cache=True)
def _x_interval(alpha, beta, gamma, rows, lo, hi):
    """The interval of ``x`` in ``[lo, hi]`` for which some ``u`` meets every row ``alpha u + beta x
    <= gamma``: ``u`` eliminated (Fourier-Motzkin), each row without ``u`` and each pair of an upper
    and a lower bound on ``u`` a bound on ``x``. Empty where ``lo > hi``."""
    for p in range(rows):
        if alpha[p] == 0.0:
            if beta[p] > 0.0:
                hi = min(hi, gamma[p] / beta[p])
            elif beta[p] < 0.0:
                lo = max(lo, gamma[p] / beta[p])
            elif gamma[p] < 0.0:
                return 1.0, 0.0
            continue
        if alpha[p] > 0.0:
            continue
        for q in range(rows):
            if alpha[q] <= 0.0:
                continue
            c = alpha[q] * beta[p] - alpha[p] * beta[q]  # alpha_q (row p) - alpha_p (row q): u cancels
            g = alpha[q] * gamma[p] - alpha[p] * gamma[q]
            if c > 0.0:
                hi = min(hi, g / c)
            elif c < 0.0:
                lo = max(lo, g / c)
            elif g < 0.0:
                return 1.0, 0.0
    return lo, hi


@njit(cache=True)
def _u_range(alpha, beta, gamma, rows, x):
    """The range ``[lo, hi]`` of ``u`` that meets every row at ``x``."""
    lo, hi = -np.inf, np.inf
    for r in range(rows):
        if alpha[r] > 0.0:
            hi = min(hi, (gamma[r] - beta[r] * x) / alpha[r])
        elif alpha[r] < 0.0:
            lo = max(lo, (gamma[r] - beta[r] * x) / alpha[r])
    return lo, hi


@njit(cache=True)
def path_velocities(dq, ddq, grid, v_max, a_max):
    """TOPP-RA's path velocities ``sd`` ``[N + 1]`` at ``grid`` ``[N + 1]`` for a path whose joint
    derivatives there are ``dq`` and ``ddq`` ``[N + 1, D]``, at rest at both ends (see the module's
    docstring); all NaN where no parameterisation exists."""
    n = len(grid) - 1
    d = dq.shape[1]
    xmax = np.empty(n + 1)
    for i in range(n + 1):
        sd = SD_CAP
        for j in range(d):
            if dq[i, j] != 0.0:
                sd = min(sd, v_max[j] / abs(dq[i, j]))
        xmax[i] = sd * sd
    rows_max = 4 * d + 2
    alpha, beta, gamma = np.empty(rows_max), np.empty(rows_max), np.empty(rows_max)
    k_lo, k_hi = np.zeros(n + 1), np.zeros(n + 1)
    failed = np.full(n + 1, np.nan)
    for i in range(n - 1, -1, -1):  # the controllable sets, backward from K_N = {0}
        rows = _stage_rows(dq, ddq, grid, i, a_max, k_lo, k_hi, alpha, beta, gamma)
        lo, hi = _x_interval(alpha, beta, gamma, rows, 0.0, xmax[i])
        if not lo <= hi:
            return failed
        k_lo[i], k_hi[i] = lo, hi
    if k_lo[0] > SMALL:  # the start at rest is not controllable
        return failed
    xs = np.zeros(n + 1)
    i, tries = 0, 0
    while i < n:  # forward: the fastest u that stays controllable
        rows = _stage_rows(dq, ddq, grid, i, a_max, k_lo, k_hi, alpha, beta, gamma)
        u_lo, u_hi = _u_range(alpha, beta, gamma, rows, xs[i])
        if not u_lo <= u_hi:  # just infeasible by rounding: toppra's remedy, x lowered a little
            if tries >= MAX_TRIES:
                return failed
            xs[i] = max(xs[i] - TINY, 0.999 * xs[i])
            tries += 1
            continue
        tries = 0
        x_next = xs[i] + 2.0 * (grid[i + 1] - grid[i]) * u_hi
        x_next = max(x_next - TINY, SHAVE * x_next)
        xs[i + 1] = min(k_hi[i + 1], max(k_lo[i + 1], x_next))
        i += 1
    out = np.empty(n + 1)
    for k in range(n + 1):
        out[k] = math.sqrt(xs[k])
    return out


class Spline:
    """The compiled clamped cubic spline through joint waypoints ``q`` ``[W >= 2, D]`` at ``knots``;
    called as ``toppra.SplineInterpolator`` is: ``path(s, order=0)`` ``[N, D]``."""

    def __init__(self, knots: np.ndarray, q: np.ndarray):
        self.knots = np.ascontiguousarray(knots, np.float64)
        self.coef = spline_coefficients(self.knots, np.ascontiguousarray(q, np.float64))

    def __call__(self, s, order: int = 0) -> np.ndarray:
        s = np.asarray(s, np.float64)
        return spline_eval(self.knots, self.coef, np.ascontiguousarray(s.reshape(-1)), order).reshape(
            *s.shape, self.coef.shape[2]
        )
