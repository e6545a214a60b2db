"""NumPy reference of the particle-filter helpers (paper 000 eq. 12): counter-based sampling, best-k.

The generator: bits = pcg(pcg(counter) + key), key = pcg(seed_lo ^ pcg(seed_hi)), with
pcg the 32-bit PCG output hash; parameters 2t, 2t+1 of sample k are the Box-Muller pair of
the uniforms of counters 2 (k H + t), 2 (k H + t) + 1, H = ceil(P / 2) (see ``normals``).
"""

from __future__ import annotations

import numpy as np


U32 = np.uint32


def pcg(x):
    """PCG-RXS-M-XS 32-bit hash (uint32 arrays; arithmetic wraps modulo 2**32)."""
    x = np.asarray(x, dtype=U32)
    state = x * U32(747796405) + U32(2891336453)
    word = ((state >> ((state >> U32(28)) + U32(4))) ^ state) * U32(277803737)
    return (word >> U32(22)) ^ word


def normals(n: int, p: int, lo: int, hi: int) -> np.ndarray:
    """(n, p) standard normal deviates (float32) of the stream keyed by (lo, hi).

    Parameters 2t and 2t+1 of sample k share one Box-Muller pair (cosine and sine branch) made
    from the uniforms of counters 2 (k H + t) and 2 (k H + t) + 1, H = ceil(p / 2).
    """
    key = pcg(np.array([lo], U32) ^ pcg(np.array([hi], U32)))[0]
    half = (p + 1) // 2
    c = np.arange(2 * n * half, dtype=U32)
    bits = pcg(pcg(c) + key)
    u1 = ((bits[0::2] >> U32(8)) + U32(1)).astype(np.float32) * np.float32(2.0**-24)  # (0, 1]
    u2 = (bits[1::2] >> U32(8)).astype(np.float32) * np.float32(2.0**-24)  # [0, 1)
    r = np.sqrt(np.float32(-2.0) * np.log(u1))
    theta = np.float32(2.0 * np.pi) * u2
    z = np.empty((n, 2 * half), np.float32)
    z[:, 0::2] = (r * np.cos(theta)).reshape(n, half)
    z[:, 1::2] = (r * np.sin(theta)).reshape(n, half)
    return z[:, :p]


def sample_around(device, cand, sig, n, lo, hi, *, per_candidate, keep_candidates):
    c, p = cand.shape
    k = np.arange(n)
    owner = k * c // n  # sample k belongs to candidate k C // K
    z = normals(n, p, lo, hi)
    s = sig[owner] if per_candidate else sig[None, :]
    out = cand[owner] + s * z  # eq. 12: p_c + dp, dp ~ N(0, diag(sigma^2))
    if keep_candidates:
        first = k == (owner * n + c - 1) // c  # the first sample of each block
        out[first] = cand[owner[first]]
    return out.astype(np.float32)


def best_k(device, scores, k, rows, out):
    """out: the (idx, val, sel) arrays to write (gputrack/ops/particles.py best_k_out)."""
    idx = np.argsort(sortable_key(scores), kind="stable")[:k]  # ascending, ties by index
    out[0][...] = idx
    out[1][...] = scores[idx]
    if rows is not None:
        out[2][...] = rows[idx]
    return out


def sortable_key(scores: np.ndarray) -> np.ndarray:
    """uint32 keys that order float32 scores ascending (-inf < ... < +inf < NaN), as the kernels do."""
    bits = np.ascontiguousarray(scores, np.float32).view(np.uint32)
    key = np.where(bits >> 31 == 1, ~bits, bits | np.uint32(0x80000000)).astype(np.uint32)
    nan = (bits & np.uint32(0x7FFFFFFF)) > np.uint32(0x7F800000)
    return np.where(nan, np.uint32(0xFFFFFFFF), key).astype(np.uint32)
