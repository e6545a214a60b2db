// Foreground points of a depth image, randomly downsampled (gputrack/ops/depth_points.py; paper 002
// sec. 4.1). Four kernels, launched in order on one queue:
//   gt_dp_count   one work-group per chunk of GT_CHUNK pixels of a row: the count of foreground keys
//                 below each of GT_LEVELS bounds 2^(31 - GT_STEP q) (q = 0: every foreground key)
//                 and the smallest key;
//   gt_dp_plan    one work-item: N, the tightest bound holding min(n, N) keys, chunk offsets;
//   gt_dp_compact NDRange (chunks, H): (key, pixel) of each candidate at its chunk's offset (row
//                 order), rescanning only the chunks that hold one;
//   gt_dp_select  one work-item: stable LSD radix sort of the candidates by key, the first
//                 min(n, C) points back-projected, NaN rows after them.
// A pixel's key: pcg(pcg(i ^ a) + b) >> 1 (i = r W + c) if it is foreground, else >= 2^31.
// GT_PIXEL: the depth image's type (float, uchar or ushort; the launcher defines it).

#ifndef GT_PIXEL
#define GT_PIXEL float
#endif
#define GT_LEVELS 4
#define GT_STEP 3
#define GT_CHUNK 32
#define GT_RADIX 256

inline uint gt_dp_pcg(const uint x)
{
    const uint state = x * 747796405u + 2891336453u;
    const uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// the key of pixel (r, c); foreground: a reading within range, >= threshold off a background value
inline uint gt_dp_key(__global const GT_PIXEL *depth, __global const float *bg, const int r, const int c, const int W,
                      const uint a, const uint b, const float threshold, const float max_range, const int nearer)
{
    const int i = r * W + c;
    const float z = (float)depth[i], g = bg[i];
    const float d = nearer ? g - z : fabs(z - g);
    const int g_nan = (as_uint(g) & 0x7fffffffu) > 0x7f800000u;
    const int fg = z > 0.0f && z <= max_range && !g_nan && g != 0.0f && d >= threshold;
    const uint key = gt_dp_pcg(gt_dp_pcg((uint)i ^ a) + b) >> 1u;
    return fg ? key : (key | 0x80000000u);
}

// NDRange (chunks GT_CHUNK, H), work-groups (GT_CHUNK, 1): work-group (ch, r) takes pixels
// [ch GT_CHUNK, (ch + 1) GT_CHUNK) of row r, one a work-item (the keys vectorise across
// work-items), and its first work-item writes hist[(r chunks + ch) GT_LEVELS + q] = the count of the
// keys below level q's bound and low[r chunks + ch] = the smallest key
__kernel __attribute__((reqd_work_group_size(GT_CHUNK, 1, 1)))
void gt_dp_count(__global const GT_PIXEL *depth, __global const float *bg, const int H, const int W, const uint a,
                 const uint b, const float threshold, const float max_range, const int nearer, __global int *hist,
                 __global uint *low)
{
    __local uint keys[GT_CHUNK];
    const int c = get_global_id(0), r = get_global_id(1), e = get_local_id(0);
    const int chunks = (W + GT_CHUNK - 1) / GT_CHUNK, ch = get_group_id(0);
    keys[e] = (c < W && r < H) ? gt_dp_key(depth, bg, r, c, W, a, b, threshold, max_range, nearer) : 0xffffffffu;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (e != 0 || r >= H)
        return;
    int h[GT_LEVELS];
    for (int q = 0; q < GT_LEVELS; ++q)
        h[q] = 0;
    uint lo = 0xffffffffu;
    for (int k = 0; k < GT_CHUNK; ++k) {
        const uint key = keys[k];
        lo = min(lo, key);
        for (int q = 0; q < GT_LEVELS; ++q)
            h[q] += key < (1u << (31 - GT_STEP * q));
    }
    const int at = r * chunks + ch;
    for (int q = 0; q < GT_LEVELS; ++q)
        hist[at * GT_LEVELS + q] = h[q];
    low[at] = lo;
}

// offs[g]: the first candidate of chunk g (g = r chunks + ch), offs[G] = C; info: [N, C, level]
__kernel void gt_dp_plan(__global const int *hist, const int G, const int n, __global int *offs, __global int *info)
{
    if (get_global_id(0) != 0)
        return;
    int tot[GT_LEVELS];
    for (int q = 0; q < GT_LEVELS; ++q)
        tot[q] = 0;
    for (int g = 0; g < G; ++g)
        for (int q = 0; q < GT_LEVELS; ++q)
            tot[q] += hist[g * GT_LEVELS + q];
    const int N = tot[0], need = min(n, N);
    int k = 0;
    for (int q = 1; q < GT_LEVELS; ++q)  // the tightest bound with at least `need` keys below it
        if (tot[q] >= need)
            k = q;
    int run = 0;
    for (int g = 0; g < G; ++g) {
        offs[g] = run;
        run += hist[g * GT_LEVELS + k];
    }
    offs[G] = run;
    info[0] = N;
    info[1] = run;
    info[2] = k;
}

// NDRange (chunks, H): the candidates (key below the level's bound) of a chunk at its offset
__kernel void gt_dp_compact(__global const GT_PIXEL *depth, __global const float *bg, const int H, const int W,
                            const uint a, const uint b, const float threshold, const float max_range, const int nearer,
                            __global const uint *low, __global const int *offs, __global const int *info,
                            __global uint *ck, __global int *ci)
{
    const int ch = get_global_id(0), r = get_global_id(1), chunks = (W + GT_CHUNK - 1) / GT_CHUNK;
    if (ch >= chunks || r >= H)
        return;
    const int g = r * chunks + ch;
    const uint t = 1u << (31 - GT_STEP * info[2]);
    if (low[g] >= t)
        return;
    int j = offs[g];
    const int c1 = min(W, (ch + 1) * GT_CHUNK);
    for (int c = ch * GT_CHUNK; c < c1; ++c) {
        const uint key = gt_dp_key(depth, bg, r, c, W, a, b, threshold, max_range, nearer);
        if (key < t) {
            ck[j] = key;
            ci[j] = r * W + c;
            ++j;
        }
    }
}

// stable counting sort of C (key, index) pairs by the 8 bits of key at `shift`
inline void gt_dp_radix(__global const uint *sk, __global const int *si, __global uint *dk, __global int *di,
                        __global int *cnt, const int C, const int shift)
{
    for (int q = 0; q < GT_RADIX; ++q)
        cnt[q] = 0;
    for (int j = 0; j < C; ++j)
        ++cnt[(sk[j] >> shift) & (GT_RADIX - 1)];
    int run = 0;
    for (int q = 0; q < GT_RADIX; ++q) {
        const int t = cnt[q];
        cnt[q] = run;
        run += t;
    }
    for (int j = 0; j < C; ++j) {
        const int p = cnt[(sk[j] >> shift) & (GT_RADIX - 1)]++;
        dk[p] = sk[j];
        di[p] = si[j];
    }
}

__kernel void gt_dp_select(__global const GT_PIXEL *depth, const int W, __global const int *info, __global uint *k0,
                           __global int *i0, __global uint *k1, __global int *i1, __global int *cnt, const int n,
                           const float fx, const float fy, const float cx, const float cy, __global float *out)
{
    if (get_global_id(0) != 0)
        return;
    const int C = info[1];
    const int passes = (31 - GT_STEP * info[2] + 7) / 8;
    for (int p = 0; p < passes; ++p) {
        if (p % 2 == 0)
            gt_dp_radix(k0, i0, k1, i1, cnt, C, 8 * p);
        else
            gt_dp_radix(k1, i1, k0, i0, cnt, C, 8 * p);
    }
    __global const int *idx = passes % 2 ? i1 : i0;
    const int m = min(n, C);
    const float nan = as_float(0x7fc00000u);
    for (int j = 0; j < n; ++j) {
        float x = nan, y = nan, z = nan;
        if (j < m) {
            const int i = idx[j], r = i / W, c = i - r * W;
            z = (float)depth[i];
            x = ((float)c - cx) * z / fx;  // pinhole back-projection
            y = ((float)r - cy) * z / fy;
        }
        out[3 * j] = x;
        out[3 * j + 1] = y;
        out[3 * j + 2] = z;
    }
}
