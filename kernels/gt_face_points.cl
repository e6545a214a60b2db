// The projection of face hypotheses (paper 003 eq. 5, 11): the same as
// gputrack/backends/reference/face_points.py, in float32. One work-item per hypothesis.
// states (N, P = 6 + D): r (Rodrigues, model -> camera), t (mm), a (D); model (K, 3, 1 + D): column 0
// the mean shape, columns 1.. the deformation basis; cam: fx, fy, cx, cy, the least depth, the clip.

__kernel void gt_face_points(__global const float *states, __global const float *model, __global const float *cam,
                             __global float *points, __global float *facing, const int N, const int K, const int D) {
    const int n = get_global_id(0);
    if (n >= N) return;
    const int P = 6 + D;
    __global const float *u = states + (long)n * P;
    const float r0 = u[0], r1 = u[1], r2 = u[2], t0 = u[3], t1 = u[4], t2 = u[5];
    // R = I + a [r]x + b [r]x^2, a = sin th / th, b = (1 - cos th) / th^2 (series below 1e-3)
    const float tt = r0 * r0 + r1 * r1 + r2 * r2, th = sqrt(tt);
    float a, b;
    if (th < 1e-3f) {
        a = 1.0f - tt / 6.0f + tt * tt / 120.0f;
        b = 0.5f - tt / 24.0f + tt * tt / 720.0f;
    } else {
        const float sh = sin(0.5f * th), ch = cos(0.5f * th);  // sin th = 2 sh ch, 1 - cos th = 2 sh^2
        a = 2.0f * sh * ch / th;
        b = 2.0f * sh * sh / (th * th);
    }
    const float Kx[9] = {0.0f, -r2, r1, r2, 0.0f, -r0, -r1, r0, 0.0f};
    float R[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            R[i * 3 + j] = (float)(i == j) + a * Kx[i * 3 + j]
                           + b * (Kx[i * 3] * Kx[j] + Kx[i * 3 + 1] * Kx[3 + j] + Kx[i * 3 + 2] * Kx[6 + j]);
    const float fx = cam[0], fy = cam[1], cx = cam[2], cy = cam[3], near = cam[4], clip = cam[5];
    for (int k = 0; k < K; ++k) {
        float X[3];
        for (int c = 0; c < 3; ++c) {
            __global const float *m = model + ((long)k * 3 + c) * (1 + D);
            float x = m[0];
            for (int d = 0; d < D; ++d) x += m[1 + d] * u[6 + d];  // eq. 11
            X[c] = x;
        }
        const float Y0 = R[0] * X[0] + R[1] * X[1] + R[2] * X[2] + t0;
        const float Y1 = R[3] * X[0] + R[4] * X[1] + R[5] * X[2] + t1;
        const float Y2 = R[6] * X[0] + R[7] * X[1] + R[8] * X[2] + t2;
        const float iz = 1.0f / fmax(Y2, near);  // eq. 5
        __global float *p = points + ((long)n * K + k) * 2;
        p[0] = fmin(fmax(fx * Y0 * iz + cx, -clip), clip);
        p[1] = fmin(fmax(fy * Y1 * iz + cy, -clip), clip);
    }
    facing[n] = (R[2] * t0 + R[5] * t1 + R[8] * t2) / fmax(sqrt(t0 * t0 + t1 * t1 + t2 * t2), 1e-9f);
}
