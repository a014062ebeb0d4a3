#include "disco/sector_correlation.hpp"

#include <algorithm>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <vector>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels
#include "disco/sector_fft.hpp"
#include "disco/simd_lanes.hpp"

namespace disco {

namespace {

// Namespaces plain, sse2, avx2 and avx512: the body compiled at each level.
#define DISCO_LEVELS_BODY "disco/sector_correlation.inc"
#include "disco/simd_levels.inc"
#undef DISCO_LEVELS_BODY

void check_shape(std::int64_t images, std::int64_t stride, std::int64_t rings,
                 std::int64_t sectors) {
    if (images < 0 || stride < 0 || rings < 1 || sectors < 1 || sectors > (1 << 20))
        throw std::invalid_argument(
            "sector_correlation: rings >= 1, sectors in [1, 2^20], images and stride >= 0");
}

// Where each of `count` images `stride` floats apart starts: the kernels take images
// by address, so that rows held apart (a cache's) need no gathered copy.
std::vector<const float*> image_table(const float* first, std::int64_t count,
                                      std::int64_t stride) {
    std::vector<const float*> table(static_cast<std::size_t>(count));
    for (std::int64_t k = 0; k < count; ++k) table[static_cast<std::size_t>(k)] = first + k * stride;
    return table;
}

}  // namespace

void aligned_correlations(const float* queries, std::int64_t views, const float* candidates,
                          std::int64_t count, std::int64_t stride, std::int64_t rings,
                          std::int64_t sectors, float* scores) {
    check_shape(count, stride, rings, sectors);
    const auto table = image_table(candidates, count, stride);
    aligned_correlations_at(queries, views, table.data(), count, rings, sectors, scores);
}

void aligned_correlations_at(const float* queries, std::int64_t views,
                             const float* const* candidates, std::int64_t count,
                             std::int64_t rings, std::int64_t sectors, float* scores) {
    check_shape(views, 0, rings, sectors);
    check_shape(count, 0, rings, sectors);
    if (views == 0 || count == 0) return;
    const auto run = [&](auto kernel) {
        kernel(queries, views, candidates, count, rings, sectors, scores);
    };
    switch (sector_fft_level()) {
#if DISCO_SIMD_X86
        case 3: return run(avx512::aligned_run);
        case 2: return run(avx2::aligned_run);
        case 1: return run(sse2::aligned_run);
#endif
        default: return run(plain::aligned_run);
    }
}

namespace {

void yaw_any(const float* query, const float* matches, std::int64_t count, std::int64_t stride,
             std::int64_t rings, std::int64_t sectors, const float* weights, float* curves,
             std::int64_t sep, float* yaws, float* confs) {
    check_shape(count, stride, rings, sectors);
    if (count == 0) return;
    const auto table = image_table(matches, count, stride);
    const auto run = [&](auto kernel) {
        kernel(query, table.data(), count, rings, sectors, weights, curves, sep, yaws, confs);
    };
    switch (sector_fft_level()) {
#if DISCO_SIMD_X86
        case 3: return run(avx512::yaw_run);
        case 2: return run(avx2::yaw_run);
        case 1: return run(sse2::yaw_run);
#endif
        default: return run(plain::yaw_run);
    }
}

}  // namespace

void yaw_curves(const float* query, const float* matches, std::int64_t count,
                std::int64_t stride, std::int64_t rings, std::int64_t sectors,
                const float* weights, float* curves) {
    yaw_any(query, matches, count, stride, rings, sectors, weights, curves, 0, nullptr,
            nullptr);
}

void yaw_conf(const float* query, const float* matches, std::int64_t count,
              std::int64_t stride, std::int64_t rings, std::int64_t sectors,
              const float* weights, std::int64_t sep, float* yaws, float* confs) {
    yaw_any(query, matches, count, stride, rings, sectors, weights, nullptr, sep, yaws, confs);
}

}  // namespace disco
