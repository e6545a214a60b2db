// Forward kinematics of an articulated chain (paper 000, eq. 2-11): one work-item per
// parameter vector, a serial loop over the parts (gt_fk_pose in gt_kinematics.clh).
// params (B, P); out (B, J, 3, 4) camera-from-part [R | t], row-major; the chain's tables as
// described in gt_kinematics.clh.
//
// Build with -DGT_FK_DOUBLE=1 for the float64 variant (default float32).

#ifndef GT_FK_DOUBLE
#define GT_FK_DOUBLE 0
#endif

#if GT_FK_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define GT_FK_REAL double
#else
#define GT_FK_REAL float
#endif

#include "gt_kinematics.clh"

__kernel void gt_forward_kinematics(__global const GT_FK_REAL *params, __global const int *table,
                                    __global const GT_FK_REAL *offsets, __global GT_FK_REAL *out,
                                    const int B, const int P, const int J)
{
    const int b = get_global_id(0);
    if (b >= B)
        return;
    gt_fk_pose(params + (size_t)b * P, table, offsets, out + (size_t)b * J * 12, J);
}
