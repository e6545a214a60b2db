// Per-pixel background model (gputrack/ops/background.py; paper 001 subtraction stereo, paper 002
// sec. 4.1): median of F frames, running average, foreground mask. One work-item per pixel. Images are GT_PIXEL (float, uchar or ushort; the launcher defines it), read as
// float; a sample is valid when it is not NaN and, with use_missing, not equal to `missing`.
// GT_MAX_FRAMES: the median's private array (the launcher rounds F up to a power of two).

#ifndef GT_PIXEL
#define GT_PIXEL float
#endif
#ifndef GT_MAX_FRAMES
#define GT_MAX_FRAMES 64
#endif

// NaN by its bits (immune to fast math)
inline int gt_bg_nan(const float x) { return (as_uint(x) & 0x7fffffffu) > 0x7f800000u; }

inline int gt_bg_valid(const float x, const int use_missing, const float missing)
{
    return !gt_bg_nan(x) && (!use_missing || x != missing);
}

__kernel void gt_background_median(__global const GT_PIXEL *frames, const int F, const int H, const int W,
                                   const int use_missing, const float missing, __global float *out)
{
    const int c = get_global_id(0), r = get_global_id(1);
    if (c >= W || r >= H)
        return;
    float v[GT_MAX_FRAMES];
    int n = 0;
    const size_t plane = (size_t)H * W, at = (size_t)r * W + c;
    for (int f = 0; f < F && f < GT_MAX_FRAMES; ++f) {
        const float x = (float)frames[f * plane + at];
        if (!gt_bg_valid(x, use_missing, missing))  // dropouts are ignored (paper 002 sec. 4.1)
            continue;
        int j = n;
        while (j > 0 && v[j - 1] > x) {
            v[j] = v[j - 1];
            --j;
        }
        v[j] = x;
        ++n;
    }
    float m = as_float(0x7fc00000u);  // NaN: no valid sample
    if (n > 0) {
        const int h = n / 2;
        m = (n % 2) ? v[h] : (v[h - 1] + v[h]) * 0.5f;  // even count: the mean of the two middle samples
    }
    out[at] = m;
}

// NDRange (H W), exactly: no bounds test (it costs PoCL's vectoriser a third of such a kernel).
// bg = (1 - rate) bg + rate frame where mask (if has_mask) is 0 and the frame valid; an invalid
// or infinite background takes the frame's value. out may be bg.
__kernel void gt_update_background(__global const float *bg, __global const GT_PIXEL *frame,
                                   __global const uchar *mask, const int has_mask, const float rate,
                                   const int use_missing, const float missing, __global float *out)
{
    const int at = get_global_id(0);
    float b = bg[at];
    const float x = (float)frame[at];
    if (gt_bg_valid(x, use_missing, missing) && !(has_mask && mask[at]))
        b = gt_bg_valid(b, use_missing, missing) && (as_uint(b) & 0x7f800000u) != 0x7f800000u
                ? (1.0f - rate) * b + rate * x  // running average
                : x;                            // no (finite) background yet
    out[at] = b;
}

// NDRange (H W), exactly. 1 where frame and bg are valid and |frame - bg| >= threshold (nearer:
// bg - frame >= threshold, i.e. also bg >= frame, threshold >= 0: no select on `nearer`)
__kernel void gt_foreground_mask(__global const GT_PIXEL *frame, __global const float *bg, const float threshold,
                                 const int use_missing, const float missing, const int nearer, __global uchar *out)
{
    const int at = get_global_id(0);
    const float x = (float)frame[at], b = bg[at];
    // x == x, b == b: not NaN (the programs are built without fast-math options)
    const int valid = x == x && b == b && (!use_missing || (x != missing && b != missing));
    out[at] = valid && fabs(x - b) >= threshold && (!nearer || b >= x);
}
