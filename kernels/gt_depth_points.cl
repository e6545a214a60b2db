// Foreground points of a depth image, randomly downsampled (gputrack/ops/depth_points.py; paper 002
// sec. 4.1). Five kernels, launched in order on one queue:
//   gt_dp_keys    NDRange (H W): a byte per pixel, bit q set where its key is below level q's
//                 bound, of GT_LEVELS bounds 2^(31 - GT_STEP q) (q = 0: every foreground key);
//   gt_dp_count   NDRange (chunks, H): per chunk of GT_CHUNK pixels of a row, the count of keys
//                 below each bound;
//   gt_dp_plan    one work-item: N, the tightest bound holding min(n, N) keys, chunk offsets;
//   gt_dp_compact NDRange (chunks, H): (key, pixel) of each candidate at its chunk's offset (row
//                 order; the key hashed again), reading only the chunks that hold one;
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

// the key of pixel i = r W + c; foreground: a reading within range, >= threshold off a background value
inline uint gt_dp_key(__global const GT_PIXEL *depth, __global const float *bg, const int i, const uint a,
                      const uint b, const float threshold, const float max_range, const int nearer)
{
    const float z = (float)depth[i], g = bg[i];
    // g == g: not NaN (the programs are built without fast-math options); nearer: g - z >= threshold,
    // i.e. |z - g| >= threshold and g >= z (threshold >= 0), without a select on `nearer`
    const int fg = z > 0.0f && z <= max_range && g == g && g != 0.0f && fabs(z - g) >= threshold && (!nearer || g >= z);
    const uint key = gt_dp_pcg(gt_dp_pcg((uint)i ^ a) + b) >> 1u;
    return fg ? key : (key | 0x80000000u);
}

// NDRange (H W): one byte per pixel, bit q set where its key is below level q's bound (a
// work-item per pixel: PoCL vectorises it across work-items; the keys themselves are not stored:
// a byte is a quarter of the memory traffic of a key, and gt_dp_compact hashes the few candidates
// again)
__kernel void gt_dp_keys(__global const GT_PIXEL *depth, __global const float *bg, const int H, const int W,
                         const uint a, const uint b, const float threshold, const float max_range, const int nearer,
                         __global uchar *below)
{
    const int i = get_global_id(0);  // launched with exactly H W work-items (a bounds test here
    // costs PoCL's vectoriser a third of the kernel's time)
    const uint key = gt_dp_key(depth, bg, i, a, b, threshold, max_range, nearer);
    // signed compares, written out for GT_LEVELS = 4: PoCL vectorises an unsigned compare (AVX2 has
    // none) or the loop form badly (1280 x 960 on one core: 3x the time of the hash)
    const int sk = (int)key;  // foreground keys are >= 0 as ints, the others < 0
    const uint bits = sk < 0 ? 0u
                             : 1u | ((uint)(sk < (1 << (31 - GT_STEP))) << 1) | ((uint)(sk < (1 << (31 - 2 * GT_STEP))) << 2) |
                                   ((uint)(sk < (1 << (31 - 3 * GT_STEP))) << 3);
    below[i] = (uchar)bits;
}

// NDRange (chunks, H), chunks = ceil(W / GT_CHUNK): hist[(r chunks + ch) GT_LEVELS + q] = the count
// of the keys of pixels [ch GT_CHUNK, (ch + 1) GT_CHUNK) of row r below level q's bound (bit q of
// each pixel's byte spread to byte q of a word, summed: <= 32 per byte)
__kernel void gt_dp_count(__global const uchar *below, const int H, const int W, __global int *hist)
{
    const int ch = get_global_id(0), r = get_global_id(1), chunks = (W + GT_CHUNK - 1) / GT_CHUNK;
    if (ch >= chunks || r >= H)
        return;
    const int c0 = ch * GT_CHUNK, c1 = min(W, c0 + GT_CHUNK);
    __global const uchar *p = below + (size_t)r * W + c0;
    uint sum = 0;
    for (int c = 0; c < c1 - c0; ++c) {
        const uint v = p[c];
        sum += (v & 1u) | ((v & 2u) << 7) | ((v & 4u) << 14) | ((v & 8u) << 21);
    }
    const int at = r * chunks + ch;
    for (int q = 0; q < GT_LEVELS; ++q)
        hist[at * GT_LEVELS + q] = (sum >> (8 * q)) & 0xffu;
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

// NDRange (chunks, H): the candidates (key below the level's bound) of a chunk at its offset, in
// order, their keys hashed again; chunks without one return at once
__kernel void gt_dp_compact(__global const uchar *below, const int H, const int W, const uint a, const uint b,
                            __global const int *hist, __global const int *offs, __global const int *info,
                            __global uint *ck, __global int *ci)
{
    const int ch = get_global_id(0), r = get_global_id(1), chunks = (W + GT_CHUNK - 1) / GT_CHUNK;
    if (ch >= chunks || r >= H)
        return;
    const int g = r * chunks + ch, k = info[2];
    if (hist[g * GT_LEVELS + k] == 0)
        return;
    int j = offs[g];
    const int c1 = min(W, (ch + 1) * GT_CHUNK);
    for (int c = ch * GT_CHUNK; c < c1; ++c) {
        const int i = r * W + c;
        if ((below[i] >> k) & 1) {  // a foreground key below the bound
            ck[j] = gt_dp_pcg(gt_dp_pcg((uint)i ^ a) + b) >> 1u;
            ci[j] = i;
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
