#pragma once
// First pass of disco's exact signature search: bounds of every row's distance to a
// query from an int8 copy of the signatures, and the rows that can still be in the top k.
//
// A signature x is stored as codes c (int8) with x_hat = mean + scale * c (per
// dimension), and its reconstruction error err = |x - x_hat|. The query enters as
// u = q - mean and w = u * scale, and w is quantized to int16 g with step t
// (w = t g + delta). Then, exactly in integers, G = g . c, and
//     A = |u|^2 - 2 t G + |scale * c|^2 = |q - x_hat|^2 - 2 delta . c,
// so |q - x_hat|^2 lies within A -/+ 2 |delta| |c|, and |q - x| within err of
// |q - x_hat| (triangle inequality). A row whose lower bound exceeds the k-th smallest
// upper bound cannot be in the top k; the caller re-measures the rest exactly.
#include <cstdint>
#include <vector>

namespace disco {

struct Int8Rows {
    const std::int8_t* codes = nullptr;  // [n, d] row-major
    std::int64_t n = 0;
    std::int64_t d = 0;
    const double* code_sq = nullptr;    // [n] |scale * c|^2
    const double* code_norm = nullptr;  // [n] |c|
    const double* err = nullptr;        // [n] |x - x_hat|, rounded up
};

struct Int8Query {
    const std::int16_t* g = nullptr;  // [d]
    double u_sq = 0.0;                // |q - mean|^2
    double step = 0.0;                // t
    double delta_norm = 0.0;          // |w - t g|
};

// The query q (float32 [d]) as int8_candidates reads it, for codes made with `offset`
// and `scale` [d]: u = q - offset, w = u * scale, g = rint(w / t) (|g| <= g_max, with
// t = max |w| / g_max), and |w - t g| rounded up. `g` [d] receives the weights.
Int8Query int8_query(const float* q, const double* offset, const double* scale, std::int64_t d,
                     int g_max, std::int16_t* g);

// Rows < limit that are not excluded (exclude may be null) and whose lower bound is
// at most the k-th smallest upper bound, in increasing row order. `threads` >= 1.
std::vector<std::int64_t> int8_candidates(const Int8Rows& rows, const Int8Query& query, int k,
                                          std::int64_t limit, const std::uint8_t* exclude,
                                          int threads);

// Codes of float32 rows x [n, d]: c = clamp(rint((x - mean) / scale), -127, 127), with
// |scale * c|^2, |c| and |x - mean - scale * c| per row (all in double precision).
// Outputs are preallocated by the caller: codes [n, d], code_sq, code_norm, err [n].
void int8_encode(const float* x, std::int64_t n, std::int64_t d, const double* mean,
                 const double* scale, std::int8_t* codes, double* code_sq, double* code_norm,
                 double* err, int threads);

// g . c for every row (for tests of the kernel itself).
std::vector<std::int32_t> int8_dots(const Int8Rows& rows, const std::int16_t* g, int threads);

// The largest |g_j| for which g . c cannot overflow int32 at dimension d (and which
// splits into the two int8 halves of the VNNI kernel).
int int8_query_limit(std::int64_t d);

// "avx512vnni", "avx2" or "plain": the kernel that computes g . c now (under the BEV
// kernels' level cap) for a g within int8_query_limit.
const char* int8_kernel_name();

}  // namespace disco
