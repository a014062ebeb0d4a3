#pragma once
// Second pass of disco's signature searches: exact distances of candidate rows, read
// in place by index (no gathered copy), and the k nearest by (distance, row).
//
// A row's squared distance to a query is summed in double over 32 lanes (lane l takes
// the dimensions j = l mod 32) and the lanes are added in a fixed tree, every product
// and sum rounded once (no FMA): the AVX-512, AVX2 and plain kernels give the same
// bits, so which rows win a near-tie never depends on the CPU.
#include <cstdint>

namespace disco {

// Squared distances out[i] = |x[rows[i]] - q|^2 (x float32 [n, d] row-major, q [d]).
// Rows must be in [0, n); the caller checks.
void exact_sq_distances(const float* x, std::int64_t d, const float* q,
                        const std::int64_t* rows, std::int64_t m, double* out);

// For each of b queries (q [b, d]): the k nearest of its m candidates cand[i, :]
// (entries < 0 are skipped) by squared distance, ties by row, written to out_rows
// [b, k] and their distances (square roots) to out_dists [b, k]; padded with -1 and
// infinity where fewer than k candidates are given.
void exact_topk(const float* x, std::int64_t d, const float* q, std::int64_t b,
                const std::int64_t* cand, std::int64_t m, int k, std::int64_t* out_rows,
                double* out_dists);

// "avx512", "avx2" or "plain": the kernel that exact_sq_distances runs now (under the
// BEV kernels' level cap).
const char* exact_kernel_name();

}  // namespace disco
