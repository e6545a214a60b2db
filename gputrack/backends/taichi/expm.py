"""exp from arithmetic only, for the Taichi kernels.

:func:`exp64`, float64:

- on the CPU archs ``ti.exp`` in float64 becomes a call into the C math library, one value at a
  time, which keeps LLVM from vectorising around it; this one is a range reduction and a
  polynomial (fused multiply-adds and integer bit work) that LLVM inlines, and on a vector of
  lanes (a kernel launched with ``scalarize=False``) computes with SIMD instructions;
- SPIR-V (taichi:vulkan) has no 64-bit Exp instruction at all.

- x = n ln 2 + r, n = round(x / ln 2), |r| <= ln 2 / 2 (plus rounding), with ln 2 split in two
  doubles (Cody-Waite: the low 21 bits of the first are zero, so n hi and x - n hi are exact);
- exp(r) = 1 + r + r^2 p(r), p the Taylor polynomial to r^13 (truncation error below 5e-18
  relative on |r| <= 0.35);
- 2^n in two steps: 2^(n >> 1) added to the exponent field of exp(r) (exact), then a
  multiplication by 2^(n - (n >> 1)) built from its bits (a normal double), so that this last
  multiplication rounds once into the subnormal range or overflows to inf as it should.

Special values as ``np.exp``: x > 709.78... gives inf (also +inf), x < -745.13... gives 0 (also
-inf), NaN gives NaN (told by its bits, as fast math may assume there is none), exp(0) = 1 exactly.
Measured against ``np.exp`` on taichi:cpu, scalar and 8 lanes (2**20 points uniform over
[-745.2, 709.8], 2**18 over [-1, 1], the edge values of tests/test_expfit_kernels.py): at most
1 ulp (relative 2.2e-16), 73 % of the values equal; results below the smallest normal double within
it of np.exp's (the CPU may flush them to 0).
"""

import math

from .runtime import ti

_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # 0x3FE62E42FEE00000: n hi exact for |n| < 2^21
_LN2_LO = 1.90821492927058770002e-10  # ln 2 - _LN2_HI
_X_MAX = 710.0  # exp overflows from 709.782712893384; clamped here, 2^n still two normal factors
_X_MIN = -746.0  # exp rounds to 0 below -745.1332191019412
_SHIFTER = 6755399441055744.0  # 1.5 2^52: v + _SHIFTER rounds v to an integer held in the low bits
_SHIFTER_BITS = 0x4338000000000000
_INV_FACT = tuple(1.0 / math.factorial(k) for k in range(14))


def _lanes(x) -> int:
    """Lanes of a vector argument, 0 for a scalar."""
    return x.get_shape()[0] if getattr(x, "is_tensor", lambda: False)() else 0


@ti.func
def _bits(x, dtype: ti.template()):
    """``ti.bit_cast`` of a scalar, or lane by lane of a vector (``ti.bit_cast`` and ``ti.cast``
    of a vector fail to compile with ``scalarize=False``; LLVM merges the lanes into one vector
    bitcast)."""
    if ti.static(_lanes(x)):
        return ti.Vector([ti.bit_cast(x[j], dtype) for j in ti.static(range(_lanes(x)))])
    else:
        return ti.bit_cast(x, dtype)


@ti.func
def exp64(x):
    """exp(x) in float64 to 1 ulp (see the module docstring), of a scalar or of each lane of a
    vector."""
    f64, i64 = ti.f64, ti.i64  # typed constants: a bare Python float would be a float32 literal
    xc = ti.select(x > f64(_X_MAX), f64(_X_MAX), ti.select(x < f64(_X_MIN), f64(_X_MIN), x))
    # n = round(x / ln 2) in the low bits of x / ln 2 + 1.5 2^52; its bits go through an integer
    # select that never changes them (-1 is a NaN's bits), so that fast math cannot fold
    # (v + c) - c into v; n as an integer from the same bits (packed double-to-int64 conversion
    # needs AVX-512DQ; with it, floor and a conversion measured the same)
    kb = _bits(xc * f64(_LOG2E) + f64(_SHIFTER), i64)
    kb = ti.select(kb == i64(-1), i64(0), kb)
    nf = _bits(kb, f64) - f64(_SHIFTER)
    n = kb - i64(_SHIFTER_BITS)
    # x - n hi (exact) through the same kind of select: fast math would otherwise reassociate
    # (x - n hi) - n lo into x - (n hi + n lo), whose sum rounds (an error of n 4e-17 in r, 100 ulp
    # at x = 700)
    hb = _bits(xc - nf * f64(_LN2_HI), i64)
    r = _bits(ti.select(hb == i64(-1), i64(0), hb), f64) - nf * f64(_LN2_LO)
    p = r * f64(0.0) + f64(_INV_FACT[13])
    for k in ti.static(range(12, 1, -1)):
        p = p * r + f64(_INV_FACT[k])
    e = f64(1.0) + (r + r * r * p)
    # 2^n in two factors 2^n1 2^(n - n1), n1 = floor(n / 2): e 2^n1 by adding n1 to e's exponent
    # field (exact: e is in [0.7, 1.5], the result normal; an integer add, which fast math cannot
    # reassociate with the next product into e (2^n1 2^n2), whose 2^n overflows for n = 1024), then
    # one rounding multiplication by 2^(n - n1)
    n1 = n >> i64(1)
    e1 = _bits(_bits(e, i64) + (n1 << i64(52)), f64)
    y = e1 * _bits((n - n1 + i64(1023)) << i64(52), f64)
    nan = (_bits(x, i64) & i64(0x7FFFFFFFFFFFFFFF)) > i64(0x7FF0000000000000)
    return ti.select(nan, x, y)
