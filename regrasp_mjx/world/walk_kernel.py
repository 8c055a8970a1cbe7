"""The continuous test of a batch of steps as one Pallas kernel: each lane walks its intervals in registers.

:func:`regrasp_mjx.world.continuous_walk.motion_collides` on an accelerator runs its walk as XLA loops over
the whole batch: every loop iteration is a chain of small kernels and a wait for the device, and a
batch of 32,768 has a lane that grazes the wire every step (issue 44: about 280 kernels a step). Here
the root test and the walk of :func:`~regrasp_mjx.world.continuous.motion_collides_host` run in one
kernel (Pallas, lowered to Triton on a GPU): a program takes :data:`BLOCK` lanes (one: a warp a
lane), lays each lane's counted capsules across its threads, poses the lane's tool at the interval's
midpoint, computes every pair's distance and both lower bounds
(:func:`~regrasp_mjx.world.continuous.interval_low`, the same formulas in the same order, float32),
takes the least over the pairs and advances the depth-first walk
(:func:`~regrasp_mjx.world.continuous_walk._advance`), looping until its own lanes are done: a grazing
lane holds up its own program alone, where an XLA loop holds up the batch.

The verdicts are those of the XLA path up to float32 rounding (the kernel's compiler may contract
products and sums differently; both are within :data:`~regrasp_mjx.world.continuous.SLACK` of the
exact bounds): 0 of 655,360 random-action steps differ on an H200 (experiments/RESULTS.md, "Verdicts"),
and tests/test_walk_kernel.py compares them lane by lane in Pallas's interpreter.

Data: ``lanes [16, B]`` (position, quaternion, translation, rotation vector, fastest ``v_t``,
pending: a lane's values down a column) and ``others [B, 8, W]`` (each counted capsule's two end
points and radius, per lane, as the needle's chords move with the lane's needle; W the count rounded
up to a power of two, Triton's tiles, the spare columns far away). The regrasping tool's capsules
(end points in its frame, radii, levers) and the margin are constants of the scene, compiled into
the kernel; where the jaws open on the way (issue 67) a lane's last row says how far its jaws are
turned from the scene's opening, and the kernel turns those two capsules per lane.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from regrasp_mjx.core.geometry import segment_params
from regrasp_mjx.world.continuous import RESOLUTION, SLACK
from regrasp_mjx.world.continuous_walk import Walk, _advance

# lanes a program walks (a grazing lane holds up this many), their pairs across NUM_WARPS warps
BLOCK = 1
NUM_WARPS = 1
FAR = 1e3  # [m] where the tiles' spare columns put their capsules
# whether the MJX environment tests its steps with this kernel; None: on a GPU (a CPU runs the XLA
# walk: Pallas has no CPU backend but its interpreter). Read when the step is traced
KERNEL: bool | None = None


def use_kernel() -> bool:
    """Whether a step traced now tests its motion with the kernel (:data:`KERNEL`)."""
    return jax.default_backend() == "gpu" if KERNEL is None else KERNEL


_LANE_ROWS = 16  # pos 3, quat 4, dp 3, rotvec 3, fastest, pending, jaw turn (a power of two, Triton's blocks)
_OTHER_ROWS = 8  # end 0 (3), end 1 (3), radius, unused


# ---- three-vectors as tuples of lane vectors: elementwise arithmetic, as the XLA path computes it
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _quat_exp(w):
    """``exp`` of a rotation vector as jaxlie's ``SO3.exp`` computes it (its Taylor branch too)."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    theta4 = theta2 * theta2
    taylor = theta2 < 1e-5  # jaxlie's float32 epsilon
    theta = jnp.sqrt(jnp.where(taylor, 1.0, theta2))
    real = jnp.where(taylor, 1.0 - theta2 / 8.0 + theta4 / 384.0, jnp.cos(0.5 * theta))
    imag = jnp.where(taylor, 0.5 - theta2 / 48.0 + theta4 / 3840.0, jnp.sin(0.5 * theta) / theta)
    return (real, imag * w[0], imag * w[1], imag * w[2])


def _quat_mul(a, b):
    """The Hamilton product ``a b`` as jaxlie's ``SO3.multiply`` sums it."""
    w0, x0, y0, z0 = a
    w1, x1, y1, z1 = b
    return (
        w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1,
        w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
        w0 * y1 + y0 * w1 + z0 * x1 - x0 * z1,
        w0 * z1 + z0 * w1 + x0 * y1 - y0 * x1,
    )


def _matrix(q):
    """Rows of the rotation matrix of ``q`` as jaxlie's ``SO3.as_matrix`` computes them."""
    norm2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    f = jnp.sqrt(2.0 / norm2)
    w, x, y, z = (c * f for c in q)
    return (
        (1.0 - y * y - z * z, x * y - z * w, x * z + y * w),
        (x * y + z * w, 1.0 - x * x - z * z, y * z - x * w),
        (x * z - y * w, y * z + x * w, 1.0 - x * x - y * y),
    )


def _place(rows, pos, end):
    """``pos + R end`` for a constant ``end`` in the tool's frame (products and sums, as the scene's ``place``)."""
    return tuple(pos[a] + (rows[a][0] * end[0] + rows[a][1] * end[1] + rows[a][2] * end[2]) for a in range(3))


def _segment_gap(a0, a1, b0, b1):
    """:func:`regrasp_mjx.core.geometry.segment_gap` on tuples of lane vectors."""
    d1, d2, r = _sub(a1, a0), _sub(b1, b0), _sub(a0, b0)
    s, t = segment_params(_dot(d1, d1), _dot(d2, d2), _dot(d1, d2), _dot(d1, r), _dot(d2, r))
    return _sub(_add(a0, _scale(d1, s)), _add(b0, _scale(d2, t)))


def make_kernel(tool_ends: np.ndarray, tool_radii: np.ndarray, levers: np.ndarray, margin: float, jaw_sides=None):
    """The kernel ``(lanes_ref, others_ref, out_ref)`` for the scene's regrasping tool (``tool_ends
    [T, 2, 3]`` in its frame, ``tool_radii [T]``, ``levers [T]``) and the clearance ``margin`` [m];
    with ``jaw_sides [T]`` (the scene's ``CapsuleFrames.jaw_sides``) each lane's jaws turned by its
    own angle (:func:`walk_tests`' ``jaw_half``; :func:`regrasp_mjx.world.distances.turn_jaws`):
    ``out [2, B]``, where a lane is pending, 1 if its motion collides (else 0) and the interval tests
    it took (the root's included; 0 where not pending). A program holds :data:`BLOCK` lanes'
    counted capsules as a tile ``[BLOCK, OTHERS]`` (a lane's pairs side by side across threads, so
    that one interval test takes the time of a few pairs, not of 240 one after another) and loops
    over the tool's capsules."""
    ends = [[tuple(float(v) for v in e) for e in t] for t in np.asarray(tool_ends, np.float32)]
    radii = [float(r) for r in np.asarray(tool_radii, np.float32)]
    lever = [float(v) for v in np.asarray(levers, np.float32)]
    margin = float(np.float32(margin))
    sides = [0.0] * len(ends) if jaw_sides is None else [float(v) for v in jaw_sides]

    def kernel(lanes_ref, others_ref, out_ref):
        row = lambda r: lanes_ref[r, :]  # noqa: E731  [L]
        pos0, quat0 = (row(0), row(1), row(2)), (row(3), row(4), row(5), row(6))
        dp, w = (row(7), row(8), row(9)), (row(10), row(11), row(12))
        fastest, pending = row(13), row(14) > 0.5
        # each jaw's capsule as this lane has it: turned about the hinge (x) by its side times the lane's angle
        turned = []
        for (end0, end1), side in zip(ends, sides):
            if side == 0.0:
                turned.append((end0, end1))
                continue
            c, s = jnp.cos(side * row(15)), jnp.sin(side * row(15))
            turned.append(tuple((e[0], c * e[1] + s * e[2], -s * e[1] + c * e[2]) for e in (end0, end1)))
        b = [others_ref[:, c, :] for c in range(_OTHER_ROWS - 1)]  # [L, OTHERS] each
        b0, b1, radius = (b[0], b[1], b[2]), (b[3], b[4], b[5]), b[6]
        # per motion, not per interval: the motion bound's speed and the rotation's axis
        step = jnp.sqrt(_dot(dp, dp))
        turn = jnp.sqrt(_dot(w, w))
        axis = tuple(c / jnp.maximum(turn, 1e-30) for c in w)
        speeds = [step + turn * v for v in lever]
        col = lambda x: x[:, None]  # noqa: E731  a lane's value against its pairs

        def test(k, i):
            """Every pair's least distance and least lower bound over the interval ``(k, i)``."""
            h = jax.lax.bitcast_convert_type((126 - k) << 23, jnp.float32)  # 2^-(k + 1), exact
            s = (2 * i + 1).astype(jnp.float32) * h
            q = _quat_mul(_quat_exp(_scale(w, s)), quat0)
            origin = _add(pos0, _scale(dp, s))
            rows = _matrix(q)
            phi = h * turn
            least_d = least_low = None
            for t, (end0, end1) in enumerate(turned):
                e0, e1 = _place(rows, origin, end0), _place(rows, origin, end1)
                r0, r1 = _sub(e0, origin), _sub(e1, origin)
                off0 = _sub(r0, _scale(axis, _dot(r0, axis)))
                off1 = _sub(r1, _scale(axis, _dot(r1, axis)))
                rho = jnp.sqrt(jnp.maximum(_dot(off0, off0), _dot(off1, off1)))
                bend = col(rho * phi * phi * (0.5 + phi / 6.0))
                u0, u1 = _add(dp, _cross(w, r0)), _add(dp, _cross(w, r1))
                e0, e1, u0, u1 = (tuple(map(col, v)) for v in (e0, e1, u0, u1))
                gap = _segment_gap(e0, e1, b0, b1)
                length = jnp.sqrt(_dot(gap, gap))
                d = length - radii[t] - radius
                n = tuple(c / jnp.maximum(length, 1e-30) for c in gap)
                sep = jnp.minimum(_dot(e0, n), _dot(e1, n)) - jnp.maximum(_dot(b0, n), _dot(b1, n)) - (length - d)
                drift = col(h) * jnp.maximum(jnp.abs(_dot(u0, n)), jnp.abs(_dot(u1, n)))
                low = jnp.maximum(d - col(h * speeds[t]), sep - drift - bend)
                d, low = jnp.min(d, axis=1), jnp.min(low, axis=1)
                least_d = d if least_d is None else jnp.minimum(least_d, d)
                least_low = low if least_low is None else jnp.minimum(least_low, low)
            proved = least_low - margin >= SLACK
            stop = (least_d < margin) | (h * fastest <= RESOLUTION)
            return proved, stop

        def advance(c):
            return _advance(c, c.active, *test(c.k, c.i))

        zero = jnp.zeros(fastest.shape, jnp.int32)
        start = Walk(zero, zero, zero, jnp.zeros(fastest.shape, jnp.bool_), pending)
        busy = lambda c: jnp.max(c.active.astype(jnp.int32)) > 0  # noqa: E731
        walk = jax.lax.while_loop(busy, advance, start)
        out_ref[0, :] = walk.collision.astype(jnp.int32)
        out_ref[1, :] = walk.tests

    return kernel


def walk_tests(
    kernel, others_ends, others_radii, pos, quat, dp, rotvec, fastest, pending, jaw_half=None, interpret=False
):
    """Whether each pending lane's motion collides (False where not pending) and how many interval tests
    its walk took (0 where not pending), batched: ``others_ends
    [B, O, 2, 3]``, ``others_radii [B, O]``, ``pos [B, 3]``, ``quat [B, 4]``, ``dp``, ``rotvec [B, 3]``,
    ``fastest [B]``, ``pending [B]``, ``jaw_half [B]`` (how far each jaw is turned from the scene's
    opening [rad], half the change of opening; a kernel made with ``jaw_sides``; None: 0); ``kernel``
    from :func:`make_kernel`. ``interpret``: Pallas's interpreter (on a CPU, for tests)."""
    size, count = others_ends.shape[0], others_ends.shape[1]
    width = 1 << max(0, (count - 1).bit_length())  # Triton's tiles: a power of two
    padded = -(-size // BLOCK) * BLOCK
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    jaw_half = jnp.zeros(size) if jaw_half is None else jaw_half
    lanes = jnp.concatenate(
        [
            f32(pos),
            f32(quat),
            f32(dp),
            f32(rotvec),
            f32(fastest)[:, None],
            f32(pending)[:, None],
            f32(jaw_half)[:, None],
        ],
        axis=1,
    )
    lanes = jnp.pad(lanes, ((0, padded - size), (0, _LANE_ROWS - lanes.shape[1]))).T  # [16, B']
    others = jnp.concatenate([f32(others_ends).reshape(size, count, 6), f32(others_radii)[..., None]], axis=2)
    # the tile's spare columns: a capsule of no radius a kilometre away, never the closest
    far = jnp.asarray([FAR, FAR, FAR, FAR + 1.0, FAR, FAR, 0.0], jnp.float32)
    others = jnp.concatenate([others, jnp.broadcast_to(far, (size, width - count, 7))], axis=1)
    others = jnp.pad(others, ((0, padded - size), (0, 0), (0, _OTHER_ROWS - 7))).transpose(0, 2, 1)  # [B', 8, W]
    out = pl.pallas_call(
        kernel,
        out_shape=jax.ShapeDtypeStruct((2, padded), jnp.int32),
        grid=(padded // BLOCK,),
        in_specs=[
            pl.BlockSpec((_LANE_ROWS, BLOCK), lambda b: (0, b)),
            pl.BlockSpec((BLOCK, _OTHER_ROWS, width), lambda b: (b, 0, 0)),
        ],
        out_specs=pl.BlockSpec((2, BLOCK), lambda b: (0, b)),
        compiler_params=plt.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        interpret=interpret,
    )(lanes, others)
    return out[0, :size] > 0, out[1, :size]


def lane_fn(kernel, interpret: bool = False):
    """:func:`walk_tests`' verdicts as one lane's function ``(others_ends [O, 2, 3], others_radii [O], pos,
    quat, dp, rotvec, fastest, pending[, jaw_half]) -> bool``, jit/vmap-able: vmapped, one kernel call on
    the batch."""

    def one(*args):
        return walk_tests(kernel, *(jnp.asarray(a)[None] for a in args), interpret=interpret)[0][0]

    fn = jax.custom_batching.custom_vmap(one)

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        grow = lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))  # noqa: E731
        args = [grow(jnp.asarray(a), b) for a, b in zip(args, in_batched)]
        return walk_tests(kernel, *args, interpret=interpret)[0], True

    return fn
