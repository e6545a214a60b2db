"""The 3D sparse template of paper 000 (sec. 2.3), built from a rendering of the model.

Render the textured model alone at a pose (hidden-surface removal, exact z-buffer); on the
visible surface pick N local intensity extrema (maxima and minima of the gray image) -> points
(X_i, Y_i, Z_i; T_i), and N' local extrema of the z-buffer -> points (X'_i, Y'_i, Z'_i). Each
point belongs to the part whose surface it lies on and is stored in that part's coordinates,
so that any pose maps it to the camera (``transforms[b, part] @ [x, y, z, 1]``).

Selection, deterministic:
- candidates are pixels at least ``border`` pixels inside their part's visible region (away
  from silhouettes and occlusion edges, where a small pose error changes what is seen) that are
  a maximum or a minimum of the value over a ``window`` x ``window`` neighbourhood of the same
  part; their strength is their distance from that neighbourhood's mean (local contrast);
- the points are spread over the parts: every visible part gets a share (half of N split
  equally among the visible parts, half by visible area), capped by what the part offers;
- within a part, candidates are taken strongest first with non-maximum suppression: no two
  points closer than ``spacing`` pixels (ties broken by pixel order);
- where a part has fewer extrema than its share (the z-buffer of a smooth limb has few: mostly
  the ridge nearest the camera), the rest are filled by farthest-point sampling of the part's
  interior pixels, so that the points still cover the part; the fill prefers pixels whose row
  and column no point has yet (rook-spread), so the points fall on as many image rows and
  columns as they can. A surface whose depth changes along one image direction only (an upright
  torso seen from the front) then gives as many distinct depths, and as many positions relative
  to a quantised sensor's steps, as there are points, instead of a few columns' worth (on the
  simulator's 5 mm depth, Table 7's protocol with ``depth_tol=2.5``, 6 trials: the torso's mean
  turn error 0.18 -> 0.11 deg).
The RGB template's value is the intensity T_i; the depth template's value is the point's
camera depth Z at the rendered pose (mm).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from ...models.camera import DEFAULT_SIZE
from ...models.chain import Chain
from ...models.render import Rendering, Texture, render
from ...ops.template import SparseTemplate

__all__ = ["TemplatePixels", "frame_template", "select_pixels", "sparse_template"]


@dataclasses.dataclass(frozen=True)
class TemplatePixels:
    """Chosen pixels: ``rows``, ``cols`` (N,) int, ``part`` (N,) int32, grouped by part."""

    rows: np.ndarray
    cols: np.ndarray
    part: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)


def _interior(part_img: np.ndarray, border: int) -> np.ndarray:
    """True where every pixel within ``border`` (a square) carries the same part id (>= 0)."""
    if border <= 0:
        return part_img >= 0
    size = 2 * border + 1
    lo = ndimage.minimum_filter(part_img, size=size, mode="constant", cval=-1)
    hi = ndimage.maximum_filter(part_img, size=size, mode="constant", cval=-1)
    return (lo == hi) & (part_img >= 0)


def _quotas(n: int, available: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Split n points over parts: half equally among parts with pixels, half by area; cap by availability."""
    q = np.zeros(len(area), dtype=np.int64)
    visible = available > 0
    if not visible.any():
        return q
    nv = int(visible.sum())
    want = np.where(visible, 0.5 * n / nv + 0.5 * n * area / max(area[visible].sum(), 1), 0.0)
    q = np.floor(want).astype(np.int64)
    order = np.argsort(-(want - q), kind="stable")  # largest remainders first
    for j in order[: n - int(q.sum())]:
        q[j] += 1
    while True:  # cap by availability, give the excess to parts with room (largest area first)
        excess = int(np.maximum(q - available, 0).sum())
        q = np.minimum(q, available)
        if excess == 0:
            return q
        room = np.flatnonzero(q < available)
        if room.size == 0:
            return q
        for j in room[np.argsort(-area[room], kind="stable")]:
            take = min(excess, int(available[j] - q[j]))
            q[j] += take
            excess -= take
            if excess == 0:
                break


def _nms(rows, cols, order, k, spacing):
    """Greedy: take candidates in ``order`` skipping any within ``spacing`` px of a taken one; up to k."""
    taken = []
    r = rows[order].astype(np.float64)
    c = cols[order].astype(np.float64)
    tr, tc = np.empty(k), np.empty(k)
    for i in range(len(order)):
        if len(taken) == k:
            break
        m = len(taken)
        if m and np.min((tr[:m] - r[i]) ** 2 + (tc[:m] - c[i]) ** 2) < spacing * spacing:
            continue
        tr[m], tc[m] = r[i], c[i]
        taken.append(order[i])
    return np.asarray(taken, dtype=np.int64)


def _farthest(rows, cols, chosen_r, chosen_c, k):
    """Farthest-point sampling, rook-spread: k more of the pixels (rows, cols), each farthest from all
    chosen so far among those whose row and column no chosen point has (then those with a new row
    or a new column, then any), so that the points' rows and columns are as many as they can be."""
    r = rows.astype(np.float64)
    c = cols.astype(np.float64)
    out = []
    chosen_r, chosen_c = np.asarray(chosen_r, np.int64), np.asarray(chosen_c, np.int64)
    row_used = np.zeros(int(np.concatenate([rows, chosen_r]).max()) + 1, bool)
    col_used = np.zeros(int(np.concatenate([cols, chosen_c]).max()) + 1, bool)
    row_used[chosen_r] = col_used[chosen_c] = True
    if len(chosen_r):
        cr = chosen_r.astype(np.float64)[None]
        cc = chosen_c.astype(np.float64)[None]
        d = np.min((r[:, None] - cr) ** 2 + (c[:, None] - cc) ** 2, axis=1)
    elif k > 0:  # start from the pixel nearest the centroid
        first = int(np.argmin((r - r.mean()) ** 2 + (c - c.mean()) ** 2))
        out.append(first)
        row_used[rows[first]] = col_used[cols[first]] = True
        d = (r - r[first]) ** 2 + (c - c[first]) ** 2
    while len(out) < k:
        new_r, new_c = ~row_used[rows], ~col_used[cols]
        for eligible in (new_r & new_c, new_r | new_c, None):
            score = d if eligible is None else np.where(eligible, d, 0.0)
            i = int(np.argmax(score))  # the first among ties: deterministic
            if score[i] > 0:
                break
        if d[i] <= 0:
            break
        out.append(i)
        row_used[rows[i]] = col_used[cols[i]] = True
        d = np.minimum(d, (r - r[i]) ** 2 + (c - c[i]) ** 2)
    return np.asarray(out, dtype=np.int64)


def select_pixels(
    values: np.ndarray,
    part_img: np.ndarray,
    n: int,
    *,
    n_parts: int | None = None,
    window: int = 5,
    border: int = 2,
    spacing: float = 4.0,
) -> TemplatePixels:
    """Pick up to ``n`` pixels at local extrema of ``values`` (H, W), spread over the parts of ``part_img``.

    See the module docstring for the rule. Returns fewer than ``n`` only when the visible
    surface has fewer pixels.
    """
    values = np.asarray(values, dtype=np.float64)
    part_img = np.asarray(part_img)
    if values.shape != part_img.shape or values.ndim != 2:
        raise ValueError(
            f"values and part image: expected the same (H, W) shape, got {values.shape} and {part_img.shape}"
        )
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window: expected an odd size >= 3, got {window}")
    if n < 1:
        raise ValueError(f"n: expected at least 1 point, got {n}")
    j_max = int(part_img.max()) + 1 if n_parts is None else int(n_parts)
    # work on the model's bounding box (plus the window) only
    ys, xs = np.nonzero(part_img >= 0)
    if ys.size == 0:
        return TemplatePixels(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int32))
    pad = max(window // 2, border) + 1
    oy, ox = max(ys.min() - pad, 0), max(xs.min() - pad, 0)
    crop = (slice(oy, ys.max() + pad + 1), slice(ox, xs.max() + pad + 1))
    values, part_img = values[crop], part_img[crop]
    interior = _interior(part_img, border)
    area = np.array([(part_img == j).sum() for j in range(j_max)], dtype=np.float64)
    pools = []
    for j in range(j_max):
        pool = interior & (part_img == j)
        if not pool.any():
            pool = part_img == j  # too thin for the border: use what is visible
        pools.append(pool)
    available = np.array([p.sum() for p in pools], dtype=np.int64)
    quota = _quotas(n, available, area)

    half = window // 2
    rows_out, cols_out, part_out = [], [], []
    for j in range(j_max):
        if quota[j] == 0:
            continue
        ys, xs = np.nonzero(part_img == j)
        y0, y1 = max(ys.min() - half, 0), min(ys.max() + half + 1, part_img.shape[0])
        x0, x1 = max(xs.min() - half, 0), min(xs.max() + half + 1, part_img.shape[1])
        mine = part_img[y0:y1, x0:x1] == j
        v = values[y0:y1, x0:x1]
        hi = ndimage.maximum_filter(np.where(mine, v, -np.inf), size=window, mode="constant", cval=-np.inf)
        lo = ndimage.minimum_filter(np.where(mine, v, np.inf), size=window, mode="constant", cval=np.inf)
        pool = pools[j][y0:y1, x0:x1]
        extremum = pool & ((v >= hi) | (v <= lo)) & (hi > lo)
        cr, cc = np.nonzero(extremum)
        # strength: distance from the neighbourhood's mean (same part), so a plateau pixel
        # beside a peak is a weak minimum and the peak a strong maximum
        w = mine.astype(np.float64)
        mean = ndimage.uniform_filter(np.where(mine, v, 0.0), size=window, mode="constant")
        mean /= np.maximum(ndimage.uniform_filter(w, size=window, mode="constant"), 1e-12)
        strength = np.abs(v - mean)[cr, cc]
        order = np.lexsort((np.arange(len(cr)), -strength))  # strongest first, then pixel order
        picked = _nms(cr, cc, order, int(quota[j]), spacing)
        pr, pc = cr[picked], cc[picked]
        missing = int(quota[j]) - len(picked)
        if missing > 0:
            fr, fc = np.nonzero(pool)
            fill = _farthest(fr, fc, pr, pc, missing)
            pr = np.concatenate([pr, fr[fill]])
            pc = np.concatenate([pc, fc[fill]])
        rows_out.append(pr + y0 + oy)
        cols_out.append(pc + x0 + ox)
        part_out.append(np.full(len(pr), j, np.int32))
    if not rows_out:
        return TemplatePixels(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int32))
    return TemplatePixels(np.concatenate(rows_out), np.concatenate(cols_out), np.concatenate(part_out))


def sparse_template(
    chain: Chain,
    params=None,
    n: int = 128,
    n_depth: int = 128,
    *,
    camera=None,
    size: tuple[int, int] = DEFAULT_SIZE,
    rendering: Rendering | None = None,
    texture: Texture | None = None,
    shading: float = 0.2,
    window: int = 5,
    border: int = 2,
    spacing: float = 4.0,
) -> tuple[SparseTemplate, SparseTemplate]:
    """(RGB template, depth template) of ``chain`` at pose ``params`` (P,).

    Renders the model alone (no background, exact depth) unless ``rendering`` (such a rendering,
    e.g. one already made) is given. The RGB template has ``n`` points with value T_i = the
    intensity; the depth template ``n_depth`` points with value Z_i = camera depth (mm). Both
    hold points in part coordinates with their part index. Raises ValueError when the model is
    not visible at all.
    """
    if rendering is None:
        rendering = render(
            chain, params, camera, size, texture=texture, background=None, depth_step=0.0, shading=shading
        )
    if not (rendering.part >= 0).any():
        raise ValueError("sparse_template: no visible model surface at this pose (the model is out of view)")
    out = []
    for count, values, name in ((n, rendering.gray, "RGB"), (n_depth, rendering.points[..., 2], "depth")):
        px = select_pixels(
            values, rendering.part, count, n_parts=chain.n_parts, window=window, border=border, spacing=spacing
        )
        xyz = rendering.local[px.rows, px.cols]
        out.append(SparseTemplate(xyz, px.part, values[px.rows, px.cols].astype(np.float32)))
    return out[0], out[1]


def frame_template(gray, depth, camera, n: int = 128, n_depth: int = 128, *, edge: float = 0.02,
                   **select) -> tuple[SparseTemplate, SparseTemplate]:  # fmt: skip
    """(RGB, depth) templates of a rigid scene from a real RGB-D frame, in that frame's camera coordinates.

    The rigid case of sec. 2.3: the "model" is the measured surface itself, one part (0). Points
    are local extrema of the gray image and of the depth map among the pixels with a depth
    measurement (> 0 and finite) away from depth discontinuities (a 3x3 depth span over ``edge``
    times the depth), back-projected with ``camera``
    (X = (u - cx) Z / fx, Y = (v - cy) Z / fy, in the depth unit). Tracking the pose of this
    part in a later frame (:func:`gputrack.models.rigid`, start at identity) gives the camera
    motion between the two frames. ``select`` passes options to :func:`select_pixels`.
    """
    gray = np.asarray(gray, dtype=np.float32)
    depth = np.asarray(depth, dtype=np.float32)
    if gray.shape != depth.shape or gray.ndim != 2:
        raise ValueError(f"gray and depth: expected the same (H, W) shape, got {gray.shape} and {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise ValueError("frame_template: expected a frame with depth measurements, got none")
    # depth discontinuities (occlusion edges) are not surface points: a small motion changes what
    # is seen there, so pixels whose 3x3 neighbourhood spans more than ``edge`` of their depth are
    # left out (with the border of select_pixels, the points stay away from them)
    d = np.where(valid, depth, 0.0)
    span = ndimage.maximum_filter(d, 3) - ndimage.minimum_filter(np.where(valid, depth, np.inf), 3)
    smooth = valid & (span <= edge * np.where(valid, depth, 1.0))
    part_img = np.where(smooth, 0, -1).astype(np.int32)
    out = []
    for count, values in ((n, gray), (n_depth, np.where(valid, depth, 0.0))):
        px = select_pixels(values, part_img, count, n_parts=1, **select)
        z = depth[px.rows, px.cols].astype(np.float64)
        x = (px.cols - camera.cx) * z / camera.fx
        y = (px.rows - camera.cy) * z / camera.fy
        xyz = np.stack([x, y, z], axis=1).astype(np.float32)
        value = gray[px.rows, px.cols] if values is gray else depth[px.rows, px.cols]
        out.append(SparseTemplate(xyz, px.part, value.astype(np.float32)))
    return out[0], out[1]
