#include "disco/recentre_curves.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels
#include "disco/resample_limits.hpp"
#include "disco/sector_fft.hpp"
#include "disco/simd_lanes.hpp"

namespace disco {

namespace {

// Cells [from, to) of one view, one at a time (polar_resample.hpp's read, the same
// operations in the same order, its four values from the corner's quad): the plain
// levels, and the tail of the vector ones.
void resample_cells(const RecentreImage& im, const float* ring, const float* sector,
                    std::int64_t from, std::int64_t to, Limits lim, float* o) {
    const std::int64_t rq = im.rows - 1;
    for (std::int64_t c = from; c < to; ++c) {
        const float rf = ring[c], sf = sector[c];
        if (!lim.holds(rf, sf)) outside("recentre_curves");
        const std::int32_t r0 = static_cast<std::int32_t>(rf);
        const std::int32_t s0 = static_cast<std::int32_t>(sf);
        const float fr = rf - static_cast<float>(r0);
        const float fs = sf - static_cast<float>(s0);
        const float* q = im.quads + (static_cast<std::int64_t>(s0) * rq + r0) * 4;
        const float near = q[0] + (q[1] - q[0]) * fs;
        const float far = q[2] + (q[3] - q[2]) * fs;
        o[c] = near + (far - near) * fr;
    }
}

// One view: its places [2][S][R] (sector-major), its cells written to o [S][Rp].
void resample_plain(const RecentreImage& im, const float* places, Limits lim, float* o) {
    const std::int64_t R = im.rings, cells = im.sectors * R;
    for (std::int64_t s = 0; s < im.sectors; ++s)
        resample_cells(im, places + s * R, places + cells + s * R, 0, R, lim,
                       o + s * im.rings_padded);
}

// The sum of 16 lanes in halves: a[l] += a[l + h] for h = 8, 4, 2, 1, then a[0] (the
// order every level keeps).
float tree16_scalar(float* a) {
    for (int h = 8; h >= 1; h /= 2)
        for (int l = 0; l < h; ++l) a[l] += a[l + h];
    return a[0];
}

#define DISCO_TREE16_SCALAR                                 \
    static inline float tree16(const vf* v) {               \
        float a[16];                                        \
        __builtin_memcpy(a, v, sizeof a);                   \
        return tree16_scalar(a);                            \
    }

namespace plain {
#define DISCO_LANES 1
#include "disco/simd_lanes.inc"
DISCO_TREE16_SCALAR
static inline void resample_view(const RecentreImage& im, const float* places, Limits lim,
                                 float* o) {
    resample_plain(im, places, lim, o);
}
#include "disco/sector_fft.inc"
// The spectra of a vector of rings, `rings` of them not padding.
static inline void rfft_block(const SectorPlan& plan, const float* in, std::int64_t in_stride,
                              float* re, float* im, std::int64_t out_stride, float* work,
                              std::int64_t) {
    rfft_lanes(plan, in, in_stride, re, im, out_stride, work);
}
#include "disco/recentre_curves.inc"
#undef DISCO_LANES
}  // namespace plain

#if DISCO_SIMD_X86
namespace sse2 {  // the x86-64 baseline: no target needed
#define DISCO_LANES 4
#include "disco/simd_lanes.inc"
DISCO_TREE16_SCALAR
static inline void resample_view(const RecentreImage& im, const float* places, Limits lim,
                                 float* o) {
    resample_plain(im, places, lim, o);
}
#include "disco/sector_fft.inc"
// The spectra of a vector of rings, `rings` of them not padding.
static inline void rfft_block(const SectorPlan& plan, const float* in, std::int64_t in_stride,
                              float* re, float* im, std::int64_t out_stride, float* work,
                              std::int64_t) {
    rfft_lanes(plan, in, in_stride, re, im, out_stride, work);
}
#include "disco/recentre_curves.inc"
#undef DISCO_LANES
}  // namespace sse2

#pragma GCC push_options
#pragma GCC target("avx2")
namespace avx2 {
#define DISCO_LANES 8
#include "disco/simd_lanes.inc"
DISCO_TREE16_SCALAR
// Eight cells at once: each cell's quad is one 16-byte load, cells c and c + 4 to a
// register, and four registers transposed within their halves give the cells' four
// values in order. The same arithmetic as resample_cells.
// The places 2 kB ahead of p (of both streams; a prefetch past their end never faults):
// a search reads each view's once, mostly from memory, and the hardware's prefetch alone
// left 2-7 % of a call waiting on them (the more, the busier the machine).
static inline void ahead(const float* p) {
    const std::uintptr_t at = reinterpret_cast<std::uintptr_t>(p) + 2048;
    _mm_prefetch(reinterpret_cast<const char*>(at), _MM_HINT_NTA);
}
static void resample_view(const RecentreImage& im, const float* places, Limits lim,
                          float* o) {
    const std::int64_t R = im.rings, cells = im.sectors * R;
    const float* quads = im.quads;
    const __m256 zero = _mm256_setzero_ps();
    const __m256 ring_lim = _mm256_set1_ps(lim.ring), sector_lim = _mm256_set1_ps(lim.sector);
    const __m256i rq = _mm256_set1_epi32(static_cast<std::int32_t>(im.rows - 1));
    for (std::int64_t s = 0; s < im.sectors; ++s) {
        const float* ring = places + s * R;
        const float* sector = places + cells + s * R;
        float* out = o + s * im.rings_padded;
        std::int64_t c = 0;
        for (; c + 8 <= R; c += 8) {
            ahead(ring + c);
            ahead(sector + c);
            const __m256 rf = _mm256_loadu_ps(ring + c);
            const __m256 sf = _mm256_loadu_ps(sector + c);
            const __m256 ok = _mm256_and_ps(
                _mm256_and_ps(_mm256_cmp_ps(rf, zero, _CMP_GE_OQ),
                              _mm256_cmp_ps(rf, ring_lim, _CMP_LT_OQ)),
                _mm256_and_ps(_mm256_cmp_ps(sf, zero, _CMP_GE_OQ),
                              _mm256_cmp_ps(sf, sector_lim, _CMP_LT_OQ)));
            if (_mm256_movemask_ps(ok) != 0xFF) outside("recentre_curves");
            const __m256i r0 = _mm256_cvttps_epi32(rf);
            const __m256i s0 = _mm256_cvttps_epi32(sf);
            const __m256 fr = _mm256_sub_ps(rf, _mm256_cvtepi32_ps(r0));
            const __m256 fs = _mm256_sub_ps(sf, _mm256_cvtepi32_ps(s0));
            const __m256i k =
                _mm256_slli_epi32(_mm256_add_epi32(_mm256_mullo_epi32(s0, rq), r0), 2);
            // The offsets two at a time, as 64 bits (one move each, where a 32-bit
            // extract is two operations), split in integer registers: 10 % faster.
            const __m128i lo = _mm256_castsi256_si128(k), hi = _mm256_extracti128_si256(k, 1);
            const std::uint64_t l01 = static_cast<std::uint64_t>(_mm_cvtsi128_si64(lo));
            const std::uint64_t l23 = static_cast<std::uint64_t>(_mm_extract_epi64(lo, 1));
            const std::uint64_t h01 = static_cast<std::uint64_t>(_mm_cvtsi128_si64(hi));
            const std::uint64_t h23 = static_cast<std::uint64_t>(_mm_extract_epi64(hi, 1));
            const auto pair = [quads](std::uint64_t a, std::uint64_t b) {  // cells a | b
                return _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(quads + a)),
                                            _mm_loadu_ps(quads + b), 1);
            };
            const __m256 q0 = pair(l01 & 0xFFFFFFFFu, h01 & 0xFFFFFFFFu);
            const __m256 q1 = pair(l01 >> 32, h01 >> 32);
            const __m256 q2 = pair(l23 & 0xFFFFFFFFu, h23 & 0xFFFFFFFFu);
            const __m256 q3 = pair(l23 >> 32, h23 >> 32);
            const __m256 t0 = _mm256_unpacklo_ps(q0, q1), t1 = _mm256_unpackhi_ps(q0, q1);
            const __m256 t2 = _mm256_unpacklo_ps(q2, q3), t3 = _mm256_unpackhi_ps(q2, q3);
            const __m256d d0 = _mm256_castps_pd(t0), d1 = _mm256_castps_pd(t1);
            const __m256d d2 = _mm256_castps_pd(t2), d3 = _mm256_castps_pd(t3);
            const __m256 a0 = _mm256_castpd_ps(_mm256_unpacklo_pd(d0, d2));
            const __m256 a1 = _mm256_castpd_ps(_mm256_unpackhi_pd(d0, d2));
            const __m256 b0 = _mm256_castpd_ps(_mm256_unpacklo_pd(d1, d3));
            const __m256 b1 = _mm256_castpd_ps(_mm256_unpackhi_pd(d1, d3));
            const __m256 near = _mm256_add_ps(a0, _mm256_mul_ps(_mm256_sub_ps(a1, a0), fs));
            const __m256 far = _mm256_add_ps(b0, _mm256_mul_ps(_mm256_sub_ps(b1, b0), fs));
            _mm256_storeu_ps(out + c,
                             _mm256_add_ps(near, _mm256_mul_ps(_mm256_sub_ps(far, near), fr)));
        }
        resample_cells(im, ring, sector, c, R, lim, out);
    }
}
#include "disco/sector_fft.inc"
// The spectra of a vector of rings, `rings` of them not padding.
static inline void rfft_block(const SectorPlan& plan, const float* in, std::int64_t in_stride,
                              float* re, float* im, std::int64_t out_stride, float* work,
                              std::int64_t) {
    rfft_lanes(plan, in, in_stride, re, im, out_stride, work);
}
#include "disco/recentre_curves.inc"
#undef DISCO_LANES
}  // namespace avx2
#pragma GCC pop_options

#pragma GCC push_options
#pragma GCC target("avx512f")
#pragma GCC diagnostic push
// GCC 12 warns inside its own avx512fintrin.h (_mm512_undefined_*): a false positive.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
namespace avx512 {
#define DISCO_LANES 16
#include "disco/simd_lanes.inc"
// tree16_scalar's halves in registers.
static inline float tree16(const vf* v) {
    const __m512 x = (__m512)v[0];
    const __m256 h8 = _mm256_add_ps(
        _mm512_castps512_ps256(x),
        _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(x), 1)));
    const __m128 h4 = _mm_add_ps(_mm256_castps256_ps128(h8), _mm256_extractf128_ps(h8, 1));
    const __m128 h2 = _mm_add_ps(h4, _mm_movehl_ps(h4, h4));
    return _mm_cvtss_f32(_mm_add_ss(h2, _mm_shuffle_ps(h2, h2, 1)));
}
// The AVX2 reads: on Zen 4 (AVX-512 in two halves) the 512-bit ones, with twice the
// shuffles per instruction, were 15 % slower.
static inline void resample_view(const RecentreImage& im, const float* places, Limits lim,
                                 float* o) {
    avx2::resample_view(im, places, lim, o);
}
#include "disco/sector_fft.inc"
// The spectra of a vector of rings, `rings` of them not padding: eight or fewer (the
// last of 40) as AVX2's eight lanes, the same values in half the work.
static inline void rfft_block(const SectorPlan& plan, const float* in, std::int64_t in_stride,
                              float* re, float* im, std::int64_t out_stride, float* work,
                              std::int64_t rings) {
    if (rings <= 8)
        avx2::rfft_lanes(plan, in, in_stride, re, im, out_stride, work);
    else
        rfft_lanes(plan, in, in_stride, re, im, out_stride, work);
}
#include "disco/recentre_curves.inc"
#undef DISCO_LANES
}  // namespace avx512
#undef DISCO_TREE16_SCALAR
#pragma GCC diagnostic pop
#pragma GCC pop_options
#endif

}  // namespace

void recentre_table(const float* padded, std::int64_t rows, std::int64_t width, float* quads) {
    for (std::int64_t s = 0; s + 1 < width; ++s)
        for (std::int64_t r = 0; r + 1 < rows; ++r) {
            const float* p = padded + r * width + s;
            float* q = quads + (s * (rows - 1) + r) * 4;
            q[0] = p[0], q[1] = p[1], q[2] = p[width], q[3] = p[width + 1];
        }
}

namespace {

void check(const RecentreImage& image) {
    if (image.rings < 1 || image.sectors < 1 || image.rings_padded < image.rings ||
        image.rings_padded % 16 != 0 || image.width < 2 || image.rows < 2 ||
        (image.rows - 1) * (image.width - 1) * 4 >= (std::int64_t{1} << 31))
        throw std::invalid_argument(
            "recentre_curves: rings and sectors >= 1, rings_padded a multiple of 16 >= rings, "
            "a table of at least 2 x 2 and under 2^31 floats");
}

}  // namespace

double recentre_ncc(const RecentreImage& image, const float* places,
                    const float* match_sectors, std::int64_t shift) {
    check(image);
    const std::int64_t R = image.rings, S = image.sectors, n = R * S;
    const Limits lim = Limits::of(image.rows, image.width);
    std::vector<float> view(static_cast<std::size_t>(n));
    RecentreImage dense = image;
    dense.rings_padded = R;  // the view written [S][R]
#if DISCO_SIMD_X86
    if (sector_fft_level() >= 2)
        avx2::resample_view(dense, places, lim, view.data());
    else
#endif
        resample_plain(dense, places, lim, view.data());
    // Sums over the cells in four lanes (ring r in lane r mod 4; SSE2 pairs), then the
    // lanes in order: the same values at every level, and short chains of additions.
    typedef double v2d __attribute__((vector_size(16)));
    v2d acc[5][2] = {};  // sum v, sum m, sum v v, sum m m, sum v m; lanes (0, 1), (2, 3)
    double tail[5][4] = {};
    shift = ((shift % S) + S) % S;
    for (std::int64_t s = 0; s < S; ++s) {
        const float* v = view.data() + s * R;
        const float* m = match_sectors + ((s - shift + S) % S) * R;  // under view sector s
        std::int64_t r = 0;
        for (; r + 4 <= R; r += 4)
            for (int h = 0; h < 2; ++h) {
                const v2d a = {v[r + 2 * h], v[r + 2 * h + 1]};
                const v2d b = {m[r + 2 * h], m[r + 2 * h + 1]};
                acc[0][h] += a, acc[1][h] += b, acc[2][h] += a * a, acc[3][h] += b * b;
                acc[4][h] += a * b;
            }
        for (; r < R; ++r) {
            const double a = v[r], b = m[r];
            const std::int64_t l = r % 4;
            tail[0][l] += a, tail[1][l] += b, tail[2][l] += a * a, tail[3][l] += b * b;
            tail[4][l] += a * b;
        }
    }
    double sum[5];
    for (int q = 0; q < 5; ++q)
        sum[q] = (((acc[q][0][0] + tail[q][0]) + (acc[q][0][1] + tail[q][1])) +
                  (acc[q][1][0] + tail[q][2])) + (acc[q][1][1] + tail[q][3]);
    const double tv = sum[0], tm = sum[1], tvv = sum[2], tmm = sum[3], tvm = sum[4];
    // Centred: sum (v - v_mean)(m - m_mean) = sum v m - n v_mean m_mean, and so on.
    const double N = static_cast<double>(n), mv = tv / N, mt = tm / N;
    const double ab = tvm - N * mv * mt;
    const double aa = std::max(tvv - N * mv * mv, 0.0), bb = std::max(tmm - N * mt * mt, 0.0);
    const double norm = std::sqrt(aa) * std::sqrt(bb);
    return norm > 0.0 ? ab / norm : 0.0;
}

void recentre_match(const RecentreImage& image, const float* match, float* spectrum) {
    check(image);
    switch (sector_fft_level()) {
#if DISCO_SIMD_X86
        case 3: return avx512::match_spectrum(image, match, spectrum);
        case 2: return avx2::match_spectrum(image, match, spectrum);
        case 1: return sse2::match_spectrum(image, match, spectrum);
#endif
        default: return plain::match_spectrum(image, match, spectrum);
    }
}

void recentre_curves(const RecentreImage& image, const std::vector<const float*>& places,
                     const float* spectrum, const float* weights, float* curves) {
    check(image);
    switch (sector_fft_level()) {
#if DISCO_SIMD_X86
        case 3: return avx512::run(image, places, spectrum, weights, curves);
        case 2: return avx2::run(image, places, spectrum, weights, curves);
        case 1: return sse2::run(image, places, spectrum, weights, curves);
#endif
        default: return plain::run(image, places, spectrum, weights, curves);
    }
}

}  // namespace disco
