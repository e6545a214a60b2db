// Forward kinematics of an articulated chain (paper 000, eq. 2-11): one work-item per
// parameter vector, a serial loop over the parts (parents precede children).
//
// table  (J, 10) int: parent, rotation axis 0-2 (0 x, 1 y, 2 z, -1 none), angle parameter 0-2,
//                     parameter added to translation x, y, z (-1 none)
// offsets (J, 3) real_t: fixed translation of each joint in its parent's coordinates
// params (B, P) real_t; out (B, J, 3, 4) real_t camera-from-part [R | t], row-major.
//
// Build with -DGT_FK_DOUBLE=1 for the float64 variant (default float32).

#ifndef GT_FK_DOUBLE
#define GT_FK_DOUBLE 0
#endif

#if GT_FK_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real_t;
typedef double3 real3;
#else
typedef float real_t;
typedef float3 real3;
#endif

#define GT_FK_COLS 10

// right-multiply R = [c0 c1 c2] (columns) by Rx/Ry/Rz(a) (eq. 7-9): columns (u, v) =
// ((axis+1)%3, (axis+2)%3) become (c col_u + s col_v, -s col_u + c col_v)
#define GT_FK_MIX(U, V)                    \
    do {                                   \
        const real3 cu = U, cv = V;        \
        U = c * cu + s * cv;               \
        V = -s * cu + c * cv;              \
    } while (0)

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
        real3 c0 = (real3)(1, 0, 0), c1 = (real3)(0, 1, 0), c2 = (real3)(0, 0, 1);
        for (int k = 0; k < 3; ++k) {
            const int axis = row[1 + k];
            if (axis < 0)
                continue;
            real_t c;
            const real_t s = sincos(p[row[4 + k]], &c);
            if (axis == 0)
                GT_FK_MIX(c1, c2);
            else if (axis == 1)
                GT_FK_MIX(c2, c0);
            else
                GT_FK_MIX(c0, c1);
        }
        real3 t = (real3)(offsets[3 * j], offsets[3 * j + 1], offsets[3 * j + 2]);
        if (row[7] >= 0)
            t.x += p[row[7]];
        if (row[8] >= 0)
            t.y += p[row[8]];
        if (row[9] >= 0)
            t.z += p[row[9]];
        const int parent = row[0];
        if (parent >= 0) {  // eq. 2-3: camera-from-parent @ parent-from-part
            __global const real_t *q = o + parent * 12;
            const real3 q0 = (real3)(q[0], q[4], q[8]), q1 = (real3)(q[1], q[5], q[9]), q2 = (real3)(q[2], q[6], q[10]);
            const real3 qt = (real3)(q[3], q[7], q[11]);
            const real3 n0 = q0 * c0.x + q1 * c0.y + q2 * c0.z;
            const real3 n1 = q0 * c1.x + q1 * c1.y + q2 * c1.z;
            const real3 n2 = q0 * c2.x + q1 * c2.y + q2 * c2.z;
            t = q0 * t.x + q1 * t.y + q2 * t.z + qt;
            c0 = n0;
            c1 = n1;
            c2 = n2;
        }
        __global real_t *dst = o + j * 12;
        dst[0] = c0.x; dst[1] = c1.x; dst[2] = c2.x; dst[3] = t.x;
        dst[4] = c0.y; dst[5] = c1.y; dst[6] = c2.y; dst[7] = t.y;
        dst[8] = c0.z; dst[9] = c1.z; dst[10] = c2.z; dst[11] = t.z;
    }
}
