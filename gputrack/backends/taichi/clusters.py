"""Taichi kernels of :mod:`gputrack.ops.clusters`: the whole op in one launch on CPU and CUDA.

The kernel ``_clusters`` runs its top-level loops one after the other (Taichi puts a barrier
between them); radius_components is dbscan with min_samples = 1 (every point is core):

1. bucket counts and loose flags zeroed;
2. each point's hashed grid cell, of side r (1 - CELL_SLACK) / sqrt(dim), so that any two points
   of a cell are neighbours; its rank in its bucket by an atomic add (a NaN row: no bucket);
3. the exclusive scan of the bucket counts (chunk sums, a serial scan of the chunks, chunk scans);
4. the points scattered in bucket order (a copy of their coordinates beside their indices);
5. neighbour counts, the point's own cell first, stopping at min_samples -> core flags;
6. union-find by atomic min (min-label hooking, path halving): (a) each core point joins its
   cell's head (the cell's first core point); (b) the bounding box of each cell's core points;
   (c) each head links its cell A to every cell B that can hold a neighbour (B's head in the box
   of A's core points +- w, w = r (1 + CELL_SLACK), and the boxes of A and B within r): unless A and
   B are connected already, the first pair of their core points within r is united, each pair of
   cells from the smaller head slot;
7. labels: the root of each core point (its component's smallest index), -1 for the rest;
8. each border point takes the smallest label among its core neighbours.

A neighbour search visits the cells of the box p +- w (floor((p +- w) / side) per axis: exact
whatever the rounding, floor and rounding being monotone) and takes a candidate only in its own
cell, so that two cells sharing a bucket do not count a point twice. Where float32 rounding of
huge coordinates puts points farther apart than r into one cell, step 6a marks the bucket loose
and 6c links its cells pair by pair, with no shortcut.

Taichi 1.7.4 on Vulkan (lavapipe) loses atomic updates made inside loops when invocations
contend (seen with a plain atomic add), so on Vulkan steps 6-8 are replaced by launches of ROUNDS
rounds of min-label hooking and pointer jumping with plain stores (``_rounds``: every write
sets a parent to a smaller index of the same component, so there are no cycles and a lost race
only costs rounds), a changed
flag read back after each launch, then ``_finish`` (steps 7-8). Small problems run every loop on
the calling thread (a parallel loop's dispatch costs more than the work). Conventions:
gputrack/ops/clusters.py.
"""

import dataclasses

import numpy as np

from .launch import launch
from .runtime import current_arch, scratch, ti

#: the searched box is p +- r (1 + CELL_SLACK) (a neighbour found by the float32 test d2 <= r2 lies
#: inside it whatever the rounding), the cell side r (1 - CELL_SLACK) / sqrt(dim) (as
#: gputrack/backends/opencl/clusters.py)
CELL_SLACK = 1e-3
#: two cells whose boxes are farther apart than r (with this relative margin on r2) cannot link
GAP_SLACK = 1.01
#: buckets are scanned in chunks of this many
CHUNK = 256
#: problems of at most this many points run on the calling thread (taichi:cpu)
SERIAL_POINTS = 2048
#: hooking rounds per launch where atomics are not used (taichi:vulkan)
ROUNDS = 8
#: at most this many launches of ROUNDS rounds (a path graph of N points converges in about
#: log2(N) rounds)
MAX_LAUNCHES = 64
#: the archs whose atomic min under contention gputrack trusts (Taichi 1.7.4 on lavapipe Vulkan
#: loses atomic updates made in a loop when invocations contend)
ATOMIC_ARCHS = ("cpu", "cuda")
#: cell coordinates are clamped to +-CLAMP before the cast to int (monotone, so still exact)
CLAMP = float(1 << 30)

nd = ti.types.ndarray()


@dataclasses.dataclass(frozen=True)
class _Variant:
    dim: int
    serial: bool
    atomic: bool  # union-find by atomic min; else rounds of hooking with plain stores


def grid(r2, dim: int):
    """(w, inv): the half-width of the searched box, r (1 + CELL_SLACK), and 1 / the cell side,
    r (1 - CELL_SLACK) / sqrt(dim) (any two points of a cell are neighbours), in float32."""
    r = np.sqrt(np.float64(r2))
    w = np.float32(r * (1.0 + CELL_SLACK))
    inv = np.float32(np.sqrt(dim) / (r * (1.0 - CELL_SLACK)))
    return w, inv


def buckets(N: int) -> int:
    """Number of hash buckets for N points: a power of two >= 2N, at least one chunk."""
    return max(CHUNK, 1 << max(0, (2 * N - 1).bit_length()))


@ti.func
def _cell(x, inv):
    c = ti.floor(x * inv)
    return ti.cast(ti.min(ti.max(c, -CLAMP), CLAMP), ti.i32)


@ti.func
def _hash(cx, cy, cz, mask):
    h = (ti.cast(cx, ti.u32) * ti.u32(73856093)) ^ (ti.cast(cy, ti.u32) * ti.u32(19349663))
    h = h ^ (ti.cast(cz, ti.u32) * ti.u32(83492791))
    return ti.cast(h & ti.cast(mask, ti.u32), ti.i32)


@ti.func
def _find(parent: ti.template(), x):
    """Root of x with path halving by atomic min (a parent only ever decreases)."""
    root = x
    p = parent[root]
    while p != root:
        gp = parent[p]
        if gp < p:
            ti.atomic_min(parent[root], gp)
        root = p
        p = parent[root]
    return root


@ti.func
def _union(parent: ti.template(), a0, b0):
    """Hook the larger root under the smaller; retry where another edge hooked it first."""
    a = a0
    b = b0
    done = False
    while not done:
        a = _find(parent, a)
        b = _find(parent, b)
        if a == b:
            done = True
        else:
            hi = ti.max(a, b)
            lo = ti.min(a, b)
            old = ti.atomic_min(parent[hi], lo)
            if old == hi:
                done = True
            else:  # hi was hooked under old meanwhile: join old and lo
                a = old
                b = lo


@ti.func
def _point(pts: ti.template(), i, dim: ti.template()):
    q = ti.Vector([0.0, 0.0, 0.0], dt=ti.f32)
    for k in ti.static(range(dim)):
        q[k] = pts[i, k]
    return q


@ti.func
def _d2(p, q, dim: ti.template()):
    d0 = p[0] - q[0]
    d1 = p[1] - q[1]
    d2 = d0 * d0 + d1 * d1
    if ti.static(dim == 3):
        d2 = d2 + (p[2] - q[2]) * (p[2] - q[2])
    return d2


@ti.func
def _same_cell(q, c, inv, dim: ti.template()):
    same = _cell(q[0], inv) == c[0] and _cell(q[1], inv) == c[1]
    if ti.static(dim == 3):
        same = same and _cell(q[2], inv) == c[2]
    return same


@ti.func
def _scan(i, p, mode: ti.template(), dim: ti.template(), order: ti.template(), spts: ti.template(),
          start: ti.template(), core: ti.template(), parent: ti.template(), out: ti.template(),
          r2, w, inv, ms, mask):  # fmt: skip
    """Visit the neighbours j of point i (coordinates p). mode 0: count them (up to ms), returns
    the count; 2: the smallest label (out) of the core neighbours (2**31 - 1 if none); 3: the
    smallest parent of the core neighbours."""
    lo = ti.Vector([0, 0, 0])
    hi = ti.Vector([0, 0, 0])
    for k in ti.static(range(dim)):
        lo[k] = _cell(p[k] - w, inv)
        hi[k] = _cell(p[k] + w, inv)
    acc = 0
    if ti.static(mode >= 2):
        acc = 2147483647
    stop = False
    own = ti.Vector([0, 0, 0])
    for k in ti.static(range(dim)):
        own[k] = _cell(p[k], inv)
    if ti.static(mode == 0):  # the point's own cell first: in a dense cell the count stops there
        b = _hash(own[0], own[1], own[2], mask)
        t = start[b]
        end = start[b + 1]
        while t < end and acc < ms:
            q = _point(spts, t, dim)
            if _same_cell(q, own, inv, dim) and _d2(p, q, dim) <= r2:
                acc += 1
            t += 1
        stop = acc >= ms
    cx = lo[0]
    while cx <= hi[0] and not stop:
        cy = lo[1]
        while cy <= hi[1] and not stop:
            cz = lo[2]
            while cz <= hi[2] and not stop:
                b = _hash(cx, cy, cz, mask)
                skip = False
                if ti.static(mode == 0):
                    skip = cx == own[0] and cy == own[1] and cz == own[2]  # counted above
                for t in range(start[b], start[b + 1]):
                    q = _point(spts, t, dim)
                    same = _cell(q[0], inv) == cx and _cell(q[1], inv) == cy
                    if ti.static(dim == 3):
                        same = same and _cell(q[2], inv) == cz
                    # neighbours (paper 001 eq. 12: linked points; paper 002: within eps)
                    if not skip and same and _d2(p, q, dim) <= r2:
                        j = order[t]
                        if ti.static(mode == 0):
                            acc += 1
                        elif ti.static(mode == 2):
                            if core[j] != 0:
                                acc = ti.min(acc, out[j])
                        else:
                            if core[j] != 0:
                                acc = ti.min(acc, parent[j])
                if ti.static(mode == 0):
                    stop = acc >= ms
                cz += 1
            cy += 1
        cx += 1
    return acc


@ti.func
def _first_core(c, b, dim: ti.template(), order: ti.template(), spts: ti.template(), start: ti.template(),
                core: ti.template(), inv):  # fmt: skip
    """The slot of the first core point of cell c in bucket b, or -1."""
    found = -1
    t = start[b]
    end = start[b + 1]
    while t < end and found < 0:
        if core[order[t]] != 0 and _same_cell(_point(spts, t, dim), c, inv, dim):
            found = t
        t += 1
    return found


@ti.func
def _link_cell(i, s, dim: ti.template(), order: ti.template(), spts: ti.template(), start: ti.template(),
               core: ti.template(), parent: ti.template(), loose: ti.template(), head: ti.template(), b, r2,
               inv):  # fmt: skip
    """Union core point i (slot s) with the first core point of its cell (the cell's head; any two
    points of a cell are neighbours). A pair that fails the distance test (rounding at huge
    coordinates) marks the bucket loose: its cells are then linked pair by pair."""
    p = _point(spts, s, dim)
    c = ti.Vector([0, 0, 0])
    for k in ti.static(range(dim)):
        c[k] = _cell(p[k], inv)
    t = _first_core(c, b, dim, order, spts, start, core, inv)
    head[s] = 1 if t == s else 0
    if t != s:
        j = order[t]
        if _d2(p, _point(spts, t, dim), dim) <= r2:
            _union(parent, i, j)
        else:
            loose[b] = 1


@ti.func
def _box(s, dim: ti.template(), order: ti.template(), spts: ti.template(), start: ti.template(),
         core: ti.template(), box: ti.template(), inv, mask):  # fmt: skip
    """box[s] = (lo, hi): the bounding box of the core points of the cell whose head is slot s."""
    p = _point(spts, s, dim)
    c = ti.Vector([0, 0, 0])
    for k in ti.static(range(dim)):
        c[k] = _cell(p[k], inv)
    lo = p
    hi = p
    for t in range(s, start[_hash(c[0], c[1], c[2], mask) + 1]):
        q = _point(spts, t, dim)
        if core[order[t]] != 0 and _same_cell(q, c, inv, dim):
            lo = ti.min(lo, q)
            hi = ti.max(hi, q)
    for k in ti.static(range(3)):
        box[s, k] = lo[k]
        box[s, 3 + k] = hi[k]


@ti.func
def _link_cells(s, dim: ti.template(), order: ti.template(), spts: ti.template(), start: ti.template(),
                core: ti.template(), parent: ti.template(), loose: ti.template(), box: ti.template(), r2, w, inv,
                mask):  # fmt: skip
    """Cell A (head slot s) with each cell B that can hold a neighbour of one of its points: unless
    they are connected already, the first pair of their core points within r is united (every pair
    where a bucket is loose). Each pair of cells is handled by the one with the smaller head slot."""
    pa = _point(spts, s, dim)
    cA = ti.Vector([0, 0, 0])
    for k in ti.static(range(dim)):
        cA[k] = _cell(pa[k], inv)
    bA = _hash(cA[0], cA[1], cA[2], mask)
    endA = start[bA + 1]
    tightA = loose[bA] == 0
    lo = ti.Vector([0.0, 0.0, 0.0], dt=ti.f32)  # the bounding box of A's core points
    hi = ti.Vector([0.0, 0.0, 0.0], dt=ti.f32)
    for k in ti.static(range(dim)):
        lo[k] = box[s, k]
        hi[k] = box[s, 3 + k]
    clo = ti.Vector([0, 0, 0])
    chi = ti.Vector([0, 0, 0])
    for k in ti.static(range(dim)):
        clo[k] = _cell(lo[k] - w, inv)
        chi[k] = _cell(hi[k] + w, inv)
    i = order[s]
    cx = clo[0]
    while cx <= chi[0]:
        cy = clo[1]
        while cy <= chi[1]:
            cz = clo[2]
            while cz <= chi[2]:
                cB = ti.Vector([cx, cy, cz])
                bB = _hash(cx, cy, cz, mask)
                tB = _first_core(cB, bB, dim, order, spts, start, core, inv)
                tight = tightA and loose[bB] == 0
                go = tB >= 0 and (tB > s or (not tight and tB == s))
                if go:  # the squared gap between the boxes of A and B: beyond r, no pair links
                    gap2 = ti.cast(0.0, ti.f32)
                    for k in ti.static(range(dim)):
                        g = ti.max(ti.max(box[tB, k] - hi[k], lo[k] - box[tB, 3 + k]), 0.0)
                        gap2 += g * g
                    go = gap2 <= r2 * GAP_SLACK
                if go and tight:
                    go = _find(parent, i) != _find(parent, order[tB])
                if go:  # the pairs of A x B until the first neighbours (all of them if not tight)
                    done = False
                    endB = start[bB + 1]
                    ta = s
                    while ta < endA and not done:
                        a = order[ta]
                        qa = _point(spts, ta, dim)
                        if core[a] != 0 and _same_cell(qa, cA, inv, dim):
                            tb = tB
                            while tb < endB and not done:
                                bpt = order[tb]
                                qb = _point(spts, tb, dim)
                                if core[bpt] != 0 and _same_cell(qb, cB, inv, dim):
                                    if _d2(qa, qb, dim) <= r2:  # paper 001 eq. 12: linked points
                                        _union(parent, a, bpt)
                                        done = tight
                                tb += 1
                        ta += 1
                cz += 1
            cy += 1
        cx += 1


@ti.kernel
def _clusters(pts: nd, out: nd, cnt: nd, start: nd, csum: nd, key: nd, rank: nd, order: nd, spts: nd,
              parent: nd, core: nd, loose: nd, head: nd, box: nd, n: ti.i32, N: ti.i32, H: ti.i32, chunks: ti.i32,
              r2: ti.f32, w: ti.f32,
              inv: ti.f32, ms: ti.i32, v: ti.template()):  # fmt: skip
    # N (rows of out), H (buckets) and chunks = H / CHUNK come as arguments: SPIR-V (Taichi Vulkan)
    # takes a top-level loop bound from an argument or a shape, not from an expression of them
    dim = ti.static(v.dim)
    mask = H - 1
    ti.loop_config(serialize=v.serial)
    for b in range(H):  # 1
        cnt[b] = 0
        loose[b] = 0
    ti.loop_config(serialize=v.serial)
    for i in range(n):  # 2: bin the points
        p = _point(pts, i, dim)
        valid = True
        for k in ti.static(range(dim)):
            if (ti.bit_cast(p[k], ti.u32) & ti.u32(0x7FFFFFFF)) > ti.u32(0x7F800000):
                valid = False  # a NaN row is not a point (a bit test: immune to fast math)
        parent[i] = i
        core[i] = 0
        key[i] = -1
        if valid:
            c = ti.Vector([0, 0, 0])
            for k in ti.static(range(dim)):
                c[k] = _cell(p[k], inv)
            b = _hash(c[0], c[1], c[2], mask)
            key[i] = b
            rank[i] = ti.atomic_add(cnt[b], 1)
            core[i] = 1
    ti.loop_config(serialize=v.serial)
    for c in range(chunks):  # 3: exclusive scan of the counts
        s = 0
        for k in range(c * CHUNK, (c + 1) * CHUNK):
            s += cnt[k]
        csum[c] = s
    ti.loop_config(serialize=True)
    for _ in range(1):
        run = 0
        for c in range(chunks):
            s = csum[c]
            csum[c] = run
            run += s
        start[H] = run
    ti.loop_config(serialize=v.serial)
    for c in range(chunks):
        run = csum[c]
        for k in range(c * CHUNK, (c + 1) * CHUNK):
            start[k] = run
            run += cnt[k]
    ti.loop_config(serialize=v.serial)
    for i in range(n):  # 4: scatter into bucket order
        b = key[i]
        if b >= 0:
            s = start[b] + rank[i]
            order[s] = i
            for k in ti.static(range(dim)):
                spts[s, k] = pts[i, k]
    # 5: core points (at least ms neighbours, the point itself included; ms = 1: every point)
    ti.loop_config(serialize=v.serial)
    for s in range(n):
        if s < start[H]:
            i = order[s]
            p = _point(spts, s, dim)
            c = _scan(i, p, 0, dim, order, spts, start, core, parent, out, r2, w, inv, ms, mask)
            if c < ms:
                core[i] = 0
    if ti.static(v.atomic):
        ti.loop_config(serialize=v.serial)
        for s in range(n):  # 6a: the core points of a cell (side < r / sqrt(dim)) are neighbours
            if s < start[H]:
                i = order[s]
                head[s] = 0
                if core[i] != 0:
                    _link_cell(i, s, dim, order, spts, start, core, parent, loose, head, key[i], r2, inv)
        ti.loop_config(serialize=v.serial)
        for s in range(n):  # 6b: the bounding box of each cell's core points
            if s < start[H]:
                if head[s] != 0:
                    _box(s, dim, order, spts, start, core, box, inv, mask)
        ti.loop_config(serialize=v.serial)
        for s in range(n):  # 6c: union-find over pairs of cells, from their heads
            if s < start[H]:
                if head[s] != 0:
                    _link_cells(s, dim, order, spts, start, core, parent, loose, box, r2, w, inv, mask)
        _finish_body(out, start, order, spts, parent, core, n, N, H, r2, w, inv, ms, v)


@ti.func
def _finish_body(out: ti.template(), start: ti.template(), order: ti.template(), spts: ti.template(),
                 parent: ti.template(), core: ti.template(), n, N, H, r2, w, inv, ms, v: ti.template()):  # fmt: skip
    dim = ti.static(v.dim)
    mask = H - 1
    ti.loop_config(serialize=v.serial)
    for i in range(N):  # 7: labels = roots (the smallest index of each component)
        lab = -1
        if i < n:
            if core[i] != 0:
                if ti.static(v.atomic):
                    lab = _find(parent, i)
                else:
                    lab = parent[i]  # converged rounds: every parent is a root
        out[i] = lab
    # 8: border points (none where ms = 1)
    ti.loop_config(serialize=v.serial)
    for s in range(n):
        if s < start[H]:
            i = order[s]
            if core[i] == 0:
                p = _point(spts, s, dim)
                m = _scan(i, p, 2, dim, order, spts, start, core, parent, out, r2, w, inv, ms, mask)
                if m < 2147483647:
                    out[i] = m


@ti.kernel
def _finish(out: nd, start: nd, order: nd, spts: nd, parent: nd, core: nd, n: ti.i32, N: ti.i32, H: ti.i32,
            r2: ti.f32, w: ti.f32, inv: ti.f32, ms: ti.i32, v: ti.template()):  # fmt: skip
    _finish_body(out, start, order, spts, parent, core, n, N, H, r2, w, inv, ms, v)


@ti.kernel
def _rounds(out: nd, start: nd, order: nd, spts: nd, parent: nd, core: nd, flag: nd, n: ti.i32, H: ti.i32,
            r2: ti.f32, w: ti.f32, inv: ti.f32, ms: ti.i32, v: ti.template()):  # fmt: skip
    """ROUNDS rounds of min-label hooking and pointer jumping with plain stores (no atomics: see
    the module); flag[0] = 1 when the last round changed a parent."""
    dim = ti.static(v.dim)
    mask = H - 1
    for _r in ti.static(range(ROUNDS)):
        for _ in range(1):
            flag[0] = 0
        for s in range(n):  # hook: the parent of i takes the smallest parent among i's core neighbours
            if s < start[H]:
                i = order[s]
                if core[i] != 0:
                    p = _point(spts, s, dim)
                    m = _scan(i, p, 3, dim, order, spts, start, core, parent, out, r2, w, inv, ms, mask)
                    t = parent[i]
                    if m < parent[t]:
                        parent[t] = m
                        flag[0] = 1
        for i in range(n):  # pointer jumping
            if core[i] != 0:
                t = parent[parent[i]]
                if t != parent[i]:
                    parent[i] = t
                    flag[0] = 1


def _scratch(device, N, dim):
    H = buckets(N)
    return (
        scratch(device, "clu_cnt", (H,), ti.i32),
        scratch(device, "clu_start", (H + 1,), ti.i32),
        scratch(device, "clu_csum", (H // CHUNK,), ti.i32),
        scratch(device, "clu_key", (N,), ti.i32),
        scratch(device, "clu_rank", (N,), ti.i32),
        scratch(device, "clu_order", (N,), ti.i32),
        scratch(device, "clu_spts", (N, dim), ti.f32),
        scratch(device, "clu_parent", (N,), ti.i32),
        scratch(device, "clu_core", (N,), ti.i32),
        scratch(device, "clu_loose", (H,), ti.i32),
        scratch(device, "clu_head", (N,), ti.i32),
        scratch(device, "clu_box", (N, 6), ti.f32),
    )


def _run(device, points, n, r2, ms, out):
    N, dim = points.shape
    w, inv = grid(r2, dim)
    arch = current_arch()
    atomic = arch in ATOMIC_ARCHS
    v = _Variant(dim, arch == "cpu" and n <= SERIAL_POINTS, atomic)  # one thread only on a CPU
    cnt, start, csum, key, rank, order, spts, parent, core, loose, head, box = _scratch(device, N, dim)
    H = buckets(N)
    arrays = (points.buffer, out.buffer, cnt, start, csum, key, rank, order, spts, parent, core, loose, head, box)
    launch(_clusters, arrays, (v,), scalars=(int(n), int(N), H, H // CHUNK, float(r2), float(w), float(inv), int(ms)))
    if atomic:
        return out
    flag = scratch(device, "clu_flag", (1,), ti.i32)
    rest = (out.buffer, start, order, spts, parent, core)
    for _ in range(MAX_LAUNCHES):
        launch(_rounds, (*rest, flag), (v,), scalars=(int(n), H, float(r2), float(w), float(inv), int(ms)))
        if int(flag.to_numpy()[0]) == 0:
            break
    else:  # pragma: no cover - the rounds converge long before
        raise RuntimeError(f"clusters: label propagation did not converge in {MAX_LAUNCHES * ROUNDS} rounds")
    launch(_finish, rest, (v,), scalars=(int(n), int(N), H, float(r2), float(w), float(inv), int(ms)))
    return out


def radius_components(device, points, n, r2, out):
    return _run(device, points, n, r2, 1, out)  # dbscan with min_samples = 1


def dbscan(device, points, n, r2, min_samples, out):
    return _run(device, points, n, r2, min_samples, out)
