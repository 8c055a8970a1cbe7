"""The moments of an error series and the fit of the camera-error model's three parts to them: per axis, a
bias fixed for an episode (variance ``B``), an AR(1) drift (variance ``D``, correlation ``exp(-L / tau)``
between frames ``L`` apart) and white noise (``W``), from the second moment about zero ``S0 = B + D + W``
and the within-episode semivariogram ``gamma(L) = W + D (1 - exp(-L / tau))``, from which the bias cancels
(:mod:`regrasp_mjx.vision.error_fit` turns them into the model's sizes).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

GRID = 241  # log-spaced correlation times, then golden-section refinement around the best


def moments(values: np.ndarray, episode: np.ndarray, frame: np.ndarray, max_lag: int):
    """The second moment about zero ``S0`` of ``values`` ``[N, C]`` (C components of one series, pooled;
    NaN rows left out) and their semivariogram ``gamma[L - 1]`` with its number of frame pairs
    ``pairs[L - 1]`` for ``L = 1 .. max_lag``: half the mean squared difference of two frames of one
    episode ``L`` apart (``frame`` numbers), over components and pairs (NaN where no pair)."""
    ok = np.all(np.isfinite(values), axis=-1)
    s0 = float(np.mean(values[ok] ** 2)) if ok.any() else math.nan
    ids, ep = np.unique(episode, return_inverse=True)
    dense = np.full((len(ids), int(frame.max()) + 1, values.shape[1]), np.nan)
    dense[ep[ok], frame[ok]] = values[ok]
    gamma, pairs = np.full(max_lag, np.nan), np.zeros(max_lag, np.int64)
    for lag in range(1, max_lag + 1):
        if lag >= dense.shape[1]:
            break
        diff = dense[:, lag:] - dense[:, :-lag]
        valid = np.all(np.isfinite(diff), axis=-1)
        pairs[lag - 1] = int(valid.sum())
        if pairs[lag - 1]:
            gamma[lag - 1] = 0.5 * float(np.mean(diff[valid] ** 2))
    return s0, gamma, pairs


def parts(s0: float, gamma: np.ndarray, weight: np.ndarray, g: np.ndarray) -> tuple[float, float, float]:
    """``(W, D, residual)`` minimising ``sum weight (gamma - W - D g)^2`` over ``W, D >= 0, W + D <= s0``
    (a convex quadratic on a triangle: its free minimum if inside, else the best on an edge)."""
    a = np.stack([np.ones_like(g), g], -1) * np.sqrt(weight)[:, None]
    b = gamma * np.sqrt(weight)

    def cost(x):
        return float(np.sum((a @ x - b) ** 2))

    q, c = a.T @ a, a.T @ b
    candidates = [np.zeros(2)]
    if abs(np.linalg.det(q)) > 1e-12 * max(q[0, 0] * q[1, 1], 1e-300):
        candidates.append(np.linalg.solve(q, c))
    for i in range(2):  # one of W, D zero: the other alone
        x = np.zeros(2)
        x[i] = np.clip(c[i] / q[i, i], 0.0, s0) if q[i, i] > 0 else 0.0
        candidates.append(x)
    # on W + D = s0: x = (s0 - t, t), a quadratic in t
    d = np.array([-1.0, 1.0])
    curvature = float(d @ q @ d)
    t = float(d @ (c - q @ np.array([s0, 0.0]))) / curvature if curvature > 0 else 0.0
    candidates.append(np.array([s0 - np.clip(t, 0.0, s0), np.clip(t, 0.0, s0)]))
    feasible = [x for x in candidates if x.min() >= -1e-15 and x.sum() <= s0 * (1 + 1e-12) + 1e-300]
    best = min(feasible, key=cost)
    best = np.maximum(best, 0.0)
    return float(best[0]), float(best[1]), cost(best)


def fit_series(stats: list[tuple[float, np.ndarray, np.ndarray]], tau_range: tuple[float, float]) -> dict[str, Any]:
    """One correlation time ``tau`` (in the data's frames, within ``tau_range``) for several series'
    :func:`moments` ``(S0, gamma, pairs)``, each series' residual scaled by its ``S0`` (so that series of
    other units weigh alike); returns ``tau`` and each series' ``(B, D, W)`` and fitted variogram."""
    lags = np.arange(1, len(stats[0][1]) + 1, dtype=np.float64)
    used = [(s0, np.nan_to_num(gam), pairs.astype(np.float64)) for s0, gam, pairs in stats]

    def total(tau: float) -> float:
        g = 1.0 - np.exp(-lags / tau)
        return sum(parts(s0, gam, w, g)[2] / s0**2 for s0, gam, w in used if s0 > 0)

    lo, hi = math.log(tau_range[0]), math.log(tau_range[1])
    grid = np.linspace(lo, hi, GRID)
    costs = np.array([total(math.exp(x)) for x in grid])
    i = int(np.argmin(costs))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, GRID - 1)]
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):  # golden section on log tau between the best point's neighbours
        x1, x2 = b - ratio * (b - a), a + ratio * (b - a)
        if total(math.exp(x1)) <= total(math.exp(x2)):
            b = x2
        else:
            a = x1
    tau = math.exp((a + b) / 2.0)
    if total(tau) > costs[i]:
        tau = math.exp(grid[i])
    at_bound = min(abs(math.log(tau) - lo), abs(math.log(tau) - hi)) < 0.01  # within 1 % of an end
    g = 1.0 - np.exp(-lags / tau)
    out = []
    for s0, gam, w in used:
        white, drift, _ = parts(s0, gam, w, g) if s0 > 0 else (0.0, 0.0, 0.0)
        out.append({"bias": max(s0 - drift - white, 0.0), "drift": drift, "white": white, "fitted": white + drift * g})
    return {"tau": tau, "series": out, "at_bound": at_bound}
