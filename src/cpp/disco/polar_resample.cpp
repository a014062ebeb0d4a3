#include "disco/polar_resample.hpp"

#include <stdexcept>
#include <string>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels
#include "disco/resample_limits.hpp"

#if defined(__SSE2__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define DISCO_RESAMPLE_AVX2 1
#endif

namespace disco {

namespace {

// Cells [from, to) of one view, one at a time: the definition, and the tail of the
// vector kernel.
void resample_cells(const float* padded, std::int64_t width, const float* ring,
                    const float* sector, std::int64_t from, std::int64_t to, Limits lim,
                    float* o) {
    for (std::int64_t c = from; c < to; ++c) {
        const float rf = ring[c], sf = sector[c];
        if (!lim.holds(rf, sf)) outside("resample_views");
        const std::int32_t r0 = static_cast<std::int32_t>(rf);
        const std::int32_t s0 = static_cast<std::int32_t>(sf);
        const float fr = rf - static_cast<float>(r0);
        const float fs = sf - static_cast<float>(s0);
        const std::int64_t k = static_cast<std::int64_t>(r0) * width + s0;
        const float a0 = padded[k], a1 = padded[k + 1];
        const float b0 = padded[k + width], b1 = padded[k + width + 1];
        const float near = a0 + (a1 - a0) * fs;
        const float far = b0 + (b1 - b0) * fs;
        o[c] = near + (far - near) * fr;
    }
}

#if DISCO_RESAMPLE_AVX2
// Eight cells at once with AVX2 gathers, chosen at run time. The same operations in
// the same order as `resample_cells` (truncating conversions, no FMA), so the same
// values to the bit.
__attribute__((target("avx2"))) void resample_avx2(const float* padded, std::int64_t width,
                                                   const float* ring, const float* sector,
                                                   std::int64_t cells, Limits lim, float* o) {
    const __m256 zero = _mm256_setzero_ps();
    const __m256 ring_lim = _mm256_set1_ps(lim.ring), sector_lim = _mm256_set1_ps(lim.sector);
    const __m256i w = _mm256_set1_epi32(static_cast<std::int32_t>(width));
    std::int64_t c = 0;
    for (; c + 8 <= cells; c += 8) {
        const __m256 rf = _mm256_loadu_ps(ring + c);
        const __m256 sf = _mm256_loadu_ps(sector + c);
        const __m256 ok = _mm256_and_ps(
            _mm256_and_ps(_mm256_cmp_ps(rf, zero, _CMP_GE_OQ), _mm256_cmp_ps(rf, ring_lim, _CMP_LT_OQ)),
            _mm256_and_ps(_mm256_cmp_ps(sf, zero, _CMP_GE_OQ),
                          _mm256_cmp_ps(sf, sector_lim, _CMP_LT_OQ)));
        if (_mm256_movemask_ps(ok) != 0xFF) outside("resample_views");
        const __m256i r0 = _mm256_cvttps_epi32(rf);
        const __m256i s0 = _mm256_cvttps_epi32(sf);
        const __m256 fr = _mm256_sub_ps(rf, _mm256_cvtepi32_ps(r0));
        const __m256 fs = _mm256_sub_ps(sf, _mm256_cvtepi32_ps(s0));
        const __m256i k = _mm256_add_epi32(_mm256_mullo_epi32(r0, w), s0);
        const __m256 a0 = _mm256_i32gather_ps(padded, k, 4);
        const __m256 a1 = _mm256_i32gather_ps(padded + 1, k, 4);
        const __m256 b0 = _mm256_i32gather_ps(padded + width, k, 4);
        const __m256 b1 = _mm256_i32gather_ps(padded + width + 1, k, 4);
        const __m256 near = _mm256_add_ps(a0, _mm256_mul_ps(_mm256_sub_ps(a1, a0), fs));
        const __m256 far = _mm256_add_ps(b0, _mm256_mul_ps(_mm256_sub_ps(b1, b0), fs));
        _mm256_storeu_ps(o + c, _mm256_add_ps(near, _mm256_mul_ps(_mm256_sub_ps(far, near), fr)));
    }
    resample_cells(padded, width, ring, sector, c, cells, lim, o);
}

bool has_avx2() {
    static const bool yes = __builtin_cpu_supports("avx2");
    return yes;
}
#endif

}  // namespace

void outside(const char* kernel) {
    throw std::out_of_range(std::string(kernel) + ": a place outside the image");
}

void resample_views(const float* padded, std::int64_t padded_size, std::int64_t width,
                    const std::vector<ResamplePlaces>& places, std::int64_t cells, float* out) {
    const Limits lim = Limits::of(padded_size / width, width);
#if DISCO_RESAMPLE_AVX2
    // The AVX2 kernel where the CPU has it and the level cap that the BEV kernels share
    // (set_bev_kernel_level) allows level 2, so tests can check the plain one too.
    // 32-bit gather offsets: images of up to 2^31 floats (any polar BEV here).
    const bool avx2 =
        bev_kernel_level() >= 2 && has_avx2() && padded_size < (std::int64_t{1} << 31);
#endif
    for (std::size_t v = 0; v < places.size(); ++v) {
        const float* ring = places[v];
        const float* sector = ring + cells;
        float* o = out + static_cast<std::int64_t>(v) * cells;
#if DISCO_RESAMPLE_AVX2
        if (avx2) {
            resample_avx2(padded, width, ring, sector, cells, lim, o);
            continue;
        }
#endif
        resample_cells(padded, width, ring, sector, 0, cells, lim, o);
    }
}

}  // namespace disco
