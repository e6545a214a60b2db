// Clusters of points (gputrack/ops/clusters.py): radius_components (paper 001 eq. 12) and DBSCAN
// (paper 002 sec. 4.2). A hashed uniform grid of cell side r (1 - slack) / sqrt(DIM) (any two
// points of a cell are neighbours) built by a counting sort; neighbours are searched in the box
// p +- w, w = r (1 + slack); a union-find by atomic min links the core points of a cell to its
// head (its first core point), then pairs of cells. The launcher
// (gputrack/backends/opencl/clusters.py) enqueues, in order: gt_clu_bin, gt_clu_chunk_sums,
// gt_clu_scan_chunks, gt_clu_chunk_scan, gt_clu_place, [gt_clu_count], gt_clu_link_cell,
// gt_clu_box, gt_clu_link_cells, gt_clu_label, [gt_clu_border]. Points (N, DIM) float32; a row with a NaN
// is not a point. Defines: DIM (2 or 3), CHUNK (buckets per scan chunk).

#pragma OPENCL FP_CONTRACT OFF  // d2 rounds as the reference: (d0 d0 + d1 d1) + d2 d2, no fused multiply-add

// Defaults (a build without the launcher's defines, as host/doctor.py does): 3D points.
#ifndef DIM
#define DIM 3
#endif
#ifndef CHUNK
#define CHUNK 256
#endif

#define GT_CLAMP 1073741824.0f  // cell coordinates clamped to +-2^30 before the cast (monotone)
#define GT_NONE 2147483647
#define GT_GAP_SLACK 1.01f  // cells whose boxes are farther apart than r (with this margin) cannot link

inline int gt_cell(float x, float inv)
{
    return (int)clamp(floor(x * inv), -GT_CLAMP, GT_CLAMP);
}

inline int gt_hash(int cx, int cy, int cz, int mask)
{
    uint h = ((uint)cx * 73856093u) ^ ((uint)cy * 19349663u) ^ ((uint)cz * 83492791u);
    return (int)(h & (uint)mask);
}

inline int gt_is_nan_row(__global const float *p)
{
    int bad = 0;
    for (int k = 0; k < DIM; k++)
        bad |= isnan(p[k]);
    return bad;
}

// Root of x, halving the path with atomic mins (a parent only ever decreases).
inline int gt_find(volatile __global int *parent, int x)
{
    int root = x, p = parent[root];
    while (p != root) {
        const int gp = parent[p];
        if (gp < p)
            atomic_min(&parent[root], gp);
        root = p;
        p = parent[root];
    }
    return root;
}

// Hook the larger root under the smaller; retry where another edge hooked it first.
inline void gt_union(volatile __global int *parent, int a, int b)
{
    for (;;) {
        a = gt_find(parent, a);
        b = gt_find(parent, b);
        if (a == b)
            return;
        const int hi = max(a, b), lo = min(a, b);
        const int old = atomic_min(&parent[hi], lo);
        if (old == hi)
            return;
        a = old;  // hi was hooked under old meanwhile: join old and lo
        b = lo;
    }
}

// 1: bin the points: parent, core flag, bucket and rank in the bucket (counts zeroed before).
__kernel void gt_clu_bin(__global const float *pts, __global int *cnt, __global int *key, __global int *rank,
                         __global int *parent, __global int *core, const int n, const int mask, const float inv)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    __global const float *p = pts + (size_t)i * DIM;
    parent[i] = i;
    if (gt_is_nan_row(p)) {  // not a point
        key[i] = -1;
        core[i] = 0;
        return;
    }
    int c[3] = {0, 0, 0};
    for (int k = 0; k < DIM; k++)
        c[k] = gt_cell(p[k], inv);
    const int b = gt_hash(c[0], c[1], c[2], mask);
    key[i] = b;
    rank[i] = atomic_inc(&cnt[b]);
    core[i] = 1;
}

// 2: exclusive scan of the bucket counts: chunk sums, a scan of the chunks (one work-item),
// chunk scans; start has H + 1 entries.
__kernel void gt_clu_chunk_sums(__global const int *cnt, __global int *csum)
{
    const int c = get_global_id(0);
    int s = 0;
    for (int k = c * CHUNK; k < (c + 1) * CHUNK; k++)
        s += cnt[k];
    csum[c] = s;
}

__kernel void gt_clu_scan_chunks(__global int *csum, __global int *start, const int chunks, const int H)
{
    int run = 0;
    for (int c = 0; c < chunks; c++) {
        const int s = csum[c];
        csum[c] = run;
        run += s;
    }
    start[H] = run;
}

__kernel void gt_clu_chunk_scan(__global const int *cnt, __global const int *csum, __global int *start)
{
    const int c = get_global_id(0);
    int run = csum[c];
    for (int k = c * CHUNK; k < (c + 1) * CHUNK; k++) {
        start[k] = run;
        run += cnt[k];
    }
}

// 3: scatter into bucket order (indices and a copy of the coordinates).
__kernel void gt_clu_place(__global const float *pts, __global const int *key, __global const int *rank,
                           __global const int *start, __global int *order, __global float *spts, const int n)
{
    const int i = get_global_id(0);
    if (i >= n || key[i] < 0)
        return;
    const int s = start[key[i]] + rank[i];
    order[s] = i;
    for (int k = 0; k < DIM; k++)
        spts[(size_t)s * DIM + k] = pts[(size_t)i * DIM + k];
}

inline int gt_same_cell(__global const float *q, int cx, int cy, int cz, float inv)
{
#if DIM == 3
    return gt_cell(q[0], inv) == cx && gt_cell(q[1], inv) == cy && gt_cell(q[2], inv) == cz;
#else
    return gt_cell(q[0], inv) == cx && gt_cell(q[1], inv) == cy;
#endif
}

inline float gt_d2(const float *p, __global const float *q)
{
    const float d0 = p[0] - q[0], d1 = p[1] - q[1];
    float d2 = d0 * d0 + d1 * d1;
    if (DIM == 3) {
        const float dz = p[2] - q[2];
        d2 = d2 + dz * dz;
    }
    return d2;
}

// The neighbours j of the point in slot s (coordinates p, cell own): MODE 0 counts them, its own
// cell first, stopping at ms; MODE 2 returns the smallest label of the core neighbours (GT_NONE if
// none).
#define GT_SCAN(MODE)                                                                                        \
    {                                                                                                        \
        int lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};                                                            \
        for (int k = 0; k < DIM; k++) {                                                                      \
            lo[k] = gt_cell(p[k] - w, inv);                                                                  \
            hi[k] = gt_cell(p[k] + w, inv);                                                                  \
        }                                                                                                    \
        if (MODE == 0) {                                                                                     \
            const int b = gt_hash(own[0], own[1], own[2], mask);                                             \
            for (int t = start[b]; t < start[b + 1]; t++)                                                    \
                if (gt_same_cell(spts + (size_t)t * DIM, own[0], own[1], own[2], inv) &&                     \
                    gt_d2(p, spts + (size_t)t * DIM) <= r2)                                                  \
                    acc++;                                                                                   \
            stop = acc >= ms;                                                                                \
        }                                                                                                    \
        for (int cx = lo[0]; cx <= hi[0] && !stop; cx++)                                                     \
            for (int cy = lo[1]; cy <= hi[1] && !stop; cy++)                                                 \
                for (int cz = lo[2]; cz <= hi[2] && !stop; cz++) {                                           \
                    if (MODE == 0 && cx == own[0] && cy == own[1] && cz == own[2])                           \
                        continue; /* counted above */                                                        \
                    const int b = gt_hash(cx, cy, cz, mask);                                                 \
                    for (int t = start[b]; t < start[b + 1]; t++) {                                          \
                        __global const float *q = spts + (size_t)t * DIM;                                    \
                        if (!gt_same_cell(q, cx, cy, cz, inv) || !(gt_d2(p, q) <= r2))                       \
                            continue;                                                                        \
                        const int j = order[t];                                                              \
                        if (MODE == 0)                                                                       \
                            acc++;                                                                           \
                        else if (core[j])                                                                    \
                            acc = min(acc, out[j]);                                                          \
                    }                                                                                        \
                    if (MODE == 0)                                                                           \
                        stop = acc >= ms;                                                                    \
                }                                                                                            \
    }

inline void gt_load(__global const float *spts, int s, float *p, int *own, float inv)
{
    for (int k = 0; k < 3; k++) {
        p[k] = k < DIM ? spts[(size_t)s * DIM + k] : 0.0f;
        own[k] = k < DIM ? gt_cell(p[k], inv) : 0;
    }
}

// The slot of the first core point of cell c in bucket b, or -1.
inline int gt_first_core(int cx, int cy, int cz, int b, __global const float *spts, __global const int *order,
                         __global const int *start, __global const int *core, float inv)
{
    for (int t = start[b]; t < start[b + 1]; t++)
        if (core[order[t]] && gt_same_cell(spts + (size_t)t * DIM, cx, cy, cz, inv))
            return t;
    return -1;
}

// 4 (dbscan): core points have at least ms neighbours, the point itself included.
__kernel void gt_clu_count(__global const float *spts, __global const int *order, __global const int *start,
                           __global int *core, const int mask, const float r2, const float w, const float inv,
                           const int ms, const int H)
{
    const int s = get_global_id(0);
    if (s >= start[H])
        return;
    const int i = order[s];
    int acc = 0, stop = 0, own[3];
    float p[3];
    gt_load(spts, s, p, own, inv);
    __global const int *out = 0;
    GT_SCAN(0)
    if (acc < ms)
        core[i] = 0;
}

// 5a: each core point joins the head of its cell (its first core point: any two points of a cell
// are neighbours); a pair failing the distance test (rounding at huge coordinates) marks the bucket
// loose, whose cells are then linked pair by pair in 5b.
__kernel void gt_clu_link_cell(__global const float *spts, __global const int *order, __global const int *start,
                               __global const int *core, volatile __global int *parent, __global int *loose,
                               __global int *heads, const int mask, const float r2, const float inv, const int H,
                               const int n)
{
    const int s = get_global_id(0);
    if (s >= start[H])
        return;
    const int i = order[s];
    if (!core[i])
        return;
    int own[3];
    float p[3];
    gt_load(spts, s, p, own, inv);
    const int b = gt_hash(own[0], own[1], own[2], mask);
    const int t = gt_first_core(own[0], own[1], own[2], b, spts, order, start, core, inv);
    if (t == s) {  // a head: appended to the list (heads[n] counts them) that 5b and 5c work through
        heads[atomic_inc(&heads[n])] = s;
        return;
    }
    if (gt_d2(p, spts + (size_t)t * DIM) <= r2)
        gt_union(parent, i, order[t]);
    else
        loose[b] = 1;
}

// 5b: the bounding box of each cell's core points, box[head slot] = (lo, hi) (one work-item per head).
__kernel void gt_clu_box(__global const float *spts, __global const int *order, __global const int *start,
                         __global const int *core, __global const int *heads, __global float *box, const int mask,
                         const float inv, const int n)
{
    const int k = get_global_id(0);
    if (k >= heads[n])
        return;
    const int s = heads[k];
    int c[3];
    float p[3];
    gt_load(spts, s, p, c, inv);
    const int b = gt_hash(c[0], c[1], c[2], mask);
    float lo[3] = {p[0], p[1], p[2]}, hi[3] = {p[0], p[1], p[2]};
    for (int t = s; t < start[b + 1]; t++) {
        __global const float *q = spts + (size_t)t * DIM;
        if (core[order[t]] && gt_same_cell(q, c[0], c[1], c[2], inv))
            for (int d = 0; d < DIM; d++) {
                lo[d] = min(lo[d], q[d]);
                hi[d] = max(hi[d], q[d]);
            }
    }
    for (int d = 0; d < 3; d++) {
        box[(size_t)s * 6 + d] = lo[d];
        box[(size_t)s * 6 + 3 + d] = hi[d];
    }
}

// 5c (NDRange n, as 5a): cell A (head slot s = heads[k]) with each cell B that can hold a neighbour
// of one of its core points:
// unless connected already, the first pair of their core points within r is united (every pair
// where a bucket is loose). Each pair of cells is handled from the smaller head slot.
__kernel void gt_clu_link_cells(__global const float *spts, __global const int *order, __global const int *start,
                                __global const int *core, volatile __global int *parent, __global const int *loose,
                                __global const int *heads, __global const float *box, const int mask,
                                const float r2, const float w, const float inv, const int H, const int n)
{
    const int k = get_global_id(0);
    if (k >= heads[n])  // one work-item per head
        return;
    const int s = heads[k];
    int cA[3];
    float pa[3];
    gt_load(spts, s, pa, cA, inv);
    const int bA = gt_hash(cA[0], cA[1], cA[2], mask), endA = start[bA + 1];
    const int tightA = !loose[bA];
    float lo[3] = {0.0f, 0.0f, 0.0f}, hi[3] = {0.0f, 0.0f, 0.0f};  // bounding box of A's core points
    for (int k = 0; k < DIM; k++) {
        lo[k] = box[(size_t)s * 6 + k];
        hi[k] = box[(size_t)s * 6 + 3 + k];
    }
    int clo[3] = {0, 0, 0}, chi[3] = {0, 0, 0};
    for (int k = 0; k < DIM; k++) {
        clo[k] = gt_cell(lo[k] - w, inv);
        chi[k] = gt_cell(hi[k] + w, inv);
    }
    const int i = order[s];
    for (int cx = clo[0]; cx <= chi[0]; cx++)
        for (int cy = clo[1]; cy <= chi[1]; cy++)
            for (int cz = clo[2]; cz <= chi[2]; cz++) {
                const int bB = gt_hash(cx, cy, cz, mask);
                const int tB = gt_first_core(cx, cy, cz, bB, spts, order, start, core, inv);
                const int tight = tightA && !loose[bB];
                if (tB < 0 || tB < s || (tB == s && tight))
                    continue;
                float gap2 = 0.0f;  // squared gap between the boxes of A and B: beyond r, no pair links
                for (int k = 0; k < DIM; k++) {
                    const float below = box[(size_t)tB * 6 + k] - hi[k], above = lo[k] - box[(size_t)tB * 6 + 3 + k];
                    const float g = max(max(below, above), 0.0f);
                    gap2 += g * g;
                }
                if (gap2 > r2 * GT_GAP_SLACK)
                    continue;
                if (tight && gt_find(parent, i) == gt_find(parent, order[tB]))
                    continue;
                const int endB = start[bB + 1];
                int done = 0;
                for (int ta = s; ta < endA && !done; ta++) {
                    const int a = order[ta];
                    if (!core[a] || !gt_same_cell(spts + (size_t)ta * DIM, cA[0], cA[1], cA[2], inv))
                        continue;
                    float qa[3];
                    for (int k = 0; k < 3; k++)
                        qa[k] = k < DIM ? spts[(size_t)ta * DIM + k] : 0.0f;
                    for (int tb = tB; tb < endB && !done; tb++) {
                        const int bp = order[tb];
                        __global const float *qb = spts + (size_t)tb * DIM;
                        if (core[bp] && gt_same_cell(qb, cx, cy, cz, inv) && gt_d2(qa, qb) <= r2) {
                            gt_union(parent, a, bp);  // paper 001 eq. 12: linked points
                            done = tight;
                        }
                    }
                }
            }
}

// 6: labels: the root of each core point (its component's smallest index), -1 for the rest.
__kernel void gt_clu_label(volatile __global int *parent, __global const int *core, __global int *out, const int n,
                           const int N)
{
    const int i = get_global_id(0);
    if (i >= N)
        return;
    out[i] = (i < n && core[i]) ? gt_find(parent, i) : -1;
}

// 7 (dbscan): a border point takes the smallest label among its core neighbours.
__kernel void gt_clu_border(__global const float *spts, __global const int *order, __global const int *start,
                            __global const int *core, __global int *out, const int mask, const float r2, const float w,
                            const float inv, const int H)
{
    const int s = get_global_id(0);
    if (s >= start[H])
        return;
    const int i = order[s];
    if (core[i])
        return;
    int acc = GT_NONE, stop = 0, ms = 0, own[3];
    float p[3];
    gt_load(spts, s, p, own, inv);
    GT_SCAN(2)
    if (acc < GT_NONE)
        out[i] = acc;
}
