"""OpenCL launchers of the batched Kalman filter ops (kernels/gt_kalman.cl).

On a CPU device each work-item runs VW = 8 tracks in the lanes of vector types (SIMD arithmetic,
per-track loads and stores, per-lane selection instead of branches); on a GPU one track per
work-item (VW = 1). The filter kernel gt_kf and the gating kernel gt_gate share the source of
the innovation covariance and its Cholesky factor. Sizes, dtype, layout (shared or per-track
matrices), options, VW and the known zero patterns of F, Q, H and R are build defines, so each
combination is built once per device (cached by ``device.program``); the kernel of each variant
is memoised here and its arguments are set again only when they change. Arguments an op does not
use are passed as NULL.
"""

import functools
from pathlib import Path

import numpy as np

from ... import tuning_cache
from ...tuning_cache import Tunable
from .program import enqueue, ndrange, source
from ...device import per_device

MODE_PREDICT, MODE_LINEAR, MODE_STEREO = 0, 1, 2
PD_EPS_FACTOR = 4.0
_STEREO_ROWS = (0b010001, 0b010100, 0b010000)  # non-zeros of the stereo Jacobian, per row


def _rows(pat: int, rows: int, cols: int):
    """Row bitmasks of a row-major bitmask pattern (-1 = dense)."""
    if pat == -1:
        return [(1 << cols) - 1] * rows
    return [(pat >> (i * cols)) & ((1 << cols) - 1) for i in range(rows)]


def lanes(device) -> int:
    """Tracks per work-item: SIMD lanes on a CPU device, one on a GPU."""
    return 8 if device.info.kind == "cpu" else 1


def default_params(device) -> dict:
    """Launch parameters of the filter kernels without a tuning-cache entry (``gputrack tune``
    may choose others: TUNABLES): tracks per work-item and work-group size (None: the driver's
    choice)."""
    return {"lanes": lanes(device), "work_group": None}


# The filter kernel (kf_predict, kf_update, ekf_update_stereo) launches with ``lanes`` tracks per
# work-item (gt_kf built with VW = 1, or with VW-wide vectors for 4, 8, 16) and a work-group size
# (None: the driver's choice), read at every call and swept by ``gputrack tune``. Every track is
# computed alike whatever the choice (each lane runs its own track), only the speed differs.
TUNABLES = {
    "kalman": Tunable(
        op="kalman",
        backend="opencl",
        candidates={"lanes": [1, 4, 8, 16], "work_group": [None, 16, 64, 256]},
        default=default_params,
        sizes=({"T": 10_000, "n": 6}, {"T": 100_000, "n": 6}, {"T": 1_000_000, "n": 6}),
        sources=(source("gt_kalman.cl"), str(Path(__file__).resolve())),
    )
}


def _launch_params(device, T, n) -> dict:
    return tuning_cache.choose(device, TUNABLES["kalman"], {"T": T, "n": n})


def _program(device, dtype, n, m, mode, predict, has_mask, has_gain, pts, pats, hrows, vw=1):
    defines = _defines(np.dtype(dtype).name, n, m, mode, predict, has_mask, has_gain, pts, pats, tuple(hrows), vw)
    return device.program("gt_kalman.cl", dict(defines))


@functools.cache
def _defines(dtype, n, m, mode, predict, has_mask, has_gain, pts, pats, hrows, vw):
    """Build defines of one kernel variant (cached: it is asked for on every call)."""
    eps = float(np.finfo(dtype).eps) * PD_EPS_FACTOR
    return tuple(
        {
            "REAL": "double" if dtype == "float64" else "float",
            "REAL_IS_DOUBLE": int(dtype == "float64"),
            "N": n,
            "M": m,
            "MODE": mode,
            "DO_PREDICT": int(predict),
            "HAS_MASK": int(has_mask),
            "HAS_GAIN": int(has_gain),
            "F_PT": pts[0],
            "Q_PT": pts[1],
            "H_PT": pts[2],
            "R_PT": pts[3],
            "FPAT": ",".join(f"{r}u" for r in _rows(pats[0], n, n)),
            "QPAT": ",".join(f"{r}u" for r in _rows(pats[1], n, n)),
            "HPAT": ",".join(f"{r}u" for r in hrows),
            "RPAT": ",".join(f"{r}u" for r in _rows(pats[3], m, m)),
            "PD_TOL": repr(eps),
            "VW": vw,
        }.items()
    )


def _pt(a):
    return int(a is not None and a.ndim == 3)


def _data(a):
    return a.buffer.data if a is not None else None


def _variant_kernel(device, dt, n, m, mode, F, Q, H, R, mask, gain_scale, pats, vw):
    return _filter_kernel(device, dt, n, m, mode, F is not None, mask is not None, gain_scale is not None,
                          (_pt(F), _pt(Q), _pt(H), _pt(R)), tuple(pats), vw)  # fmt: skip


@per_device
def _filter_kernel(device, dt, n, m, mode, predict, has_mask, has_gain, pts, pats, vw):
    """gt_kf of one variant (memoised: building the defines and finding the program costs ~10 us)."""
    import pyopencl as cl

    if mode == MODE_STEREO:
        hrows = _STEREO_ROWS
    elif mode == MODE_LINEAR:
        hrows = _rows(pats[2], m, n)
    else:
        hrows = [0]
    prg = _program(
        device, dt, n, m, mode, predict, has_mask, has_gain, pts,
        (pats[0], pats[1], -1, pats[3]) if predict else (-1, -1, -1, pats[3]), hrows, vw,
    )  # fmt: skip
    return cl.Kernel(prg, "gt_kf")


@per_device
def _gate_kernel(device, dt, n, m, pt_h, pt_r, pat_h, pat_r, vw):
    """gt_gate of one variant (memoised)."""
    import pyopencl as cl

    prg = _program(
        device, dt, n, m, MODE_LINEAR, False, False, False, (0, 0, pt_h, pt_r), (-1, -1, -1, pat_r),
        _rows(pat_h, m, n), vw,
    )  # fmt: skip
    return cl.Kernel(prg, "gt_gate")


def _run(device, x, P, z, F, Q, H, R, mask, gain_scale, mode, out, pats, cam=(0.0, 0.0, 0.0, 0.0), params=None):
    T, n = x.shape
    params = params or _launch_params(device, T, n)
    vw, wg = int(params["lanes"]), params["work_group"]
    m = z.shape[1] if z is not None else 1
    dt = x.dtype
    if out is None:
        out = (device.empty((T, n), dt), device.empty((T, n, n), dt))
        if mode != MODE_PREDICT:
            out += (device.empty((T,), np.uint8),)
    xo, Po = out[0], out[1]
    st = out[2] if mode != MODE_PREDICT else None
    knl = _variant_kernel(device, dt, n, m, mode, F, Q, H, R, mask, gain_scale, pats, vw)
    real = dt.type
    items = (T + vw - 1) // vw
    enqueue(
        device, knl, *ndrange(items, group=(wg,) if wg else None),
        _data(x), _data(P), _data(z), _data(F), _data(Q), _data(H), _data(R), _data(mask), _data(gain_scale),
        _data(xo), _data(Po), _data(st), real(cam[0]), real(cam[1]), real(cam[2]), real(cam[3]), np.int32(T),
    )  # fmt: skip
    return (xo, Po) if mode == MODE_PREDICT else (xo, Po, st)


def kf_predict(device, x, P, F, Q, out=None, pats=(-1, -1, -1, -1)):
    return _run(device, x, P, None, F, Q, None, None, None, None, MODE_PREDICT, out, pats)


def kf_update(
    device, x, P, z, H, R, mask=None, gain_scale=None, F=None, Q=None, out=None, pats=(-1, -1, -1, -1), params=None
):
    return _run(device, x, P, z, F, Q, H, R, mask, gain_scale, MODE_LINEAR, out, pats, params=params)


def ekf_update_stereo(
    device,
    x,
    P,
    z,
    R,
    f,
    b,
    cx=0.0,
    cy=0.0,
    mask=None,
    gain_scale=None,
    F=None,
    Q=None,
    out=None,
    pats=(-1, -1, -1, -1),
):
    return _run(device, x, P, z, F, Q, None, R, mask, gain_scale, MODE_STEREO, out, pats, (f, b, cx, cy))


def mahalanobis(device, x, P, H, R, z, out=None, pats=(-1, -1, -1, -1)):
    T, n = x.shape
    D, m = z.shape
    out = out if out is not None else device.empty((T, D), x.dtype)
    vw = lanes(device)
    knl = _gate_kernel(device, x.dtype, n, m, _pt(H), _pt(R), pats[2], pats[3], vw)
    args = (_data(x), _data(P), _data(H), _data(R), _data(z), _data(out), np.int32(T), np.int32(D))
    enqueue(device, knl, *ndrange((T + vw - 1) // vw), *args)
    return out
