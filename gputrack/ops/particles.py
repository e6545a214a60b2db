"""Particle-filter helpers that keep the filter on the device (paper 000 sec. 3.1, eq. 12).

- :func:`sample_around`: K samples p_c + dp around C candidate poses, dp ~ N(0, diag(sigma^2))
  (eq. 12), from a counter-based generator keyed by the caller's seed: no state, the same seed
  gives the same samples on a device, and a sample depends only on (seed, its index), so any
  backend can draw it without a round trip. Backends share the generator (a PCG hash of the
  counter, Box-Muller), so they agree to float rounding, but only the distribution is promised.
- :func:`best_k`: the k lowest scores of B (ascending cost) and, optionally, their rows (the next
  candidates), on the device.

Sample k belongs to candidate ``c = k * C // K`` (contiguous blocks, so that a block of
consecutive hypotheses lies around one candidate, which is what the template kernels' lanes
like). With ``keep_candidates=True`` the first sample of each block is the candidate itself
(dp = 0), so a stage never loses its best pose.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..device import DeviceArray, as_host_array
from . import backend_module
from ._args import arg, check_device, check_shapes, out_array

__all__ = ["BestK", "best_k", "sample_around"]

MAX_SEED = 2**64


def _seed(seed) -> tuple[int, int]:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed: expected an integer in [0, 2**64), got {type(seed).__name__}")
    s = int(seed)
    if not 0 <= s < MAX_SEED:
        raise ValueError(f"seed: expected an integer in [0, 2**64), got {s}")
    return s & 0xFFFFFFFF, s >> 32


def sample_around(device, candidates, sigma, n, seed, *, keep_candidates=False):
    """Draw ``n`` samples around C candidates: (n, P) float32 (eq. 12).

    candidates: (C, P) float32; sigma: (P,) or (C, P) float32 standard deviations (>= 0), per
    parameter or per candidate and parameter; n: number of samples (>= 1); seed: integer in
    [0, 2**64), e.g. ``rng.integers(2**63)`` from the caller's seeded generator (use a new seed
    per call). See the module docstring for the block layout and ``keep_candidates``. A sigma
    already on the device is not checked for negative values (that would cost a download).
    """
    check_device(device)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"n: expected an integer number of samples, got {type(n).__name__}")
    if int(n) < 1:
        raise ValueError(f"n: expected at least one sample, got {n}")
    lo, hi = _seed(seed)
    if not isinstance(sigma, DeviceArray):
        host = as_host_array(sigma, "sigma")
        if host.dtype.kind in "biuf" and (host < 0).any():
            raise ValueError(f"sigma: expected standard deviations >= 0, got {host.min()}")
    dims = {}
    cand = arg(device, candidates, "candidates", ("C", "P"), dims)
    if dims["C"] == 0 or dims["P"] == 0:
        raise ValueError(f"candidates: expected at least one candidate and one parameter, got shape {cand.shape}")
    per_candidate = len(getattr(sigma, "shape", np.shape(sigma))) != 1
    sig = arg(device, sigma, "sigma", ("C", "P") if per_candidate else ("P",), dims)
    if int(n) * (dims["P"] + 1) >= 2**31 or int(n) * dims["C"] >= 2**31:
        raise ValueError(f"n: expected n * (P + 1) and n * C below 2**31 (the generator's counter), got n={n}")
    return backend_module(device, "particles").sample_around(
        device, cand, sig, int(n), lo, hi, per_candidate=per_candidate, keep_candidates=bool(keep_candidates)
    )


@dataclasses.dataclass
class BestK:
    """The k best of B scores, ascending: ``indices`` (k,) int32, ``scores`` (k,) float32, and
    ``rows`` (k, P) float32 (the selected rows) when rows were given, else None."""

    indices: object
    scores: object
    rows: object = None


def best_k(device, scores, k, rows=None, *, out=None) -> BestK:
    """Select the k lowest of B scores on the device (ascending cost), one launch.

    scores: (B,) float32 (NaN ranks after +inf); ties keep the lower index first; k in [1, B];
    rows: optional (B, P) float32 (e.g. the samples) whose selected rows are returned too.
    ``out``: a BestK on the device (e.g. an earlier result of the same sizes) to write into
    instead of allocating; its ``rows`` must not be ``rows``.
    The selection is a single pass with an ordered k-list (O(B k)): meant for k << B.
    """
    check_device(device)
    check_shapes({}, (scores, "scores", ("B",)), (rows, "rows", ("B", "P")))  # before any value is read
    dims = {}
    s = arg(device, scores, "scores", ("B",), dims, finite=False)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise TypeError(f"k: expected an integer, got {type(k).__name__}")
    if not 1 <= int(k) <= dims["B"]:
        raise ValueError(f"k: expected 1 <= k <= B={dims['B']}, got {k}")
    r = None
    if rows is not None:
        r = arg(device, rows, "rows", ("B", "P"), dims, finite=False)
        if dims["P"] == 0:
            raise ValueError(f"rows: expected at least one column, got shape {r.shape}")
    outs = best_k_out(device, out, int(k), dims.get("P"), r)
    idx, val, sel = backend_module(device, "particles").best_k(device, s, int(k), r, outs)
    return BestK(idx, val, sel)


def best_k_out(device, out, k: int, P: int | None, rows=None):
    """The output arrays (idx, val, rows) of best_k / pf_stage: ``out``'s after checking it (a BestK
    of k indices, k scores and, when P is not None, (k, P) rows, on ``device``), or new ones."""
    if out is not None and not isinstance(out, BestK):
        raise TypeError(f"out: expected a gputrack.BestK (e.g. an earlier result), got {type(out).__name__}")
    if out is not None and rows is not None and out.rows is rows:
        raise ValueError("out.rows: expected an array other than the rows selected from")

    def one(name, shape, dtype):
        return out_array(device, None if out is None else getattr(out, name), f"out.{name}", shape, dtype)

    idx, val = one("indices", (k,), np.int32), one("scores", (k,), np.float32)
    return idx, val, (one("rows", (k, P), np.float32) if P is not None else None)
