#include "disco/exact_search.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define DISCO_X86 1
#endif

namespace disco {
namespace {

constexpr int kLanes = 32;

// The tail dimensions (d mod 32) into their lanes, then the fixed tree: lane i takes
// lane i + w for w = 16, 8, 4, 2, 1. Shared by every kernel.
double finish(double* lane, const float* row, const double* q, std::int64_t from,
              std::int64_t d) {
    for (std::int64_t j = from; j < d; ++j) {
        const double t = static_cast<double>(row[j]) - q[j];
        lane[j % kLanes] += t * t;
    }
    for (int w = kLanes / 2; w >= 1; w /= 2)
        for (int i = 0; i < w; ++i) lane[i] += lane[i + w];
    return lane[0];
}

double row_plain(const float* row, const double* q, std::int64_t d) {
    double lane[kLanes] = {};
    const std::int64_t full = d - d % kLanes;
    for (std::int64_t j = 0; j < full; j += kLanes)
        for (int l = 0; l < kLanes; ++l) {
            const double t = static_cast<double>(row[j + l]) - q[j + l];
            lane[l] += t * t;
        }
    return finish(lane, row, q, full, d);
}

#ifdef DISCO_X86
// Lanes 4v .. 4v + 3 in acc[v].
__attribute__((target("avx2"))) double row_avx2(const float* row, const double* q,
                                                std::int64_t d) {
    __m256d acc[8];
    for (auto& a : acc) a = _mm256_setzero_pd();
    const std::int64_t full = d - d % kLanes;
    for (std::int64_t j = 0; j < full; j += kLanes)
        for (int v = 0; v < 8; ++v) {
            const __m256d x = _mm256_cvtps_pd(_mm_loadu_ps(row + j + 4 * v));
            const __m256d t = _mm256_sub_pd(x, _mm256_loadu_pd(q + j + 4 * v));
            acc[v] = _mm256_add_pd(acc[v], _mm256_mul_pd(t, t));
        }
    alignas(32) double lane[kLanes];
    for (int v = 0; v < 8; ++v) _mm256_store_pd(lane + 4 * v, acc[v]);
    return finish(lane, row, q, full, d);
}

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
// GCC 12 warns inside its own avx512fintrin.h (_mm512_undefined_pd): a false positive.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
// Lanes 8v .. 8v + 7 in acc[v].
__attribute__((target("avx512f"))) double row_avx512(const float* row, const double* q,
                                                     std::int64_t d) {
    __m512d acc[4];
    for (auto& a : acc) a = _mm512_setzero_pd();
    const std::int64_t full = d - d % kLanes;
    for (std::int64_t j = 0; j < full; j += kLanes)
        for (int v = 0; v < 4; ++v) {
            const __m512d x = _mm512_cvtps_pd(_mm256_loadu_ps(row + j + 8 * v));
            const __m512d t = _mm512_sub_pd(x, _mm512_loadu_pd(q + j + 8 * v));
            acc[v] = _mm512_add_pd(acc[v], _mm512_mul_pd(t, t));
        }
    alignas(64) double lane[kLanes];
    for (int v = 0; v < 4; ++v) _mm512_store_pd(lane + 8 * v, acc[v]);
    return finish(lane, row, q, full, d);
}
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
#endif

using RowFn = double (*)(const float*, const double*, std::int64_t);

int level_now() {
#ifdef DISCO_X86
    static const bool avx512 = __builtin_cpu_supports("avx512f");
    static const bool avx2 = __builtin_cpu_supports("avx2");
    const int cap = bev_kernel_level();
    if (cap >= 3 && avx512) return 3;
    if (cap >= 2 && avx2) return 2;
#endif
    return 0;
}

RowFn pick_row() {
#ifdef DISCO_X86
    switch (level_now()) {
        case 3:
            return row_avx512;
        case 2:
            return row_avx2;
        default:
            break;
    }
#endif
    return row_plain;
}

void sq_distances(RowFn fn, const float* x, std::int64_t d, const double* q,
                  const std::int64_t* rows, std::int64_t m, double* out) {
    for (std::int64_t i = 0; i < m; ++i) {
        if (rows[i] < 0) {
            out[i] = std::numeric_limits<double>::infinity();
            continue;
        }
        out[i] = fn(x + rows[i] * d, q, d);
    }
}

}  // namespace

void exact_sq_distances(const float* x, std::int64_t d, const float* q,
                        const std::int64_t* rows, std::int64_t m, double* out) {
    const std::vector<double> q64(q, q + d);
    sq_distances(pick_row(), x, d, q64.data(), rows, m, out);
}

void exact_topk(const float* x, std::int64_t d, const float* q, std::int64_t b,
                const std::int64_t* cand, std::int64_t m, int k, std::int64_t* out_rows,
                double* out_dists) {
    const RowFn fn = pick_row();
    const double inf = std::numeric_limits<double>::infinity();
    const auto kk = static_cast<std::size_t>(std::max(k, 0));
    std::vector<double> q64(static_cast<std::size_t>(d)), sq(static_cast<std::size_t>(m));
    std::vector<std::pair<double, std::int64_t>> found;
    found.reserve(static_cast<std::size_t>(m));
    for (std::int64_t i = 0; i < b; ++i) {
        const float* qi = q + i * d;
        std::copy(qi, qi + d, q64.begin());
        const std::int64_t* ci = cand + i * m;
        sq_distances(fn, x, d, q64.data(), ci, m, sq.data());
        found.clear();
        for (std::int64_t j = 0; j < m; ++j)
            if (ci[j] >= 0) found.emplace_back(sq[j], ci[j]);
        const std::size_t keep = std::min(found.size(), kk);
        std::partial_sort(found.begin(), found.begin() + keep, found.end());
        for (std::size_t j = 0; j < kk; ++j) {
            const bool have = j < keep;
            out_rows[i * kk + j] = have ? found[j].second : -1;
            out_dists[i * kk + j] = have ? std::sqrt(found[j].first) : inf;
        }
    }
}

const char* exact_kernel_name() {
    return wide_kernel_name(level_now());
}

}  // namespace disco
