"""Taichi forward kinematics: one thread per parameter vector, the parts unrolled at compile time.

The chain's structure (per part: its parent, up to three rotation axes with their angle parameter,
the parameters added to its translation; gputrack.models.Chain.packed) is a compile-time value,
``Chain.structure()``: the kernel for a chain is straight-line code, with no table reads or branches,
and each part's transform stays in registers for its children. The fixed offsets are an array
(they change with the person, e.g. the shoulder width, without a recompile). A new structure
compiles a new kernel (the upper body has two: with and without the shoulder parameters).
"""

import numpy as np

from ...abi import ANGLE_MAX
from ...models.chain import chain_tables
from .launch import launch
from .runtime import current_arch, ti
from .tasks import CPU_TASK
from .trig import sincos32, sincos64


def _make(real):
    bits, exponent = (ti.u64, 0x7FF0000000000000) if real == ti.f64 else (ti.u32, 0x7F800000)

    @ti.func
    def clamp_angle(a):
        """A finite angle clamped to [-ANGLE_MAX, ANGLE_MAX] (gputrack/abi.py); inf and NaN kept (told by
        their bits, as fast math may assume there are none)."""
        m = ti.cast(float(ANGLE_MAX), real)
        finite = (ti.bit_cast(a, bits) & bits(exponent)) != bits(exponent)
        return ti.select(finite & (ti.abs(a) > m), ti.select(a > 0, m, -m), a)

    @ti.func
    def rotate(c0, c1, c2, axis: ti.template(), a):
        # right-multiply R = [c0 c1 c2] (columns) by Rx/Ry/Rz(a) (eq. 7-9)
        a = clamp_angle(a)
        s = ti.cast(0.0, real)
        c = ti.cast(1.0, real)
        if ti.static(real == ti.f64):
            s, c = sincos64(a)
        else:
            s, c = sincos32(a)
        n0, n1, n2 = c0, c1, c2
        if ti.static(axis == 0):  # Rx: columns 1, 2
            n1 = c * c1 + s * c2
            n2 = -s * c1 + c * c2
        elif ti.static(axis == 1):  # Ry: columns 2, 0
            n2 = c * c2 + s * c0
            n0 = -s * c2 + c * c0
        else:  # Rz: columns 0, 1
            n0 = c * c0 + s * c1
            n1 = -s * c0 + c * c1
        return n0, n1, n2

    @ti.func
    def pose(params: ti.template(), b, chain: ti.template(), offsets: ti.template(), out: ti.template()):
        """Camera-from-part transforms of parameter vector b into out[b, j, :, :] for every part j.

        For fused kernels: params (B, P), chain = Chain.structure() (compile-time), offsets (J, 3),
        out (B, J, 3, 4).
        """
        J = ti.static(len(chain))
        # part j's columns c0, c1, c2, t, for its children (3-vectors, not one J x 12 matrix: with
        # scalarisation off a big matrix's element reads and writes are vector shuffles)
        R = [[ti.Vector([0.0, 0.0, 0.0], dt=real) for _ in ti.static(range(4))] for _ in ti.static(range(J))]
        for j in ti.static(range(J)):
            row = ti.static(chain[j])
            c0 = ti.Vector([1.0, 0.0, 0.0], dt=real)
            c1 = ti.Vector([0.0, 1.0, 0.0], dt=real)
            c2 = ti.Vector([0.0, 0.0, 1.0], dt=real)
            for k in ti.static(range(3)):
                if ti.static(row[1 + k] >= 0):
                    c0, c1, c2 = rotate(c0, c1, c2, row[1 + k], ti.cast(params[b, row[4 + k]], real))
            t = ti.Vector([offsets[j, 0], offsets[j, 1], offsets[j, 2]], dt=real)
            for k in ti.static(range(3)):
                if ti.static(row[7 + k] >= 0):
                    t[k] += params[b, row[7 + k]]
            if ti.static(row[0] >= 0):  # eq. 2-3: camera-from-parent @ parent-from-part
                q = ti.static(row[0])
                p0, p1, p2, pt = R[q][0], R[q][1], R[q][2], R[q][3]
                n0 = p0 * c0[0] + p1 * c0[1] + p2 * c0[2]
                n1 = p0 * c1[0] + p1 * c1[1] + p2 * c1[2]
                n2 = p0 * c2[0] + p1 * c2[1] + p2 * c2[2]
                t = p0 * t[0] + p1 * t[1] + p2 * t[2] + pt
                c0, c1, c2 = n0, n1, n2
            R[j][0], R[j][1], R[j][2], R[j][3] = c0, c1, c2, t
            for r in ti.static(range(3)):
                out[b, j, r, 0] = c0[r]
                out[b, j, r, 1] = c1[r]
                out[b, j, r, 2] = c2[r]
                out[b, j, r, 3] = t[r]

    @ti.kernel
    def fk(
        params: ti.types.ndarray(dtype=real, ndim=2),
        offsets: ti.types.ndarray(dtype=real, ndim=2),
        out: ti.types.ndarray(dtype=real, ndim=4),
        chain: ti.template(),
        serial: ti.template(),
    ):
        ti.loop_config(serialize=serial)  # a batch Taichi would run as one task anyway (CPU)
        for b in range(params.shape[0]):
            pose(params, b, chain, offsets, out)

    return pose, fk


#: ti.func pose(params, b, chain, offsets, out) for fused kernels, and the op's kernels
pose_f32, _fk_f32 = _make(ti.f32)
pose_f64, _fk_f64 = _make(ti.f64)


def forward_kinematics(device, chain, params, out):
    _, offsets = chain_tables(device, chain, params.dtype)
    kernel = _fk_f64 if params.dtype == np.float64 else _fk_f32
    serial = current_arch() == "cpu" and params.shape[0] <= CPU_TASK
    # compiled as the fused kernels that pose through pose_f32 are (template.py), so that the
    # composition forward_kinematics -> rgbd_* rounds as they do
    launch(kernel, (params.buffer, offsets.buffer, out.buffer), (chain.structure(), serial), scalarize=False)
    return out
