// Particle-filter helpers (paper 000 eq. 12): counter-based sampling around candidates, best-k.
// Same generator as the NumPy reference (gputrack/backends/reference/particles.py).

#include "gt_math.clh"
#include "gt_pcg.clh"

// out (n, p): sample k belongs to candidate k c / n; sigma is (p,) or, with per_candidate, (c, p).
// One work-item per Box-Muller pair: parameters 2t, 2t+1 of sample k are the (cos, sin) pair of
// the uniforms of counters 2 (k hp + t), 2 (k hp + t) + 1, hp = ceil(p / 2). NDRange (n hp,): work-item
// k hp + t (one dimension: PoCL split an (hp, n) range into groups of one sample, ~0.2 us each).
__kernel void gt_sample_around(__global const float *cand, const int c, const int p, __global const float *sig,
                               const int per_candidate, const int n, const uint lo, const uint hi, const int keep,
                               __global float *out)
{
    const int hp = (p + 1) / 2;
    const int g = get_global_id(0);
    if (g >= n * hp)
        return;
    const int t = g % hp, k = g / hp;  // pair t of sample k
    const uint key = gt_pcg(lo ^ gt_pcg(hi));
    const int owner = k * c / n;  // n c < 2**31 (checked by the op)
    const int same = keep && k == (owner * n + c - 1) / c;  // the first sample of the block
    const uint cnt = (uint)(k * hp + t) * 2u;
    const uint b1 = gt_pcg(gt_pcg(cnt) + key), b2 = gt_pcg(gt_pcg(cnt + 1u) + key);
    const float u1 = (float)((b1 >> 8u) + 1u) * (1.0f / 16777216.0f);  // (0, 1]
    const float u2 = (float)(b2 >> 8u) * (1.0f / 16777216.0f);         // [0, 1)
    // gt_math.clh's log and sincos (vectorised on CPUs); the tests pin them to the reference's libm values
    const float r = sqrt(-2.0f * gt_logf(u1));
    float cs;
    const float sn = gt_sincosf(6.2831853071795864f * u2, &cs);
    const int q0 = 2 * t, q1 = 2 * t + 1;
    const float s0 = per_candidate ? sig[owner * p + q0] : sig[q0];
    // eq. 12: p_c + dp, dp ~ N(0, diag(sigma^2))
    out[k * p + q0] = same ? cand[owner * p + q0] : cand[owner * p + q0] + s0 * (r * cs);
    if (q1 < p) {
        const float s1 = per_candidate ? sig[owner * p + q1] : sig[q1];
        out[k * p + q1] = same ? cand[owner * p + q1] : cand[owner * p + q1] + s1 * (r * sn);
    }
}

// uint key ordering float scores ascending; NaN last (bit tests: immune to fast math).
inline uint gt_key(const float s)
{
    const uint bits = as_uint(s);
    if ((bits & 0x7fffffffu) > 0x7f800000u)
        return 0xffffffffu;
    return (bits >> 31u) ? ~bits : (bits | 0x80000000u);
}

// One work-item: an ordered k-list over the b scores (ties keep the lower index), then the
// selected scores and, when p > 0, rows.
__kernel void gt_best_k(__global const float *scores, const int b, const int k, __global int *idx, __global float *val,
                        __global uint *keys, __global const float *rows, const int p, __global float *sel)
{
    if (get_global_id(0) != 0)
        return;
    int cnt = 0;
    for (int i = 0; i < b; ++i) {
        const uint key = gt_key(scores[i]);
        if (cnt < k || key < keys[k - 1]) {
            int pos = min(cnt, k - 1);
            while (pos > 0 && keys[pos - 1] > key) {
                keys[pos] = keys[pos - 1];
                idx[pos] = idx[pos - 1];
                --pos;
            }
            keys[pos] = key;
            idx[pos] = i;
            cnt = min(cnt + 1, k);
        }
    }
    for (int r = 0; r < k; ++r) {
        val[r] = scores[idx[r]];
        for (int q = 0; q < p; ++q)
            sel[r * p + q] = rows[idx[r] * p + q];
    }
}
