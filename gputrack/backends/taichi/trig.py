"""sin and cos from arithmetic only, for the Taichi kernels.

- :func:`sincos64`: SPIR-V (taichi:vulkan) has no 64-bit Sin/Cos instructions.
- :func:`sincos32`: on the CPU, ``ti.sin``/``ti.cos`` in float32 become calls into the C math
  library, one value at a time; this polynomial is a few fused multiply-adds that LLVM inlines and
  vectorises. Forward kinematics and the particle sampler take two of them per angle, thousands
  per filter stage.
"""

from .runtime import ti

_PIO2_HI = 1.5707963267948966  # pi/2 split in two doubles (Cody-Waite reduction)
_PIO2_LO = 6.123233995736766e-17
_TWO_OVER_PI = 0.6366197723675814

# pi/2 in three float32 pieces (the first two exact in few bits, so n * piece is exact for |n| < 2**15)
_PIO2_F1 = 1.5703125
_PIO2_F2 = 4.837512969970703125e-4
_PIO2_F3 = 7.54978995489188216e-8
# minimax polynomials on [-pi/4, pi/4] (Cephes sinf/cosf): relative error ~1e-7
_S = (-1.6666654611e-1, 8.3321608736e-3, -1.9515295891e-4)
_C = (4.166664568298827e-2, -1.388731625493765e-3, 2.443315711809948e-5)
# fdlibm's minimax polynomials for double sin / cos on [-pi/4, pi/4] (< 1 ulp)
_S64 = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
        2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)  # fmt: skip
_C64 = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
        -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)  # fmt: skip


@ti.func
def _quadrant(n, s, c):
    """(sin a, cos a) from s = sin r, c = cos r, a = r + n pi/2 (branch-free)."""
    q = ti.cast(n, ti.i32) & 3  # n mod 4, also for negative n
    sin_a = ti.select((q & 1) == 1, c, s)
    cos_a = ti.select((q & 1) == 1, s, c)
    sin_a = ti.select((q & 2) == 2, -sin_a, sin_a)  # quadrants 2, 3
    cos_a = ti.select(((q + 1) & 2) == 2, -cos_a, cos_a)  # quadrants 1, 2
    return sin_a, cos_a


def _reduce_in_f64() -> bool:
    """Whether :func:`sincos32` reduces its argument in float64: on the LLVM archs (CPU, CUDA)
    Taichi's fast math reassociates the three-piece float32 reduction into one product with a
    rounded pi/2 (measured: sin(100) off by 1e-5, sin(32768) by 1e-3 on taichi:cpu); they have
    float64, whose one-product reduction keeps r within ~1e-11 for |a| <= 2**15 (gputrack.abi
    ANGLE_MAX). SPIR-V (Vulkan) keeps the float32 pieces apart."""
    return ti.lang.impl.current_cfg().arch in (ti.x64, ti.arm64, ti.cuda)


@ti.func
def sincos32(a):
    """(sin a, cos a) in float32 to ~2 ulp for |a| up to 2**15 (any angle of a pose)."""
    n = a * 0.0
    r = a * 0.0
    if ti.static(_reduce_in_f64()):
        af = ti.cast(a, ti.f64)
        n64 = ti.floor(af * ti.f64(_TWO_OVER_PI) + ti.f64(0.5))
        r = ti.cast((af - n64 * ti.f64(_PIO2_HI)) - n64 * ti.f64(_PIO2_LO), ti.f32)
        n = ti.cast(n64, ti.f32)
    else:
        n = ti.floor(a * _TWO_OVER_PI + 0.5)
        r = ((a - n * _PIO2_F1) - n * _PIO2_F2) - n * _PIO2_F3
    r2 = r * r
    s = r + r * r2 * (_S[0] + r2 * (_S[1] + r2 * _S[2]))
    c = 1.0 - 0.5 * r2 + r2 * r2 * (_C[0] + r2 * (_C[1] + r2 * _C[2]))
    return _quadrant(n, s, c)


@ti.func
def _reduced64(a):
    """(n, sin r, cos r) with a = r + n pi/2, |r| <= pi/4, in float64 (scalars or vectors of lanes):
    the arithmetic of :func:`sincos64` and :func:`sin64_lanes`."""
    f64 = ti.f64  # typed constants: a bare Python float would be a float32 literal
    n = ti.floor(a * f64(_TWO_OVER_PI) + f64(0.5))
    r = (a - n * f64(_PIO2_HI)) - n * f64(_PIO2_LO)
    z = r * r
    w = z * z
    sr = f64(_S64[1]) + z * (f64(_S64[2]) + z * f64(_S64[3])) + z * w * (f64(_S64[4]) + z * f64(_S64[5]))
    s = r + (z * r) * (f64(_S64[0]) + z * sr)
    cr = z * (f64(_C64[0]) + z * (f64(_C64[1]) + z * f64(_C64[2]))) + w * w * (
        f64(_C64[3]) + z * (f64(_C64[4]) + z * f64(_C64[5]))
    )
    hz = f64(0.5) * z
    c1 = f64(1.0) - hz
    c = c1 + (((f64(1.0) - c1) - hz) + z * cr)  # cos r = 1 - z/2 + z^2 C(z), the 1 - z/2 split exactly
    return n, s, c


@ti.func
def sincos64(a):
    """(sin a, cos a) in float64: reduce to |r| <= pi/4 (a - n pi/2 with pi/2 in two doubles), then
    fdlibm's (musl's) minimax kernels __sin / __cos (multiply-adds only; the Taylor series to r^19
    this replaces took 18 divisions and twice the time). The reduction's error grows with n:
    measured on taichi:cpu against np.sin / np.cos (2e6 uniform angles), max absolute error 2.2e-16
    on |a| <= 4, 4.7e-14 on |a| <= 500, 3.1e-12 on |a| <= 2**15 (gputrack.abi ANGLE_MAX, where the
    kinematics clamp)."""
    n, s, c = _reduced64(a)
    return _quadrant(n, s, c)


@ti.func
def sin64_lanes(a):
    """The sine of :func:`trig.sincos64` (the same arithmetic) for a vector of float64 lanes, its
    quadrant n mod 4 in float64 and two selects (``sincos64`` itself, and an int cast of a vector
    in a loop, do not compile with scalarisation off in Taichi 1.7: LLVM assertions)."""
    f64 = ti.f64
    n, s, c = _reduced64(a)
    q = n - f64(4.0) * ti.floor(n * f64(0.25))  # n mod 4, exactly (an integer-valued float64)
    v = ti.select((q == f64(1.0)) | (q == f64(3.0)), c, s)
    return ti.select(q >= f64(2.0), f64(0.0) - v, v)  # 0 - v: -v of a select's vector trips an assertion
