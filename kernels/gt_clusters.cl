// Clusters of points (gputrack/ops/clusters.py): radius_components (paper 001 eq. 12) and DBSCAN
// (paper 002 sec. 4.2). A hashed uniform grid of cell size w = r (1 + slack) built by a counting
// sort, then a union-find by atomic min over the edges between core points. The launcher
// (gputrack/backends/opencl/clusters.py) enqueues, in order: gt_clu_bin, gt_clu_chunk_sums,
// gt_clu_scan_chunks, gt_clu_chunk_scan, gt_clu_place, [gt_clu_count], gt_clu_union,
// gt_clu_label, [gt_clu_border]. Points (N, DIM) float32; a row with a NaN is not a point.
// Defines: DIM (2 or 3), CHUNK (buckets per scan chunk).

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

// The neighbours j of the point in slot s: MODE 0 counts them (stopping at ms), 1 unions i with
// each core neighbour j < i, 2 returns the smallest label of the core neighbours (GT_NONE if none).
#define GT_SCAN(MODE)                                                                                        \
    {                                                                                                        \
        float p[3] = {0.0f, 0.0f, 0.0f};                                                                     \
        int lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};                                                            \
        for (int k = 0; k < DIM; k++) {                                                                      \
            p[k] = spts[(size_t)s * DIM + k];                                                                \
            lo[k] = gt_cell(p[k] - w, inv);                                                                  \
            hi[k] = gt_cell(p[k] + w, inv);                                                                  \
        }                                                                                                    \
        for (int cx = lo[0]; cx <= hi[0] && !stop; cx++)                                                     \
            for (int cy = lo[1]; cy <= hi[1] && !stop; cy++)                                                 \
                for (int cz = lo[2]; cz <= hi[2] && !stop; cz++) {                                           \
                    const int b = gt_hash(cx, cy, cz, mask);                                                 \
                    for (int t = start[b]; t < start[b + 1]; t++) {                                          \
                        __global const float *q = spts + (size_t)t * DIM;                                    \
                        int same = gt_cell(q[0], inv) == cx && gt_cell(q[1], inv) == cy;                     \
                        const float d0 = p[0] - q[0], d1 = p[1] - q[1];                                      \
                        float d2 = d0 * d0 + d1 * d1;                                                        \
                        if (DIM == 3) {                                                                      \
                            same = same && gt_cell(q[2], inv) == cz;                                         \
                            const float dz = p[2] - q[2];                                                    \
                            d2 = d2 + dz * dz;                                                               \
                        }                                                                                    \
                        if (!same || !(d2 <= r2))                                                            \
                            continue;                                                                        \
                        const int j = order[t];                                                              \
                        if (MODE == 0)                                                                       \
                            acc++;                                                                           \
                        else if (MODE == 1) {                                                                \
                            if (j < i && core[j])                                                            \
                                gt_union(parent, i, j);                                                      \
                        } else if (core[j])                                                                  \
                            acc = min(acc, out[j]);                                                          \
                    }                                                                                        \
                    if (MODE == 0)                                                                           \
                        stop = acc >= ms;                                                                    \
                }                                                                                            \
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
    int acc = 0, stop = 0;
    volatile __global int *parent = 0;
    __global const int *out = 0;
    GT_SCAN(0)
    if (acc < ms)
        core[i] = 0;
}

// 5: union-find over the edges between core points, each from its larger index.
__kernel void gt_clu_union(__global const float *spts, __global const int *order, __global const int *start,
                           __global const int *core, volatile __global int *parent, const int mask, const float r2,
                           const float w, const float inv, const int H)
{
    const int s = get_global_id(0);
    if (s >= start[H])
        return;
    const int i = order[s];
    if (!core[i])
        return;
    int acc = 0, stop = 0, ms = 0;
    __global const int *out = 0;
    GT_SCAN(1)
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
    int acc = GT_NONE, stop = 0, ms = 0;
    volatile __global int *parent = 0;
    GT_SCAN(2)
    if (acc < GT_NONE)
        out[i] = acc;
}
