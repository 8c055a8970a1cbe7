"""The policy's network and its observation for one query, compiled with numba (the lean
planner's): :func:`regrasp_mjx.core.geometry.observation` and the members' MLPs in float32, written into
buffers made once per query.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from regrasp_mjx.envs.lean_geometry import canonical, relative


@njit(cache=True)
def _put(obs, at, v):
    for i in range(len(v)):
        obs[at + i] = v[i]


@njit(cache=True)
def observe(obs, general, needle_p, needle_q, ee_p, ee_q, goal_p, goal_q, radius, wire):
    """The observation (:func:`regrasp_mjx.core.geometry.observation`) written into ``obs`` (float32)."""
    _put(obs, 0, needle_p)
    _put(obs, 3, canonical(needle_q))
    _put(obs, 7, ee_p)
    _put(obs, 10, canonical(ee_q))
    p, q = relative(ee_p, ee_q, needle_p, needle_q)
    _put(obs, 14, p)
    _put(obs, 17, q)
    if general:
        p, q = relative(goal_p, goal_q, needle_p, needle_q)
        _put(obs, 21, p)
        _put(obs, 24, q)
        p, q = relative(ee_p, ee_q, goal_p, goal_q)
        _put(obs, 28, p)
        _put(obs, 31, q)
        obs[35] = radius
        obs[36] = wire


@njit(cache=True, fastmath=True)
def _hidden(x, kernel, bias, out, rows):
    """``out[:n] = relu(x[:m] @ kernel + bias)`` (float32, kernel ``[m, n]``), as rows of the kernel
    added in, four at a time: the inputs that ReLU zeroed (about half) are left out, their indices
    gathered first into ``rows`` without a branch (a data-dependent branch per input mispredicts
    half the time). Faster here than BLAS's gemv at this size."""
    n = kernel.shape[1]
    m = 0
    for i in range(kernel.shape[0]):
        rows[m] = i
        m += x[i] != 0.0
    for j in range(n):
        out[j] = bias[j]
    k = 0
    while k + 4 <= m:
        i0, i1, i2, i3 = rows[k], rows[k + 1], rows[k + 2], rows[k + 3]
        a0, a1, a2, a3 = x[i0], x[i1], x[i2], x[i3]
        for j in range(n):
            out[j] += (a0 * kernel[i0, j] + a1 * kernel[i1, j]) + (a2 * kernel[i2, j] + a3 * kernel[i3, j])
        k += 4
    while k < m:
        a0, i0 = x[rows[k]], rows[k]
        for j in range(n):
            out[j] += a0 * kernel[i0, j]
        k += 1
    for j in range(n):
        out[j] = max(out[j], np.float32(0.0))


@njit(cache=True, fastmath=True)
def _output(x, kernel_t, bias, out):
    """``out = tanh(x @ kernel + bias)`` with the kernel stored transposed (``[6, m]``): six dot
    products, each one pass over the hidden layer."""
    for j in range(kernel_t.shape[0]):
        acc = np.float32(0.0)
        for i in range(kernel_t.shape[1]):
            acc += x[i] * kernel_t[j, i]
        out[j] = np.tanh(acc + bias[j])


@njit(cache=True)
def member_actions(kernels, biases, layers, mean, std, obs, work, rows, own):
    """``own[m] = tanh(MLP_m(clip((obs - mean_m) / std_m, +-5)))`` for each member (float32;
    ``work``: two rows of the widest layer's buffers, the normalised observation in row 2; ``rows``:
    the widest layer's input indices)."""
    for m in range(mean.shape[0]):
        x = work[2]
        for i in range(obs.shape[0]):
            x[i] = min(max((obs[i] - mean[m, i]) / std[m, i], np.float32(-5.0)), np.float32(5.0))
        for k in range(layers - 1):
            out = work[k % 2]
            _hidden(x, kernels[m * layers + k], biases[m * layers + k], out, rows)
            x = out
        _output(x, kernels[m * layers + layers - 1], biases[m * layers + layers - 1], own[m])


@njit(cache=True)
def buffers(mean, biases):
    """What a step of the network and the shield write into, made once per query: the observation,
    the layers' work rows, the members' own actions, the action and a candidate."""
    width = max(mean.shape[1], biases[0].shape[0])
    for b in biases:
        width = max(width, b.shape[0])
    obs = np.empty(mean.shape[1], np.float32)
    work = np.zeros((3, width), np.float32)
    rows = np.empty(width, np.int64)
    own = np.empty((mean.shape[0], 6), np.float32)
    return obs, work, rows, own, np.empty(6, np.float32), np.empty(6, np.float32)
