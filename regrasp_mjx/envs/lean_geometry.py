"""Pose algebra for one query, compiled with numba (the lean planner's): the quantities of
:mod:`regrasp_mjx.core.geometry` for one pose at a time, the goal pose of a goal grasp, the distance
to the nearest pose of the grasp library, and the capsules' segment distances.

3-vectors and wxyz quaternions are tuples of floats and rotation matrices tuples of nine
(row-major), so the per-step work allocates nothing on the heap (an array of four floats costs more
to allocate than to compute with). Geometry is float64 here.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# ---- pose algebra: 3-tuples, wxyz 4-tuples, row-major 9-tuples ------------------------------------


@njit(cache=True)
def qmul(a, b):
    return (
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


@njit(cache=True)
def conj(q):
    return (q[0], -q[1], -q[2], -q[3])


@njit(cache=True)
def canonical(q):
    """The same rotation with ``w >= 0`` (the observation's convention)."""
    return (-q[0], -q[1], -q[2], -q[3]) if q[0] < 0.0 else q


@njit(cache=True)
def unit(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@njit(cache=True)
def qexp(vx, vy, vz):
    """jaxlie's ``SO3.exp``: the Taylor branch below its float32 epsilon, as the JAX path takes it."""
    th2 = vx * vx + vy * vy + vz * vz
    if th2 < 1e-5:
        real = 1.0 - th2 / 8.0 + th2 * th2 / 384.0
        imag = 0.5 - th2 / 48.0 + th2 * th2 / 3840.0
    else:
        th = math.sqrt(th2)
        real = math.cos(0.5 * th)
        imag = math.sin(0.5 * th) / th
    return (real, imag * vx, imag * vy, imag * vz)


@njit(cache=True)
def log_rotation(q):
    """The rotation vector of the unit quaternion ``q`` the shorter way round (angle in [0, pi]):
    ``qexp(*log_rotation(q))`` is ``q`` up to sign."""
    w, x, y, z = q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-12:
        return (2.0 * x, 2.0 * y, 2.0 * z)
    f = 2.0 * math.atan2(n, w) / n
    return (f * x, f * y, f * z)


@njit(cache=True)
def matrix(q):
    w, x, y, z = q
    return (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )


@njit(cache=True)
def rotate(m, x, y, z):
    """``m @ (x, y, z)``."""
    return (m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z, m[6] * x + m[7] * y + m[8] * z)


@njit(cache=True)
def relative(ap, aq, bp, bq):
    """``T_a_b``: pose b seen from frame a (both in one frame), quaternion canonical."""
    m = matrix(aq)
    dx, dy, dz = bp[0] - ap[0], bp[1] - ap[1], bp[2] - ap[2]
    p = (m[0] * dx + m[3] * dy + m[6] * dz, m[1] * dx + m[4] * dy + m[7] * dz, m[2] * dx + m[5] * dy + m[8] * dz)
    return p, canonical(qmul(conj(aq), bq))


@njit(cache=True)
def angle(q1, q2):
    d = qmul(q1, conj(q2))
    return 2.0 * math.atan2(math.sqrt(d[1] * d[1] + d[2] * d[2] + d[3] * d[3]), abs(d[0]))


@njit(cache=True)
def from_matrix(m):
    """The unit quaternion (w >= 0) of a rotation matrix (Shepperd's method: the largest of the four
    squares first, for accuracy)."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    tr = m00 + m11 + m22
    if tr > m00 and tr > m11 and tr > m22:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    return canonical(unit(q))


@njit(cache=True)
def goal_pose(needle, alpha, depth, theta, phi, radius):
    """The goal end-effector pose ``[7]`` (e_g) of a goal grasp on a needle: ``needle ∘
    grasp_pose(...)`` (:func:`regrasp_mjx.core.geometry.grasp_pose`, paper eq. 3, and ``compose``)."""
    ox, oy, oz = depth * math.cos(phi), depth * math.sin(phi) * math.cos(theta), depth * math.sin(phi) * math.sin(theta)
    px, py, pz = ox, radius * math.cos(alpha) + oy, radius * math.sin(alpha) + oz
    n = math.sqrt(ox * ox + oy * oy + oz * oz)
    zx, zy, zz = -ox / n, -oy / n, -oz / n
    tx, ty, tz = 0.0, -math.sin(alpha), math.cos(alpha)
    tz_dot = tx * zx + ty * zy + tz * zz
    xx, xy, xz = tx - tz_dot * zx, ty - tz_dot * zy, tz - tz_dot * zz
    if math.sqrt(xx * xx + xy * xy + xz * xz) < 1e-6:  # the jaws along the wire: the needle-plane normal instead
        xx, xy, xz = 1.0 - zx * zx, -zx * zy, -zx * zz
    n = math.sqrt(xx * xx + xy * xy + xz * xz)
    xx, xy, xz = xx / n, xy / n, xz / n
    yx, yy, yz = zy * xz - zz * xy, zz * xx - zx * xz, zx * xy - zy * xx
    q_n = unit((needle[3], needle[4], needle[5], needle[6]))
    w = rotate(matrix(q_n), px, py, pz)
    q = canonical(qmul(q_n, from_matrix((xx, yx, zx, xy, yy, zy, xz, yz, zz))))
    return np.array([needle[0] + w[0], needle[1] + w[1], needle[2] + w[2], q[0], q[1], q[2], q[3]])


# ---- the grasp library (regrasp_mjx.grasps) ------------------------------------------------------


@njit(cache=True)
def _grasp_distance(library_p, library_q, needle, i):
    dx, dy, dz = needle[0] - library_p[i, 0], needle[1] - library_p[i, 1], needle[2] - library_p[i, 2]
    q = library_q[i]
    c = min(abs(needle[3] * q[0] + needle[4] * q[1] + needle[5] * q[2] + needle[6] * q[3]), 1.0)
    return math.sqrt(dx * dx + dy * dy + dz * dz) * 1e3 + math.degrees(2.0 * math.acos(c)) / 5.0


@njit(cache=True, fastmath=True)
def _grasp_bounds(columns, needle, out):
    """Lower bounds of every library pose's distance (float32, vectorised: positions and unit
    quaternions as ``columns[7, n]``): ``|dp|`` plus the angle's bound ``2 sqrt(2 (1 - c))``
    (``1 - cos x <= x^2 / 2``), less a slack for float32's rounding."""
    x, y, z = np.float32(needle[0]), np.float32(needle[1]), np.float32(needle[2])
    w, a, b, c = np.float32(needle[3]), np.float32(needle[4]), np.float32(needle[5]), np.float32(needle[6])
    to_mm, per_rad = np.float32(1e3), np.float32(2.0 * 180.0 / math.pi / 5.0)
    for i in range(columns.shape[1]):
        dx, dy, dz = x - columns[0, i], y - columns[1, i], z - columns[2, i]
        cos = min(abs(w * columns[3, i] + a * columns[4, i] + b * columns[5, i] + c * columns[6, i]), np.float32(1.0))
        d = math.sqrt(dx * dx + dy * dy + dz * dz) * to_mm + per_rad * math.sqrt(
            np.float32(2.0) * (np.float32(1.0) - cos)
        )
        out[i] = d * np.float32(0.999) - np.float32(1e-3)


@njit(cache=True)
def nearest_grasp(library_p, library_q, columns, needle):
    """The distance of a needle pose ``[7]`` (unit quaternion) to the nearest of the grasp library's
    (positions ``[n, 3]`` m and unit quaternions ``[n, 4]``, float64, and the same as float32
    ``columns[7, n]``): ``|dp| mm + angle deg / 5`` (:func:`regrasp_mjx.grasps.pose_distance`).
    The angle costs an ``acos``: every pose is bounded from below first (:func:`_grasp_bounds`), and
    the exact distance is computed only where the bound is below the best so far, the lowest first."""
    bound = np.empty(columns.shape[1], np.float32)
    _grasp_bounds(columns, needle, bound)
    first = np.argmin(bound)
    best = _grasp_distance(library_p, library_q, needle, first)
    for i in range(bound.shape[0]):
        if bound[i] < best and i != first:
            best = min(best, _grasp_distance(library_p, library_q, needle, i))
    return best


# ---- distances -----------------------------------------------------------------------------------


@njit(cache=True)
def segment_gap(e, i, f, j):
    """Ericson's closest points of segments ``e[i]`` and ``f[j]`` (``[., 2, 3]`` end points): the
    vector from ``f[j]``'s to ``e[i]``'s, as :func:`regrasp_mjx.core.geometry.segment_gap`; scalar
    code, nothing allocated."""
    d1x, d1y, d1z = e[i, 1, 0] - e[i, 0, 0], e[i, 1, 1] - e[i, 0, 1], e[i, 1, 2] - e[i, 0, 2]
    d2x, d2y, d2z = f[j, 1, 0] - f[j, 0, 0], f[j, 1, 1] - f[j, 0, 1], f[j, 1, 2] - f[j, 0, 2]
    rx, ry, rz = e[i, 0, 0] - f[j, 0, 0], e[i, 0, 1] - f[j, 0, 1], e[i, 0, 2] - f[j, 0, 2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    ee = d2x * d2x + d2y * d2y + d2z * d2z
    b = d1x * d2x + d1y * d2y + d1z * d2z
    c = d1x * rx + d1y * ry + d1z * rz
    ff = d2x * rx + d2y * ry + d2z * rz
    denom = a * ee - b * b
    s = 0.0
    if denom > 1e-9 * a * ee:
        s = min(max((b * ff - c * ee) / denom, 0.0), 1.0)
    t = (b * s + ff) / ee
    if t < 0.0:
        s = min(max(-c / a, 0.0), 1.0)
        t = 0.0
    elif t > 1.0:
        s = min(max((b - c) / a, 0.0), 1.0)
        t = 1.0
    return rx + d1x * s - d2x * t, ry + d1y * s - d2y * t, rz + d1z * s - d2z * t


@njit(cache=True)
def segment_distance(e, i, f, j):
    """The distance of segments ``e[i]`` and ``f[j]``: the length of :func:`segment_gap`."""
    x, y, z = segment_gap(e, i, f, j)
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def point_distance(seg, i, px, py, pz):
    """Distance of the point ``(px, py, pz)`` to the segment ``seg[i]`` (scalar code)."""
    dx, dy, dz = seg[i, 1, 0] - seg[i, 0, 0], seg[i, 1, 1] - seg[i, 0, 1], seg[i, 1, 2] - seg[i, 0, 2]
    px, py, pz = px - seg[i, 0, 0], py - seg[i, 0, 1], pz - seg[i, 0, 2]
    s = min(max((px * dx + py * dy + pz * dz) / (dx * dx + dy * dy + dz * dz), 0.0), 1.0)
    x, y, z = px - s * dx, py - s * dy, pz - s * dz
    return math.sqrt(x * x + y * y + z * z)
