// Self-test kernel: y = a * x + y. Used by the device probe and host/doctor.py.
__kernel void gt_axpy(const float a, __global const float *x, __global float *y, const int n)
{
    const int i = get_global_id(0);
    if (i < n)
        y[i] = a * x[i] + y[i];
}
