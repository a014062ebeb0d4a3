#include "disco/recentre_curves.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels
#include "disco/sector_fft.hpp"

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define DISCO_RECENTRE_X86 1
#endif

namespace disco {

namespace {

// The limits that keep all four reads of a corner inside the table: ring < rows - 1 and
// sector < width - 1, checked as floats (NaN fails every comparison) before any cast.
struct Limits {
    float ring, sector;
};

[[noreturn]] void outside() {
    throw std::out_of_range("recentre_curves: a place outside the image");
}

// Cells [from, to) of one view, one at a time (polar_resample.hpp's read, the same
// operations in the same order): the plain levels, and the tail of the vector ones.
void resample_cells(const RecentreImage& im, const float* ring, const float* sector,
                    std::int64_t from, std::int64_t to, Limits lim, float* o) {
    const float* padded = im.padded;
    const std::int64_t width = im.width;
    for (std::int64_t c = from; c < to; ++c) {
        const float rf = ring[c], sf = sector[c];
        if (!(rf >= 0.0f && rf < lim.ring && sf >= 0.0f && sf < lim.sector)) outside();
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

void resample_plain(const RecentreImage& im, const float* places, std::int64_t cells,
                    Limits lim, float* o) {
    resample_cells(im, places, places + cells, 0, cells, lim, o);
}

namespace plain {
constexpr int W = 1;
typedef float vf;
static inline vf vsqrt(vf x) { return std::sqrt(x); }
static inline void resample_view(const RecentreImage& im, const float* places,
                                 std::int64_t cells, Limits lim, float* o) {
    resample_plain(im, places, cells, lim, o);
}
#include "disco/sector_fft.inc"
#include "disco/recentre_curves.inc"
}  // namespace plain

#if DISCO_RECENTRE_X86
namespace sse2 {  // the x86-64 baseline: no target needed
constexpr int W = 4;
typedef float vf __attribute__((vector_size(16)));
static inline vf vsqrt(vf x) { return (vf)_mm_sqrt_ps((__m128)x); }
static inline void resample_view(const RecentreImage& im, const float* places,
                                 std::int64_t cells, Limits lim, float* o) {
    resample_plain(im, places, cells, lim, o);
}
#include "disco/sector_fft.inc"
#include "disco/recentre_curves.inc"
}  // namespace sse2

#pragma GCC push_options
#pragma GCC target("avx2")
namespace avx2 {
constexpr int W = 8;
typedef float vf __attribute__((vector_size(32)));
static inline vf vsqrt(vf x) { return (vf)_mm256_sqrt_ps((__m256)x); }
// Eight cells at once with AVX2 gathers (polar_resample.cpp's kernel).
static void resample_view(const RecentreImage& im, const float* places, std::int64_t cells,
                          Limits lim, float* o) {
    const float* ring = places;
    const float* sector = places + cells;
    const float* padded = im.padded;
    const __m256 zero = _mm256_setzero_ps();
    const __m256 ring_lim = _mm256_set1_ps(lim.ring), sector_lim = _mm256_set1_ps(lim.sector);
    const __m256i w = _mm256_set1_epi32(static_cast<std::int32_t>(im.width));
    std::int64_t c = 0;
    for (; c + 8 <= cells; c += 8) {
        const __m256 rf = _mm256_loadu_ps(ring + c);
        const __m256 sf = _mm256_loadu_ps(sector + c);
        const __m256 ok = _mm256_and_ps(
            _mm256_and_ps(_mm256_cmp_ps(rf, zero, _CMP_GE_OQ),
                          _mm256_cmp_ps(rf, ring_lim, _CMP_LT_OQ)),
            _mm256_and_ps(_mm256_cmp_ps(sf, zero, _CMP_GE_OQ),
                          _mm256_cmp_ps(sf, sector_lim, _CMP_LT_OQ)));
        if (_mm256_movemask_ps(ok) != 0xFF) outside();
        const __m256i r0 = _mm256_cvttps_epi32(rf);
        const __m256i s0 = _mm256_cvttps_epi32(sf);
        const __m256 fr = _mm256_sub_ps(rf, _mm256_cvtepi32_ps(r0));
        const __m256 fs = _mm256_sub_ps(sf, _mm256_cvtepi32_ps(s0));
        const __m256i k = _mm256_add_epi32(_mm256_mullo_epi32(r0, w), s0);
        const __m256 a0 = _mm256_i32gather_ps(padded, k, 4);
        const __m256 a1 = _mm256_i32gather_ps(padded + 1, k, 4);
        const __m256 b0 = _mm256_i32gather_ps(padded + im.width, k, 4);
        const __m256 b1 = _mm256_i32gather_ps(padded + im.width + 1, k, 4);
        const __m256 near = _mm256_add_ps(a0, _mm256_mul_ps(_mm256_sub_ps(a1, a0), fs));
        const __m256 far = _mm256_add_ps(b0, _mm256_mul_ps(_mm256_sub_ps(b1, b0), fs));
        _mm256_storeu_ps(o + c, _mm256_add_ps(near, _mm256_mul_ps(_mm256_sub_ps(far, near), fr)));
    }
    resample_cells(im, ring, sector, c, cells, lim, o);
}
#include "disco/sector_fft.inc"
#include "disco/recentre_curves.inc"
}  // namespace avx2
#pragma GCC pop_options

#pragma GCC push_options
#pragma GCC target("avx512f")
#pragma GCC diagnostic push
// GCC 12 warns inside its own avx512fintrin.h (_mm512_undefined_*): a false positive.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
namespace avx512 {
constexpr int W = 16;
typedef float vf __attribute__((vector_size(64)));
static inline vf vsqrt(vf x) { return (vf)_mm512_sqrt_ps((__m512)x); }
// Sixteen cells at once: each corner's two neighbours along sectors are one 64-bit
// gather (half the gathered elements of four 32-bit gathers), split into the two
// floats afterwards. The same arithmetic as resample_cells.
static void resample_view(const RecentreImage& im, const float* places, std::int64_t cells,
                          Limits lim, float* o) {
    const float* ring = places;
    const float* sector = places + cells;
    const float* padded = im.padded;
    const float* next = padded + im.width;
    const __m512 zero = _mm512_setzero_ps();
    const __m512 ring_lim = _mm512_set1_ps(lim.ring), sector_lim = _mm512_set1_ps(lim.sector);
    const __m512i w = _mm512_set1_epi32(static_cast<std::int32_t>(im.width));
    const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24,
                                           26, 28, 30);
    const __m512i odd = _mm512_add_epi32(even, _mm512_set1_epi32(1));
    std::int64_t c = 0;
    for (; c + 16 <= cells; c += 16) {
        const __m512 rf = _mm512_loadu_ps(ring + c);
        const __m512 sf = _mm512_loadu_ps(sector + c);
        const __mmask16 ok = _mm512_cmp_ps_mask(rf, zero, _CMP_GE_OQ) &
                             _mm512_cmp_ps_mask(rf, ring_lim, _CMP_LT_OQ) &
                             _mm512_cmp_ps_mask(sf, zero, _CMP_GE_OQ) &
                             _mm512_cmp_ps_mask(sf, sector_lim, _CMP_LT_OQ);
        if (ok != 0xFFFF) outside();
        const __m512i r0 = _mm512_cvttps_epi32(rf);
        const __m512i s0 = _mm512_cvttps_epi32(sf);
        const __m512 fr = _mm512_sub_ps(rf, _mm512_cvtepi32_ps(r0));
        const __m512 fs = _mm512_sub_ps(sf, _mm512_cvtepi32_ps(s0));
        const __m512i k = _mm512_add_epi32(_mm512_mullo_epi32(r0, w), s0);
        const __m256i klo = _mm512_castsi512_si256(k);
        const __m256i khi = _mm512_extracti64x4_epi64(k, 1);
        const __m512 alo = _mm512_castsi512_ps(_mm512_i32gather_epi64(klo, padded, 4));
        const __m512 ahi = _mm512_castsi512_ps(_mm512_i32gather_epi64(khi, padded, 4));
        const __m512 blo = _mm512_castsi512_ps(_mm512_i32gather_epi64(klo, next, 4));
        const __m512 bhi = _mm512_castsi512_ps(_mm512_i32gather_epi64(khi, next, 4));
        const __m512 a0 = _mm512_permutex2var_ps(alo, even, ahi);
        const __m512 a1 = _mm512_permutex2var_ps(alo, odd, ahi);
        const __m512 b0 = _mm512_permutex2var_ps(blo, even, bhi);
        const __m512 b1 = _mm512_permutex2var_ps(blo, odd, bhi);
        const __m512 near = _mm512_add_ps(a0, _mm512_mul_ps(_mm512_sub_ps(a1, a0), fs));
        const __m512 far = _mm512_add_ps(b0, _mm512_mul_ps(_mm512_sub_ps(b1, b0), fs));
        _mm512_storeu_ps(o + c, _mm512_add_ps(near, _mm512_mul_ps(_mm512_sub_ps(far, near), fr)));
    }
    resample_cells(im, ring, sector, c, cells, lim, o);
}
#include "disco/sector_fft.inc"
#include "disco/recentre_curves.inc"
}  // namespace avx512
#pragma GCC diagnostic pop
#pragma GCC pop_options
#endif

}  // namespace

void recentre_curves(const RecentreImage& image, const std::vector<const float*>& places,
                     const float* match, const float* weights, float* curves) {
    if (image.rings < 1 || image.sectors < 1 || image.rings_padded < image.rings ||
        image.rings_padded % 16 != 0 || image.width < 2 || image.padded_size < 2 * image.width)
        throw std::invalid_argument(
            "recentre_curves: rings and sectors >= 1, rings_padded a multiple of 16 >= rings");
    switch (sector_fft_level()) {
#if DISCO_RECENTRE_X86
        case 3: return avx512::run(image, places, match, weights, curves);
        case 2: return avx2::run(image, places, match, weights, curves);
        case 1: return sse2::run(image, places, match, weights, curves);
#endif
        default: return plain::run(image, places, match, weights, curves);
    }
}

}  // namespace disco
