// Forward kinematics of an articulated chain (paper 000, eq. 2-11): one work-item per
// parameter vector, a serial loop over the parts (parents precede children).
//
// table  (J, 10) int: parent, rotation axis 0-2 (0 x, 1 y, 2 z, -1 none), angle parameter 0-2,
//                     parameter added to translation x, y, z (-1 none)
// offsets (J, 3) REAL: fixed translation of each joint in its parent's coordinates
// params (B, P) REAL; out (B, J, 3, 4) REAL camera-from-part [R | t], row-major.
//
// Build with -DGT_FK_DOUBLE=1 for the float64 variant (default float32).

#ifndef GT_FK_DOUBLE
#define GT_FK_DOUBLE 0
#endif

#if GT_FK_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real_t;
#else
typedef float real_t;
#endif

#define GT_FK_COLS 10

// right-multiply R (row-major 3x3) by Rx/Ry/Rz(a) (eq. 7-9): columns (u, v) = ((axis+1)%3, (axis+2)%3)
// become (c col_u + s col_v, -s col_u + c col_v)
static void gt_fk_rotate(real_t *R, const int axis, const real_t a)
{
    const real_t c = cos(a), s = sin(a);
    const int u = (axis + 1) % 3, v = (axis + 2) % 3;
    for (int r = 0; r < 3; ++r) {
        const real_t cu = R[3 * r + u], cv = R[3 * r + v];
        R[3 * r + u] = c * cu + s * cv;
        R[3 * r + v] = -s * cu + c * cv;
    }
}

__kernel void gt_forward_kinematics(__global const real_t *params, __global const int *table,
                                    __global const real_t *offsets, __global real_t *out,
                                    const int B, const int P, const int J)
{
    const int b = get_global_id(0);
    if (b >= B)
        return;
    __global const real_t *p = params + (size_t)b * P;
    __global real_t *o = out + (size_t)b * J * 12;
    for (int j = 0; j < J; ++j) {
        __global const int *row = table + j * GT_FK_COLS;
        real_t R[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
        for (int k = 0; k < 3; ++k) {
            const int axis = row[1 + k];
            if (axis >= 0)
                gt_fk_rotate(R, axis, p[row[4 + k]]);
        }
        real_t t[3];
        for (int k = 0; k < 3; ++k) {
            const int idx = row[7 + k];
            t[k] = offsets[3 * j + k] + (idx >= 0 ? p[idx] : (real_t)0);
        }
        __global real_t *dst = o + j * 12;
        const int parent = row[0];
        if (parent >= 0) {  // eq. 2-3: camera-from-parent @ parent-from-part
            __global const real_t *q = o + parent * 12;
            for (int r = 0; r < 3; ++r) {
                const real_t q0 = q[4 * r], q1 = q[4 * r + 1], q2 = q[4 * r + 2];
                dst[4 * r + 0] = q0 * R[0] + q1 * R[3] + q2 * R[6];
                dst[4 * r + 1] = q0 * R[1] + q1 * R[4] + q2 * R[7];
                dst[4 * r + 2] = q0 * R[2] + q1 * R[5] + q2 * R[8];
                dst[4 * r + 3] = q0 * t[0] + q1 * t[1] + q2 * t[2] + q[4 * r + 3];
            }
        } else {
            for (int r = 0; r < 3; ++r) {
                dst[4 * r + 0] = R[3 * r];
                dst[4 * r + 1] = R[3 * r + 1];
                dst[4 * r + 2] = R[3 * r + 2];
                dst[4 * r + 3] = t[r];
            }
        }
    }
}
