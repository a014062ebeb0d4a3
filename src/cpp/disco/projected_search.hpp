#pragma once
// The views' first pass (disco_cli.maps.signature_index.ProjectedSignatures): each map
// row's approximate squared distance to a few projected queries, from the rows'
// projections held in column tiles, so that one pass reads them in order.
//
// Each dot product is summed as one fused multiply-add per projected axis, in axis
// order, from zero: the float32 value that a BLAS sgemm summing over k in order
// gives (NumPy's OpenBLAS does, bit for bit), on every kernel level.
#include <cstdint>

namespace disco {

// Columns per tile: tiles[t, k, c] = pt[k, t * kProjectedTile + c] (zero past n).
constexpr int kProjectedTile = 64;

// out[i, j] = sq[j] - 2 (q[i, :] . pt[:, j]) in float32 for i < b, j < n, where q is
// [b, p] and pt [p, n] is given as tiles [ceil(n / kProjectedTile), p, kProjectedTile].
void projected_approx(const float* tiles, std::int64_t p, std::int64_t n, const float* sq,
                      const float* q, std::int64_t b, float* out);

// "avx512", "avx2" or "plain": the kernel that projected_approx runs now.
const char* projected_kernel_name();

}  // namespace disco
