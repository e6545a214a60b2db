// Rows of an array written by index (gputrack/ops/rows.py): dst[index[k]] = src[k], bit for bit.
// A row is `row` elements of 4 bytes (gt_scatter_words) or of 1 byte (gt_scatter_bytes); with
// src_rows == 1 the one row of src is written at every index. NDRange (row, K): work-item (e, k)
// copies element e of row k.

__kernel void gt_scatter_words(__global uint *dst, __global const int *index, __global const uint *src,
                               const int row, const int K, const int src_rows)
{
    const int e = get_global_id(0), k = get_global_id(1);
    if (e >= row || k >= K)
        return;
    dst[(size_t)index[k] * row + e] = src[(size_t)min(k, src_rows - 1) * row + e];
}

__kernel void gt_scatter_bytes(__global uchar *dst, __global const int *index, __global const uchar *src,
                               const int row, const int K, const int src_rows)
{
    const int e = get_global_id(0), k = get_global_id(1);
    if (e >= row || k >= K)
        return;
    dst[(size_t)index[k] * row + e] = src[(size_t)min(k, src_rows - 1) * row + e];
}
