"""The exact distance to the true needle (a wire of radius w about a semicircle of radius R: a
torus piece with round ends), the reference the capsule-chord model is measured against.

Frames: the needle frame n (centre of the circle, needle in the y-z plane, angles 90-270 degrees
from +y, tip at +z). Slow (numpy, a dense sample refined per segment): for tests and experiments.
"""

from __future__ import annotations

import math

import numpy as np


def point_distance(p: np.ndarray, radius: float, wire: float) -> np.ndarray:
    """Exact signed distance of points ``[n, 3]`` (frame n) to the true wire's surface [m]."""
    x, y, z = np.asarray(p, np.float64).T
    rho, angle = np.hypot(y, z), np.mod(np.arctan2(z, y), 2 * np.pi)
    on_arc = (angle >= np.pi / 2) & (angle <= 3 * np.pi / 2)
    ends = np.array([[0.0, 0.0, radius], [0.0, 0.0, -radius]])
    to_end = np.linalg.norm(np.asarray(p)[:, None] - ends[None], axis=-1).min(axis=1)
    return np.where(on_arc, np.hypot(x, rho - radius), to_end) - wire


def nearest_wire_point(p: np.ndarray, radius: float) -> np.ndarray:
    """The point of the wire's centre line (the arc) nearest to ``p`` ``[3]``."""
    y, z = p[1], p[2]
    angle = math.atan2(z, y) % (2 * math.pi)
    if math.pi / 2 <= angle <= 3 * math.pi / 2 and math.hypot(y, z) > 0:
        return np.array([0.0, y, z]) * radius / math.hypot(y, z)
    ends = np.array([[0.0, 0.0, radius], [0.0, 0.0, -radius]])
    return ends[np.argmin(np.linalg.norm(ends - p, axis=1))]


def segment_distance(a0: np.ndarray, a1: np.ndarray, radius: float, wire: float) -> tuple[float, float]:
    """Exact clearance of the segment ``[a0, a1]`` (frame n) to the true wire [m] and the segment
    parameter where it is reached: the point distance (exact, 1-Lipschitz) on 4001 points along
    it, then golden-section refinement about each local minimum to 1e-12 of the parameter."""
    a0, a1 = np.asarray(a0, np.float64), np.asarray(a1, np.float64)
    ts = np.linspace(0.0, 1.0, 4001)

    def f(t):
        return point_distance(a0 + np.atleast_1d(t)[:, None] * (a1 - a0), radius, wire)

    values = f(ts)
    best, best_t = float(values.min()), float(ts[values.argmin()])
    minima = np.nonzero((values <= np.roll(values, 1)) & (values <= np.roll(values, -1)))[0]
    g = (math.sqrt(5) - 1) / 2
    for i in list(minima) + [0, len(ts) - 1]:
        lo, hi = ts[max(i - 1, 0)], ts[min(i + 1, len(ts) - 1)]
        while hi - lo > 1e-12:
            m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
            if f(m1)[0] <= f(m2)[0]:
                hi = m2
            else:
                lo = m1
        t = 0.5 * (lo + hi)
        value = float(f(t)[0])
        if value < best:
            best, best_t = value, t
    return best, best_t
