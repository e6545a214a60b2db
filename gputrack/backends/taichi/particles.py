"""Taichi kernels of the particle-filter helpers: counter-based sampling (eq. 12) and best-k.

Same generator as the reference (gputrack/backends/reference/particles.py). best-k runs as one
serial task (an ordered k-list over the B scores, O(B k)), which on CPUs costs a few
microseconds for the filter's sizes and saves a second launch.
"""

import numpy as np

from .launch import launch
from .runtime import scratch, ti
from .trig import sincos32


@ti.func
def _pcg(x):
    state = x * ti.u32(747796405) + ti.u32(2891336453)
    word = ((state >> ((state >> ti.u32(28)) + ti.u32(4))) ^ state) * ti.u32(277803737)
    return (word >> ti.u32(22)) ^ word


@ti.func
def _pair(key, cnt):
    """Box-Muller pair (cos, sin branch) of the uniforms of counters cnt, cnt + 1."""
    b1 = _pcg(_pcg(cnt) + key)
    b2 = _pcg(_pcg(cnt + ti.u32(1)) + key)
    u1 = ti.cast((b1 >> ti.u32(8)) + ti.u32(1), ti.f32) * (1.0 / 16777216.0)  # (0, 1]
    u2 = ti.cast(b2 >> ti.u32(8), ti.f32) * (1.0 / 16777216.0)  # [0, 1)
    r = ti.sqrt(-2.0 * ti.log(u1))
    s, c = sincos32(6.2831853071795864 * u2)
    return r * c, r * s


@ti.func
def sample_key(lo, hi):
    """The generator's key of a seed (lo, hi = its low and high 32 bits)."""
    return _pcg(lo ^ _pcg(hi))


@ti.func
def sample_one(cand: ti.template(), sig: ti.template(), out: ti.template(), key, k, keep, per_candidate: ti.template()):
    """Sample k of out (eq. 12): one division per sample, one log/sqrt per pair of parameters
    (skipped for a pair whose sigmas are both 0: those parameters are their candidate's)."""
    n = out.shape[0]
    p = out.shape[1]
    c = cand.shape[0]
    half = (p + 1) // 2
    owner = k * c // n  # sample k belongs to candidate k C // K (n C < 2**31, checked by the op)
    first = (owner * n + c - 1) // c  # the first sample of the block
    same = keep != 0 and k == first
    for t in range(half):
        sp = ti.Vector([0.0, 0.0], dt=ti.f32)  # the pair's sigmas
        for h in ti.static(range(2)):
            q = ti.min(2 * t + h, p - 1)
            if ti.static(per_candidate):
                sp[h] = sig[owner, q]
            else:
                sp[h] = sig[q]
        z0 = ti.f32(0.0)
        z1 = ti.f32(0.0)
        if sp[0] != 0.0 or sp[1] != 0.0:
            z0, z1 = _pair(key, ti.cast(k * half + t, ti.u32) * ti.u32(2))
        for h in ti.static(range(2)):
            q = 2 * t + h
            if q < p:
                z = z0 if ti.static(h == 0) else z1
                val = cand[owner, q] + sp[h] * z  # eq. 12: p_c + dp, dp ~ N(0, diag(sigma^2))
                if same:
                    val = cand[owner, q]
                out[k, q] = val


@ti.func
def sample_body(
    cand: ti.template(), sig: ti.template(), out: ti.template(), lo, hi, keep, per_candidate: ti.template()
):
    key = sample_key(lo, hi)
    for k in range(out.shape[0]):  # one thread per sample
        sample_one(cand, sig, out, key, k, keep, per_candidate)


@ti.kernel
def _sample(
    cand: ti.types.ndarray(dtype=ti.f32, ndim=2),
    sig: ti.types.ndarray(dtype=ti.f32),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    seed: ti.types.ndarray(dtype=ti.u32, ndim=1),
    keep: ti.template(),
    per_candidate: ti.template(),
):
    """seed = [lo, hi] (an array: launch() passes Python scalars as signed integers)."""
    sample_body(cand, sig, out, seed[0], seed[1], keep, per_candidate)


def sample_around(device, cand, sig, n, lo, hi, *, per_candidate, keep_candidates):
    out = device.empty((n, cand.shape[1]), np.float32)
    seed = np.array([lo, hi], np.uint32)
    launch(_sample, (cand.buffer, sig.buffer, out.buffer, seed), (int(keep_candidates), bool(per_candidate)))
    return out


@ti.func
def _key(s):
    """uint32 key ordering float32 scores ascending; NaN last (bit tests: immune to fast math)."""
    bits = ti.bit_cast(s, ti.u32)
    key = bits | ti.u32(0x80000000)
    if (bits >> ti.u32(31)) == ti.u32(1):
        key = ~bits
    if (bits & ti.u32(0x7FFFFFFF)) > ti.u32(0x7F800000):
        key = ti.u32(0xFFFFFFFF)
    return key


@ti.func
def best_k_body(scores: ti.template(), idx: ti.template(), val: ti.template(), keys: ti.template(),
                rows: ti.template(), sel: ti.template(), with_rows: ti.template()):  # fmt: skip
    """The k = idx.shape[0] lowest scores, ascending, as one serial task (also for fused kernels)."""
    nb = scores.shape[0]
    k = idx.shape[0]
    ti.loop_config(serialize=True)  # on the calling thread (no thread-pool dispatch)
    for _ in range(1):  # one serial task
        cnt = 0
        for i in range(nb):
            key = _key(scores[i])
            # strictly better than the current k-th (ties keep the lower index: i is larger)
            if cnt < k or key < keys[k - 1]:
                pos = ti.min(cnt, k - 1)
                while pos > 0 and keys[pos - 1] > key:
                    keys[pos] = keys[pos - 1]
                    idx[pos] = idx[pos - 1]
                    pos -= 1
                keys[pos] = key
                idx[pos] = i
                cnt = ti.min(cnt + 1, k)
        for r in range(k):
            val[r] = scores[idx[r]]
            if ti.static(with_rows):
                for q in range(rows.shape[1]):
                    sel[r, q] = rows[idx[r], q]


@ti.kernel
def _best_k(
    scores: ti.types.ndarray(dtype=ti.f32, ndim=1),
    idx: ti.types.ndarray(dtype=ti.i32, ndim=1),
    val: ti.types.ndarray(dtype=ti.f32, ndim=1),
    keys: ti.types.ndarray(dtype=ti.u32, ndim=1),
    rows: ti.types.ndarray(dtype=ti.f32, ndim=2),
    sel: ti.types.ndarray(dtype=ti.f32, ndim=2),
    with_rows: ti.template(),
):
    best_k_body(scores, idx, val, keys, rows, sel, with_rows)


def best_k(device, scores, k, rows, out):
    """out: the (idx, val, sel) arrays to write (gputrack/ops/particles.py best_k_out)."""
    idx, val, sel = out
    keys = scratch(device, "keys", (k,), ti.u32)
    if rows is None:
        dummy = scratch(device, "dummy", (1, 1), ti.f32)
        launch(_best_k, (scores.buffer, idx.buffer, val.buffer, keys, dummy, dummy), (False,))
        return idx, val, None
    launch(_best_k, (scores.buffer, idx.buffer, val.buffer, keys, rows.buffer, sel.buffer), (True,))
    return idx, val, sel
