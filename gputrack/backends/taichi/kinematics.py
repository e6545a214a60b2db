"""Taichi forward kinematics: one thread per parameter vector, a serial loop over the parts.

The chain comes as tables (see gputrack.models.Chain.packed): per part its parent, up to three
rotation axes with their angle parameter, and a translation = offset + optional parameters.
Parents precede children, so a part reads its parent's transform from the output just written.
"""

import numpy as np

from .launch import launch
from .runtime import current_arch, ti
from .tasks import CPU_TASK

# float64 sin/cos from arithmetic only: SPIR-V (taichi:vulkan) has no 64-bit Sin/Cos instructions.
_PIO2_HI = 1.5707963267948966  # pi/2 split in two doubles (Cody-Waite reduction)
_PIO2_LO = 6.123233995736766e-17
_TWO_OVER_PI = 0.6366197723675814


@ti.func
def sincos64(a):
    """(sin a, cos a) in float64 to ~1 ulp for |a| up to ~1e6: reduce to |r| <= pi/4, Taylor to r^19."""
    f64 = ti.f64  # typed constants: a bare Python float would be a float32 literal
    n = ti.floor(a * f64(_TWO_OVER_PI) + f64(0.5))
    r = (a - n * f64(_PIO2_HI)) - n * f64(_PIO2_LO)
    r2 = r * r
    s = f64(1.0)  # Horner: sin r = r (1 - r^2/(2*3) (1 - r^2/(4*5) (...))), cos r = 1 - r^2/(1*2) (1 - ...)
    c = f64(1.0)
    for k in ti.static(range(9, 0, -1)):
        s = f64(1.0) - r2 / f64(float((2 * k) * (2 * k + 1))) * s
        c = f64(1.0) - r2 / f64(float((2 * k - 1) * (2 * k))) * c
    sr = r * s
    cr = c
    q = ti.cast(n - f64(4.0) * ti.floor(n * f64(0.25)), ti.i32)  # n mod 4
    sin_a, cos_a = sr, cr
    if q == 1:
        sin_a, cos_a = cr, -sr
    elif q == 2:
        sin_a, cos_a = -sr, -cr
    elif q == 3:
        sin_a, cos_a = -cr, sr
    return sin_a, cos_a


def _make(real):
    @ti.func
    def rotate(c0, c1, c2, axis, a):
        # right-multiply R = [c0 c1 c2] (columns) by Rx/Ry/Rz(a) (eq. 7-9)
        c = ti.cast(0.0, real)
        s = ti.cast(0.0, real)
        if ti.static(real == ti.f64):
            s, c = sincos64(a)
        else:
            c = ti.cos(a)
            s = ti.sin(a)
        n0, n1, n2 = c0, c1, c2
        if axis == 0:  # Rx: columns 1, 2
            n1 = c * c1 + s * c2
            n2 = -s * c1 + c * c2
        elif axis == 1:  # Ry: columns 2, 0
            n2 = c * c2 + s * c0
            n0 = -s * c2 + c * c0
        elif axis == 2:  # Rz: columns 0, 1
            n0 = c * c0 + s * c1
            n1 = -s * c0 + c * c1
        return n0, n1, n2

    @ti.func
    def pose(params: ti.template(), b, table: ti.template(), offsets: ti.template(), out: ti.template()):
        """Camera-from-part transforms of parameter vector b into out[b, j, :, :] for every part j.

        For fused kernels: params (B, P), table (J, 10) int32, offsets (J, 3), out (B, J, 3, 4).
        """
        for j in range(table.shape[0]):
            c0 = ti.Vector([1.0, 0.0, 0.0], dt=real)
            c1 = ti.Vector([0.0, 1.0, 0.0], dt=real)
            c2 = ti.Vector([0.0, 0.0, 1.0], dt=real)
            for k in ti.static(range(3)):
                axis = table[j, 1 + k]
                if axis >= 0:
                    c0, c1, c2 = rotate(c0, c1, c2, axis, params[b, table[j, 4 + k]])
            t = ti.Vector([offsets[j, 0], offsets[j, 1], offsets[j, 2]], dt=real)
            for k in ti.static(range(3)):
                idx = table[j, 7 + k]
                if idx >= 0:
                    t[k] += params[b, idx]
            parent = table[j, 0]
            if parent >= 0:  # eq. 2-3: camera-from-parent @ parent-from-part
                p0 = ti.Vector([out[b, parent, 0, 0], out[b, parent, 1, 0], out[b, parent, 2, 0]], dt=real)
                p1 = ti.Vector([out[b, parent, 0, 1], out[b, parent, 1, 1], out[b, parent, 2, 1]], dt=real)
                p2 = ti.Vector([out[b, parent, 0, 2], out[b, parent, 1, 2], out[b, parent, 2, 2]], dt=real)
                pt = ti.Vector([out[b, parent, 0, 3], out[b, parent, 1, 3], out[b, parent, 2, 3]], dt=real)
                n0 = p0 * c0[0] + p1 * c0[1] + p2 * c0[2]
                n1 = p0 * c1[0] + p1 * c1[1] + p2 * c1[2]
                n2 = p0 * c2[0] + p1 * c2[1] + p2 * c2[2]
                t = p0 * t[0] + p1 * t[1] + p2 * t[2] + pt
                c0, c1, c2 = n0, n1, n2
            for r in ti.static(range(3)):
                out[b, j, r, 0] = c0[r]
                out[b, j, r, 1] = c1[r]
                out[b, j, r, 2] = c2[r]
                out[b, j, r, 3] = t[r]

    @ti.kernel
    def fk(
        params: ti.types.ndarray(dtype=real, ndim=2),
        table: ti.types.ndarray(dtype=ti.i32, ndim=2),
        offsets: ti.types.ndarray(dtype=real, ndim=2),
        out: ti.types.ndarray(dtype=real, ndim=4),
        serial: ti.template(),
    ):
        ti.loop_config(serialize=serial)  # a batch Taichi would run as one task anyway (CPU)
        for b in range(params.shape[0]):
            pose(params, b, table, offsets, out)

    return pose, fk


#: ti.func pose(params, b, table, offsets, out) for fused kernels, and the op's kernels
pose_f32, _fk_f32 = _make(ti.f32)
pose_f64, _fk_f64 = _make(ti.f64)


def forward_kinematics(device, chain, params, out):
    from ...ops.kinematics import chain_tables

    table, offsets = chain_tables(device, chain, params.dtype)
    kernel = _fk_f64 if params.dtype == np.float64 else _fk_f32
    serial = current_arch() == "cpu" and params.shape[0] <= CPU_TASK
    launch(kernel, (params.buffer, table.buffer, offsets.buffer, out.buffer), (serial,))
    return out
