"""NumPy reference of :mod:`gputrack.ops.model_template`: render the model, classify the pixels,
take the extrema and fill (steps 1-8 of the op's docstring, in that order).

The render is :func:`gputrack.models.render.render` (float64); every later step is integer
arithmetic on q = floor(v s), so the devices pick exactly these pixels from the same images.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from ...models.render import render as render_chain
from .particles import pcg

__all__ = ["NO_ROW", "STATS", "classify", "emit", "render", "render_dtype"]

#: columns of the per-part statistics: area, interior count, interior rows and columns (min, max),
#: all pixels' rows and columns (min, max)
STATS = ("area", "interior", "ir0", "ir1", "ic0", "ic1", "ar0", "ar1", "ac0", "ac1")
NO_ROW = 1 << 30  # the initial minimum of a row or column range


def render_dtype(device):
    """The type the render computes in: float64 (gputrack.models.render.render)."""
    return np.float64


def render(device, chain, transforms, texture, table, waves, consts, crop, part, values, local):
    """Step 1 into ``part``, ``values``, ``local`` (the reference renders the whole box region)."""
    fx, fy, cx, cy, _, shading = (float(c) for c in consts)
    from ...models.camera import Camera

    H, W = part.shape
    cam = Camera(fx=fx, fy=fy, cx=cx, cy=cy)
    r = render_chain(chain, camera=cam, size=(W, H), transforms=transforms, texture=texture, background=None,
                     depth_step=0.0, shading=shading)  # fmt: skip
    part[...] = r.part
    values[0] = r.gray
    values[1] = r.depth
    local[...] = r.local


def _shifted(a, dy, dx, fill):
    """a shifted so that out[r, c] = a[r + dy, c + dx] (``fill`` outside)."""
    out = np.full_like(a, fill)
    H, W = a.shape[-2:]
    ys, yd = (slice(dy, H), slice(0, H - dy)) if dy >= 0 else (slice(0, H + dy), slice(-dy, H))
    xs, xd = (slice(dx, W), slice(0, W - dx)) if dx >= 0 else (slice(0, W + dx), slice(-dx, W))
    out[..., yd, xd] = a[..., ys, xs]
    return out


def _padded(a, crop, pad, fill):
    """``a[..., r0 - pad:r1 + pad, c0 - pad:c1 + pad]`` with ``fill`` outside ``crop`` (pixels outside the
    crop belong to no part and are never read)."""
    r0, r1, c0, c1 = crop
    out = np.full((*a.shape[:-2], r1 - r0 + 2 * pad, c1 - c0 + 2 * pad), fill, a.dtype)
    out[..., pad:pad + r1 - r0, pad:pad + c1 - c0] = a[..., r0:r1, c0:c1]
    return out


def classify(device, part, values, crop, scales, window, border, interior_out, num_out, cnt, bins, stats, surv):
    """Steps 2-4: the interior flag, num[k] the strength numerator |c q - S| of extrema (-1
    elsewhere, int64), cnt the same-part window count; stats (J, 10); surv (2, J) the counts of candidates
    (pool extrema) and bins[k, start_j + i] their pixel indices (in pixel order here)."""
    J = stats.shape[0]
    W = part.shape[1]
    r0, r1, c0, c1 = crop
    pad = max(window // 2, border) + 1
    p = _padded(part, crop, pad, -1)
    model = p >= 0
    interior = model.copy()
    for dy in range(-border, border + 1):
        for dx in range(-border, border + 1):
            interior &= _shifted(p, dy, dx, -1) == p
    half = window // 2
    q = np.floor(_padded(values, crop, pad, 0).astype(np.float32) * scales.astype(np.float32)[:, None, None])
    q = np.where(model[None], q, 0).astype(np.int64)
    c = np.zeros(p.shape, np.int64)
    S = np.zeros((2, *p.shape), np.int64)
    hi = np.full((2, *p.shape), -(1 << 40), np.int64)
    lo = np.full((2, *p.shape), 1 << 40, np.int64)
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            same = (_shifted(p, dy, dx, -1) == p) & model
            qs = _shifted(q, dy, dx, 0)
            c += same
            S += np.where(same, qs, 0)
            hi = np.maximum(hi, np.where(same, qs, -(1 << 40)))
            lo = np.minimum(lo, np.where(same, qs, 1 << 40))
    extremum = model & (hi > lo) & ((q == hi) | (q == lo))
    num = np.where(extremum, np.abs(c * q - S), -1)
    inner = (slice(pad, -pad), slice(pad, -pad))
    interior_out[r0:r1, c0:c1] = interior[inner]
    num_out[:, r0:r1, c0:c1] = num[(slice(None), *inner)]
    cnt[r0:r1, c0:c1] = c[inner]
    st = np.zeros((J, len(STATS)), np.int64)
    st[:, 2::2] = NO_ROW
    st[:, 3::2] = -1
    rows, cols = np.nonzero(model)
    for j in range(J):
        for base, mask in ((6, model), (2, interior)):  # all pixels: columns 6-9; interior: 2-5
            m = mask[rows, cols] & (p[rows, cols] == j)
            st[j, 0 if base == 6 else 1] = m.sum()
            if m.any():
                rr, cc = rows[m] - pad + r0, cols[m] - pad + c0
                st[j, base:base + 4] = rr.min(), rr.max(), cc.min(), cc.max()
    stats[...] = st
    pool = model & (interior | (st[np.maximum(p, 0), 1] == 0))
    yy, xx = np.indices(p.shape)
    idx = (yy - pad + r0) * W + (xx - pad + c0)  # the full image's pixel index
    starts = np.concatenate([[0], np.cumsum(st[:, 0])[:-1]])
    for k in range(2):
        cand = pool & (num[k] >= 0)
        for j in range(J):
            mine = np.sort(idx[cand & (p == j)])
            surv[k, j] = mine.size
            bins[k, starts[j]:starts[j] + mine.size] = mine


def _greedy(sv, num, cnt, W, quota, s2):
    """Step 6: the candidates ``sv`` (pixel indices) strongest first, each taken unless a taken one
    lies closer than the spacing; at most ``quota``."""
    # strongest first (|c q - S| / c as exact fractions: numerators up to 2**47), ties by the pcg hash
    # of the pixel index, then the index
    tie = pcg(sv.astype(np.uint32))
    order = sorted(range(len(sv)), key=lambda i: (-Fraction(int(num[sv[i]]), int(cnt[sv[i]])), int(tie[i]),
                                                  int(sv[i])))  # fmt: skip
    taken_r, taken_c, taken = [], [], []
    for o in order:
        if len(taken) == quota:
            break
        r, c = divmod(int(sv[o]), W)
        if taken and min((r - tr) ** 2 + (c - tc) ** 2 for tr, tc in zip(taken_r, taken_c)) < s2:
            continue
        taken.append(int(sv[o]))
        taken_r.append(r)
        taken_c.append(c)
    return taken


def _farthest(rows, cols, chosen_r, chosen_c, m):
    """Step 7: m more of the pool pixels (rows, cols) (pixel order), each farthest from all chosen
    so far, preferring those whose row and column no chosen point has (then a new row or a new
    column, then any); the first among ties. With nothing chosen, the first is the pixel nearest the
    pool's centroid (integer arithmetic)."""
    rows, cols = rows.astype(np.int64), cols.astype(np.int64)
    out = []
    row_used = np.zeros(int(max(rows.max(), *chosen_r, 0)) + 1, bool)
    col_used = np.zeros(int(max(cols.max(), *chosen_c, 0)) + 1, bool)
    row_used[chosen_r] = col_used[chosen_c] = True
    if len(chosen_r):
        cr, cc = np.asarray(chosen_r)[None], np.asarray(chosen_c)[None]
        d = np.min((rows[:, None] - cr) ** 2 + (cols[:, None] - cc) ** 2, axis=1)
    else:
        n = len(rows)
        first = int(np.argmin((n * rows - rows.sum()) ** 2 + (n * cols - cols.sum()) ** 2))
        out.append(first)
        row_used[rows[first]] = col_used[cols[first]] = True
        d = (rows - rows[first]) ** 2 + (cols - cols[first]) ** 2
    while len(out) < m:
        new_r, new_c = ~row_used[rows], ~col_used[cols]
        for eligible in (new_r & new_c, new_r | new_c, None):
            score = d if eligible is None else np.where(eligible, d, 0)
            i = int(np.argmax(score))  # the first among ties
            if score[i] > 0:
                break
        out.append(i)
        row_used[rows[i]] = col_used[cols[i]] = True
        d = np.minimum(d, (rows - rows[i]) ** 2 + (cols - cols[i]) ** 2)
    return out


def emit(device, part, values, local, crop, plan, stats, surv, bins, interior, num_img, cnt, dist, used, s2, out0, out1):
    """Steps 6-8 per kind and part: the greedy extrema, then the farthest-point fill, written into
    out0 (RGB) and out1 (depth)."""
    W = part.shape[1]
    r0c, r1c, c0c, c1c = crop
    p = part[r0c:r1c, c0c:c1c]
    for k, out in enumerate((out0, out1)):
        num = num_img[k].ravel()
        for j in range(stats.shape[0]):
            offset, quota, start = (int(x) for x in plan[k, j, :3])
            if quota == 0:
                continue
            sv = bins[k, start:start + int(surv[k, j])].astype(np.int64)
            chosen = _greedy(sv, num, cnt.ravel(), W, quota, s2)
            pool = (p == j) & ((interior[r0c:r1c, c0c:c1c] != 0) if stats[j, 1] > 0 else True)
            pr, pc = np.nonzero(pool)
            pr, pc = pr + r0c, pc + c0c
            cr, cc = (list(x) for x in np.divmod(np.asarray(chosen, np.int64), W)) if chosen else ([], [])
            fill = _farthest(pr, pc, cr, cc, quota - len(chosen))
            rows = np.concatenate([np.asarray(cr, np.int64), pr[fill]]).astype(np.int64)
            cols = np.concatenate([np.asarray(cc, np.int64), pc[fill]]).astype(np.int64)
            out[offset:offset + quota, :3] = local[rows, cols]
            out[offset:offset + quota, 3] = values[k][rows, cols]
