// The polar BEV voxelizer. The definition (polar_bev.hpp) is in double precision;
// evaluating it per point (sqrt, two divisions, atan2 in double) would cost several
// times our budget, so each point takes a fast single-precision path with a
// polynomial atan2, and only a point that lands within a worst-case error margin of a
// cell edge (0.07-0.27% of the points of real scans) is redone with the exact double
// formulas. The result is therefore the double-precision definition, not an
// approximation of it.
#include "disco/polar_bev.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <type_traits>

#if defined(__SSE2__)
#include <emmintrin.h>
#define DISCO_BEV_SSE2 1
#if defined(__GNUC__) || defined(__clang__)
#include <immintrin.h>
#define DISCO_BEV_AVX2 1
#endif
#endif
#if defined(__aarch64__) && defined(__ARM_NEON)
#include <arm_neon.h>
#define DISCO_BEV_NEON 1  // Advanced SIMD is part of every aarch64 CPU
#endif

namespace disco {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kTwoPi = 2.0 * kPi;
// Unit roundoff of float: every float operation errs by at most this, relatively.
constexpr double kFloatEps = 5.9604644775390625e-08;
// Bound on |fast_angle - atan2| in radians: the polynomial is within 6e-7 rad of
// atan on [0, 1]; the rest covers the float reductions around it.
constexpr double kAngleErr = 2e-6;
// Points are processed in chunks that fit in L1, so the fast path vectorizes.
constexpr int kChunk = 256;
constexpr int32_t kDrop = -1;   // the point is surely outside the grid
constexpr int32_t kExact = -2;  // too close to an edge to trust the fast path

// atan(t) ~= t * P(t^2) on [0, 1]: a Chebyshev fit of degree 6 in t^2 (fitted for
// this project; max error 5e-7 rad).
constexpr float kA0 = 0.9999993443489075f;
constexpr float kA1 = -0.3332637846469879f;
constexpr float kA2 = 0.19879889488220215f;
constexpr float kA3 = -0.13480456173419952f;
constexpr float kA4 = 0.08374223858118057f;
constexpr float kA5 = -0.03689904883503914f;
constexpr float kA6 = 0.007825573906302452f;

// The config turned into the constants both paths need.
struct Binning {
    int rings, sectors, heights;  // heights is 1 for max_height
    // exact path (double)
    double min_range, max_range, z_min, z_max, ring_w, sector_w, height_w;
    // fast path (float): scales to index units and error margins in index units
    float ring_scale, sector_scale, height_scale, z_min_f, ring_min;
    float ring_margin, sector_margin, height_margin;
    float rings_f, heights_f;
    // Bounds on the float x^2 + y^2 of a point that might be in the ring window.
    float r2_lo, r2_hi;
};

Binning make_binning(const BEVConfig& c) {
    Binning b{};
    b.rings = c.rings;
    b.sectors = c.sectors;
    b.heights = c.layers();
    b.min_range = c.min_range;
    b.max_range = c.max_range;
    b.z_min = c.z_min;
    b.z_max = c.z_max;
    b.ring_w = c.max_range / c.rings;
    b.sector_w = kTwoPi / c.sectors;
    b.height_w = (c.z_max - c.z_min) / b.heights;

    b.ring_scale = static_cast<float>(c.rings / c.max_range);
    b.sector_scale = static_cast<float>(c.sectors / kTwoPi);
    b.height_scale = static_cast<float>(b.heights / (c.z_max - c.z_min));
    b.z_min_f = static_cast<float>(c.z_min);
    b.ring_min = static_cast<float>(c.min_range / b.ring_w);
    b.rings_f = static_cast<float>(c.rings);
    b.heights_f = static_cast<float>(b.heights);
    // Each margin is >= 4x the worst float error of that index (a handful of
    // roundings, each kFloatEps relative, on values up to the grid size).
    const double eps = kFloatEps;
    b.ring_margin = static_cast<float>(32.0 * eps * (c.rings + 2.0));
    b.sector_margin =
        static_cast<float>(4.0 * kAngleErr * c.sectors / kTwoPi + 32.0 * eps * (c.sectors + 2.0));
    const double z_abs = std::max(std::abs(c.z_min), std::abs(c.z_max)) + b.height_w;
    b.height_margin = static_cast<float>(
        32.0 * eps * ((2.0 * z_abs + (c.z_max - c.z_min)) / b.height_w + b.heights + 2.0));
    // The float x^2 + y^2 is within 1e-6 of the exact value, relatively (the float
    // conversions of x and y and two roundings: under 4 * kFloatEps), so these bounds,
    // 2e-5 outside the window, drop only points surely outside it. A low bound below
    // the normal floats (where the float product is no longer relatively exact) is 0.
    const double lo = c.min_range * (1.0 - 1e-5);
    b.r2_lo = lo * lo >= 1e-30 ? static_cast<float>(lo * lo) : 0.0f;
    const double hi = c.max_range * (1.0 + 1e-5);
    b.r2_hi = static_cast<float>(hi * hi);
    return b;
}

int clamp_index(double a, int n) {
    // a is finite and >= 0 here; the clamp catches a value that rounded up to n.
    return std::min(static_cast<int>(a), n - 1);
}

// The definition itself, in double: the flat cell index, or kDrop.
int32_t exact_cell(double x, double y, double z, const Binning& b) {
    if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) return kDrop;
    const double r = std::sqrt(x * x + y * y);
    if (!(r >= b.min_range && r < b.max_range)) return kDrop;
    if (!(z >= b.z_min && z < b.z_max)) return kDrop;
    double theta = std::atan2(y, x);
    if (theta < 0.0) theta += kTwoPi;
    const int ring = clamp_index(std::floor(r / b.ring_w), b.rings);
    const int sector = clamp_index(std::floor(theta / b.sector_w), b.sectors);
    const int height = clamp_index(std::floor((z - b.z_min) / b.height_w), b.heights);
    return (height * b.rings + ring) * b.sectors + sector;
}

// One index axis of the fast path: `a` is the value in index units, n the cell count.
// Returns i = trunc(a clamped into [-1, n]) as float (the clamp keeps the conversion
// defined), and sets ok where frac = a - i lies in (margin, 1 - margin): then, for
// a < n, i is the exact index. A negative or NaN `a` is never ok; an `a` above n may
// be, and the caller's drop test (which wins over ok) covers it. Selects only (no
// std::min, no branches), so that compilers vectorize the loop that inlines it.
inline float fast_index(float a, float n, float margin, bool& ok) {
    float c = a > -1.0f ? a : -1.0f;
    c = c < n ? c : n;
    const float i = static_cast<float>(static_cast<int32_t>(c));
    const float frac = a - i;
    ok = (frac > margin) & (frac < 1.0f - margin);
    return i;
}

// Fast path over one chunk of deinterleaved coordinates: a cell index, kDrop or
// kExact per point. The plain kernel (level 0) and the tail of every SIMD kernel:
// portable C++ that GCC and Clang vectorize for the baseline of any target (SSE2,
// NEON), with the same polynomial and margins as the intrinsics kernels.
//
// Two passes over the chunk, each a short chain of dependent operations: in one
// loop, the chain from a point's coordinates to its code is long enough that the
// CPU's scheduler fills with waiting work and its units idle. The first pass
// overwrites xs, ys, zs with the coordinates in index units (ring, sector, height).
// `Small`: the grid has < 2^24 cells, so the cell index can be formed in float
// (cheaper than 32-bit integer products, which SSE2 lacks).
template <bool Small>
void fast_codes_plain(float* __restrict xs, float* __restrict ys, float* __restrict zs, int n,
                      const Binning& bin, int32_t* __restrict codes) {
    const float half_pi = static_cast<float>(kPi / 2.0);
    const float pi = static_cast<float>(kPi);
    const float two_pi = static_cast<float>(kTwoPi);
    // Locals, so that the loops hold them in registers (codes might alias `bin`).
    const float ring_scale = bin.ring_scale, sector_scale = bin.sector_scale;
    const float height_scale = bin.height_scale, z_min = bin.z_min_f;
    for (int i = 0; i < n; ++i) {
        const float x = xs[i];
        const float y = ys[i];
        const float z = zs[i];
        // atan2 by octant: t = min/max in [0, 1], atan(t) by polynomial (Estrin, as the
        // SIMD kernels), then unfold.
        const float ax = std::fabs(x);
        const float ay = std::fabs(y);
        const bool steep = ay > ax;
        const float t = (steep ? ax : ay) / (steep ? ay : ax);
        const float u = t * t;
        const float u2 = u * u;
        const float u4 = u2 * u2;
        const float q01 = kA1 * u + kA0;
        const float q23 = kA3 * u + kA2;
        const float q456 = kA6 * u2 + (kA5 * u + kA4);
        const float p = (q456 * u4 + (q23 * u2 + q01)) * t;
        // Unfold as offset + (+-value): selects of constants and a sign flip, which
        // compilers if-convert (GCC will not if-convert "c ? k - v : v", as the
        // subtraction might trap). k + (-v) is exactly k - v, and 0 + v is v.
        const float theta1 = (steep ? half_pi : 0.0f) + (steep ? -p : p);
        const bool left = x < 0.0f;
        const float theta2 = (left ? pi : 0.0f) + (left ? -theta1 : theta1);
        const bool below = y < 0.0f;
        const float theta = (below ? two_pi : 0.0f) + (below ? -theta2 : theta2);
        xs[i] = std::sqrt(x * x + y * y) * ring_scale;
        ys[i] = theta * sector_scale;
        zs[i] = (z - z_min) * height_scale;
    }

    const float rings_f = bin.rings_f, heights_f = bin.heights_f;
    const float sectors_f = static_cast<float>(bin.sectors);
    const float ring_margin = bin.ring_margin, sector_margin = bin.sector_margin;
    const float height_margin = bin.height_margin;
    const float ring_lo = bin.ring_min - ring_margin, ring_hi = bin.ring_min + ring_margin;
    const float ring_out = rings_f + ring_margin, height_out = heights_f + height_margin;
    const auto rings = static_cast<uint32_t>(bin.rings);
    const auto sectors = static_cast<uint32_t>(bin.sectors);
    for (int i = 0; i < n; ++i) {
        const float a_ring = xs[i];
        const float a_sector = ys[i];
        const float a_height = zs[i];
        // A drop wins over ok, so no axis needs a test against its top edge: a value
        // at n or within the margin above it is not ok, and beyond that it is dropped
        // (theta <= 2 pi up to float error, so a_sector is never beyond it).
        bool ok_ring, ok_sector, ok_height;
        const float ring = fast_index(a_ring, rings_f, ring_margin, ok_ring);
        const float sector = fast_index(a_sector, sectors_f, sector_margin, ok_sector);
        const float height = fast_index(a_height, heights_f, height_margin, ok_height);
        const bool ok = ok_ring & ok_sector & ok_height & (a_ring > ring_hi);
        const bool drop = (a_ring < ring_lo) | (a_ring > ring_out) | (a_height < -height_margin) |
                          (a_height > height_out);
        int32_t cell;
        if constexpr (Small) {
            cell = static_cast<int32_t>((height * rings_f + ring) * sectors_f + sector);
        } else {
            // Unsigned: a lane that is not ok may hold -1 or n, and must not overflow.
            const auto h = static_cast<uint32_t>(static_cast<int32_t>(height));
            const auto r = static_cast<uint32_t>(static_cast<int32_t>(ring));
            const auto s = static_cast<uint32_t>(static_cast<int32_t>(sector));
            cell = static_cast<int32_t>((h * rings + r) * sectors + s);
        }
        // ok ? cell : kExact, then kDrop (all ones) where surely outside, by masks:
        // a select here would let GCC move the conversion into a branch, which it
        // then will not vectorize.
        const int32_t ok_mask = -static_cast<int32_t>(ok);
        const int32_t drop_mask = -static_cast<int32_t>(drop);
        codes[i] = (cell & ok_mask) | (kExact & ~ok_mask) | drop_mask;
    }
}

// The plain kernel over one chunk, skipping what is surely dropped: a cheap first
// pass marks the points that might be in the grid (r^2 and height windows, NaN out),
// the groups of kGroup points with at least one such point are moved to the front,
// and only those take the square root and polynomial of fast_codes_plain. Scans
// come in sensor order, so the points out of the window (mostly ground, under z_min)
// come in long runs, and nearly all of them fall in whole groups that are skipped.
// Returns the number of groups kept: codes[k * kGroup + l] is the code of point
// where[k] * kGroup + l (points past n have codes too, to be ignored).
constexpr int kGroup = 4;

template <bool Small>
int fast_codes_plain_skip(float* __restrict xs, float* __restrict ys, float* __restrict zs,
                          int n, const Binning& bin, int32_t* __restrict codes,
                          int32_t* __restrict where) {
    const int groups = (n + kGroup - 1) / kGroup;
    for (int i = n; i < groups * kGroup; ++i) xs[i] = ys[i] = zs[i] = 0.0f;
    const float r2_lo = bin.r2_lo, r2_hi = bin.r2_hi;
    const float height_scale = bin.height_scale, z_min = bin.z_min_f;
    const float height_lo = -bin.height_margin, height_hi = bin.heights_f + bin.height_margin;
    alignas(64) int32_t keep[kChunk];
    for (int i = 0; i < groups * kGroup; ++i) {
        const float x = xs[i];
        const float y = ys[i];
        // The drop test of fast_codes_plain for the height, the same expression; for
        // the ring, bounds on r^2 (see make_binning). NaN fails every comparison.
        const float r2 = x * x + y * y;
        const float a_height = (zs[i] - z_min) * height_scale;
        keep[i] = (r2 >= r2_lo) & (r2 <= r2_hi) & (a_height >= height_lo) &
                  (a_height <= height_hi);
    }
    int kept = 0;
    for (int g = 0; g < groups; ++g) {
        int32_t any = 0;
        for (int l = 0; l < kGroup; ++l) any |= keep[g * kGroup + l];
        // In place (the destination group is never after the source): memmove of a
        // constant size is one vector load and store.
        std::memmove(xs + kept * kGroup, xs + g * kGroup, sizeof(float) * kGroup);
        std::memmove(ys + kept * kGroup, ys + g * kGroup, sizeof(float) * kGroup);
        std::memmove(zs + kept * kGroup, zs + g * kGroup, sizeof(float) * kGroup);
        where[kept] = g;
        kept += any;
    }
    fast_codes_plain<Small>(xs, ys, zs, kept * kGroup, bin, codes);
    return kept;
}

// The tails of the SIMD kernels: fewer than 16 points, always on a small grid.
void fast_codes(const float* xs, const float* ys, const float* zs, int n, const Binning& b,
                int32_t* codes) {
    float x[16], y[16], z[16];
    for (int i = 0; i < n; ++i) {
        x[i] = xs[i];
        y[i] = ys[i];
        z[i] = zs[i];
    }
    fast_codes_plain<true>(x, y, z, n, b, codes);
}

// The SIMD kernels skip as fast_codes_plain_skip does, a vector at a time: one whose
// points all fail the cheap window test gets no codes. The tail, rows [i, n) with i
// a multiple of kGroup, is coded whole: the groups it covers are appended to where.
#if DISCO_BEV_SSE2 || DISCO_BEV_NEON
int append_tail(int i, int n, int kept, int32_t* where) {
    for (int g = i / kGroup; g * kGroup < n; ++g) where[kept++] = g;
    return kept;
}
#endif

#if DISCO_BEV_SSE2
// The fast path on four points at once (SSE2, the x86-64 baseline): the same
// arithmetic as fast_codes, lane by lane, with the cell index formed in float
// (exact because the grid has < 2^24 cells when this is used).
struct SimdBinning {
    __m128 ring_scale, sector_scale, height_scale, z_min;
    __m128 ring_lo, ring_hi, ring_max_out, height_lo_out, height_max_out;
    __m128 rings, sectors, heights;
    __m128 ring_margin, ring_margin_hi, sector_margin, sector_margin_hi, height_margin,
        height_margin_hi;
    __m128 r2_lo, r2_hi;

    explicit SimdBinning(const Binning& b)
        : ring_scale(_mm_set1_ps(b.ring_scale)),
          sector_scale(_mm_set1_ps(b.sector_scale)),
          height_scale(_mm_set1_ps(b.height_scale)),
          z_min(_mm_set1_ps(b.z_min_f)),
          ring_lo(_mm_set1_ps(b.ring_min - b.ring_margin)),
          ring_hi(_mm_set1_ps(b.ring_min + b.ring_margin)),
          ring_max_out(_mm_set1_ps(b.rings_f + b.ring_margin)),
          height_lo_out(_mm_set1_ps(-b.height_margin)),
          height_max_out(_mm_set1_ps(b.heights_f + b.height_margin)),
          rings(_mm_set1_ps(b.rings_f)),
          sectors(_mm_set1_ps(static_cast<float>(b.sectors))),
          heights(_mm_set1_ps(b.heights_f)),
          ring_margin(_mm_set1_ps(b.ring_margin)),
          ring_margin_hi(_mm_set1_ps(1.0f - b.ring_margin)),
          sector_margin(_mm_set1_ps(b.sector_margin)),
          sector_margin_hi(_mm_set1_ps(1.0f - b.sector_margin)),
          height_margin(_mm_set1_ps(b.height_margin)),
          height_margin_hi(_mm_set1_ps(1.0f - b.height_margin)),
          r2_lo(_mm_set1_ps(b.r2_lo)),
          r2_hi(_mm_set1_ps(b.r2_hi)) {}
};

// Whether any of the four points might be in the grid: the window test of
// fast_codes_plain_skip.
inline bool any4(__m128 x, __m128 y, __m128 z, const SimdBinning& s) {
    const __m128 r2 = _mm_add_ps(_mm_mul_ps(x, x), _mm_mul_ps(y, y));
    const __m128 a_height = _mm_mul_ps(_mm_sub_ps(z, s.z_min), s.height_scale);
    const __m128 keep =
        _mm_and_ps(_mm_and_ps(_mm_cmpge_ps(r2, s.r2_lo), _mm_cmple_ps(r2, s.r2_hi)),
                   _mm_and_ps(_mm_cmpge_ps(a_height, s.height_lo_out),
                              _mm_cmple_ps(a_height, s.height_max_out)));
    return _mm_movemask_ps(keep) != 0;
}

inline __m128 select4(__m128 mask, __m128 a, __m128 b) {
    return _mm_or_ps(_mm_and_ps(mask, a), _mm_andnot_ps(mask, b));
}

// floor(a) clamped into [0, n] as float, and the mask of lanes where it is certain.
inline __m128 index4(__m128 a, __m128 n, __m128 margin, __m128 margin_hi, __m128& ok) {
    const __m128 clamped = _mm_min_ps(_mm_max_ps(a, _mm_setzero_ps()), n);  // NaN -> 0
    const __m128 i = _mm_cvtepi32_ps(_mm_cvttps_epi32(clamped));
    const __m128 frac = _mm_sub_ps(a, i);
    ok = _mm_and_ps(_mm_cmplt_ps(a, n),
                    _mm_and_ps(_mm_cmpgt_ps(frac, margin), _mm_cmplt_ps(frac, margin_hi)));
    return i;
}

inline __m128i codes4(__m128 x, __m128 y, __m128 z, const SimdBinning& s) {
    const __m128 zero = _mm_setzero_ps();
    const __m128 a_ring =
        _mm_mul_ps(_mm_sqrt_ps(_mm_add_ps(_mm_mul_ps(x, x), _mm_mul_ps(y, y))), s.ring_scale);
    const __m128 a_height = _mm_mul_ps(_mm_sub_ps(z, s.z_min), s.height_scale);

    const __m128 abs_mask = _mm_castsi128_ps(_mm_set1_epi32(0x7fffffff));
    const __m128 ax = _mm_and_ps(x, abs_mask);
    const __m128 ay = _mm_and_ps(y, abs_mask);
    const __m128 t = _mm_div_ps(_mm_min_ps(ax, ay), _mm_max_ps(ax, ay));
    const __m128 u = _mm_mul_ps(t, t);
    // Estrin's scheme (shorter dependency chain than Horner's).
    const __m128 u2 = _mm_mul_ps(u, u);
    const __m128 u4 = _mm_mul_ps(u2, u2);
    const __m128 q01 = _mm_add_ps(_mm_mul_ps(_mm_set1_ps(kA1), u), _mm_set1_ps(kA0));
    const __m128 q23 = _mm_add_ps(_mm_mul_ps(_mm_set1_ps(kA3), u), _mm_set1_ps(kA2));
    const __m128 q45 = _mm_add_ps(_mm_mul_ps(_mm_set1_ps(kA5), u), _mm_set1_ps(kA4));
    const __m128 q456 = _mm_add_ps(_mm_mul_ps(_mm_set1_ps(kA6), u2), q45);
    const __m128 q0123 = _mm_add_ps(_mm_mul_ps(q23, u2), q01);
    const __m128 p = _mm_mul_ps(_mm_add_ps(_mm_mul_ps(q456, u4), q0123), t);
    __m128 theta =
        select4(_mm_cmpgt_ps(ay, ax), _mm_sub_ps(_mm_set1_ps(static_cast<float>(kPi / 2.0)), p), p);
    theta = select4(_mm_cmplt_ps(x, zero), _mm_sub_ps(_mm_set1_ps(static_cast<float>(kPi)), theta),
                    theta);
    theta = select4(_mm_cmplt_ps(y, zero),
                    _mm_sub_ps(_mm_set1_ps(static_cast<float>(kTwoPi)), theta), theta);
    const __m128 a_sector = _mm_mul_ps(theta, s.sector_scale);

    __m128 ok_ring, ok_sector, ok_height;
    const __m128 ring = index4(a_ring, s.rings, s.ring_margin, s.ring_margin_hi, ok_ring);
    const __m128 sector =
        index4(a_sector, s.sectors, s.sector_margin, s.sector_margin_hi, ok_sector);
    const __m128 height =
        index4(a_height, s.heights, s.height_margin, s.height_margin_hi, ok_height);
    const __m128 ok = _mm_and_ps(_mm_and_ps(ok_ring, _mm_cmpgt_ps(a_ring, s.ring_hi)),
                                 _mm_and_ps(ok_sector, ok_height));
    const __m128 drop =
        _mm_or_ps(_mm_or_ps(_mm_cmplt_ps(a_ring, s.ring_lo), _mm_cmpgt_ps(a_ring, s.ring_max_out)),
                  _mm_or_ps(_mm_cmplt_ps(a_height, s.height_lo_out),
                            _mm_cmpgt_ps(a_height, s.height_max_out)));
    const __m128 cell_f =
        _mm_add_ps(_mm_mul_ps(_mm_add_ps(_mm_mul_ps(height, s.rings), ring), s.sectors), sector);
    const __m128i cell = _mm_cvttps_epi32(cell_f);
    // Not certain: kDrop (-1) where surely outside, else kExact (-2).
    const __m128i other = _mm_sub_epi32(_mm_set1_epi32(kExact), _mm_castps_si128(drop));
    const __m128i okm = _mm_castps_si128(ok);
    return _mm_or_si128(_mm_and_si128(okm, cell), _mm_andnot_si128(okm, other));
}

// Deinterleaved coordinates.
int fast_codes_simd(const float* xs, const float* ys, const float* zs, int n, const Binning& b,
                    const SimdBinning& s, int32_t* codes, int32_t* where) {
    int i = 0, kept = 0;
    for (; i + 4 <= n; i += 4) {
        const __m128 x = _mm_load_ps(xs + i), y = _mm_load_ps(ys + i), z = _mm_load_ps(zs + i);
        if (!any4(x, y, z, s)) continue;
        _mm_store_si128(reinterpret_cast<__m128i*>(codes + kGroup * kept), codes4(x, y, z, s));
        where[kept++] = i / kGroup;
    }
    if (i < n) fast_codes(xs + i, ys + i, zs + i, n - i, b, codes + kGroup * kept);
    return append_tail(i, n, kept, where);
}

// Packed x, y, z, w float rows (the KITTI layout), read in place.
int fast_codes_xyzw(const float* rows, int n, const Binning& b, const SimdBinning& s,
                    int32_t* codes, int32_t* where) {
    int i = 0, kept = 0;
    for (; i + 4 <= n; i += 4) {
        __m128 p0 = _mm_loadu_ps(rows + 4 * i);
        __m128 p1 = _mm_loadu_ps(rows + 4 * i + 4);
        __m128 p2 = _mm_loadu_ps(rows + 4 * i + 8);
        __m128 p3 = _mm_loadu_ps(rows + 4 * i + 12);
        _MM_TRANSPOSE4_PS(p0, p1, p2, p3);  // now x, y, z, w
        if (!any4(p0, p1, p2, s)) continue;
        _mm_store_si128(reinterpret_cast<__m128i*>(codes + kGroup * kept), codes4(p0, p1, p2, s));
        where[kept++] = i / kGroup;
    }
    for (int j = i; j < n; ++j) {
        const float* r = rows + 4 * j;
        fast_codes(r, r + 1, r + 2, 1, b, codes + kGroup * kept + (j - i));
    }
    return append_tail(i, n, kept, where);
}
#endif

#if DISCO_BEV_AVX2
// The same fast path on eight points at once, for CPUs with AVX2 and FMA (chosen at
// run time; the build itself targets the x86-64 baseline). FMA only makes the
// float values more accurate, and the margins cover either way.
#define DISCO_AVX2_FMA __attribute__((target("avx2,fma")))

DISCO_AVX2_FMA inline __m256 select8(__m256 mask, __m256 a, __m256 b) {
    return _mm256_blendv_ps(b, a, mask);
}

// The constants of codes8, broadcast once per chunk (held in registers, not
// reloaded from a Binning that the compiler must assume the code stores alias).
struct Binning8 {
    __m256 ring_scale, sector_scale, height_scale, z_min;
    __m256 ring_lo, ring_hi, ring_max_out, height_lo_out, height_max_out;
    __m256 rings, sectors, heights;
    __m256 ring_margin, ring_margin_hi, sector_margin, sector_margin_hi, height_margin,
        height_margin_hi;
    __m256 r2_lo, r2_hi;

    DISCO_AVX2_FMA explicit Binning8(const Binning& b)
        : ring_scale(_mm256_set1_ps(b.ring_scale)),
          sector_scale(_mm256_set1_ps(b.sector_scale)),
          height_scale(_mm256_set1_ps(b.height_scale)),
          z_min(_mm256_set1_ps(b.z_min_f)),
          ring_lo(_mm256_set1_ps(b.ring_min - b.ring_margin)),
          ring_hi(_mm256_set1_ps(b.ring_min + b.ring_margin)),
          ring_max_out(_mm256_set1_ps(b.rings_f + b.ring_margin)),
          height_lo_out(_mm256_set1_ps(-b.height_margin)),
          height_max_out(_mm256_set1_ps(b.heights_f + b.height_margin)),
          rings(_mm256_set1_ps(b.rings_f)),
          sectors(_mm256_set1_ps(static_cast<float>(b.sectors))),
          heights(_mm256_set1_ps(b.heights_f)),
          ring_margin(_mm256_set1_ps(b.ring_margin)),
          ring_margin_hi(_mm256_set1_ps(1.0f - b.ring_margin)),
          sector_margin(_mm256_set1_ps(b.sector_margin)),
          sector_margin_hi(_mm256_set1_ps(1.0f - b.sector_margin)),
          height_margin(_mm256_set1_ps(b.height_margin)),
          height_margin_hi(_mm256_set1_ps(1.0f - b.height_margin)),
          r2_lo(_mm256_set1_ps(b.r2_lo)),
          r2_hi(_mm256_set1_ps(b.r2_hi)) {}
};

// Whether any of the eight points might be in the grid (see any4).
DISCO_AVX2_FMA inline bool any8(__m256 x, __m256 y, __m256 z, const Binning8& s) {
    const __m256 r2 = _mm256_add_ps(_mm256_mul_ps(x, x), _mm256_mul_ps(y, y));
    const __m256 a_height = _mm256_mul_ps(_mm256_sub_ps(z, s.z_min), s.height_scale);
    const __m256 keep =
        _mm256_and_ps(_mm256_and_ps(_mm256_cmp_ps(r2, s.r2_lo, _CMP_GE_OQ),
                                    _mm256_cmp_ps(r2, s.r2_hi, _CMP_LE_OQ)),
                      _mm256_and_ps(_mm256_cmp_ps(a_height, s.height_lo_out, _CMP_GE_OQ),
                                    _mm256_cmp_ps(a_height, s.height_max_out, _CMP_LE_OQ)));
    return _mm256_movemask_ps(keep) != 0;
}

// trunc(a) and the mask of lanes where it is certainly the cell index. No clamp is
// needed: a negative, NaN or huge `a` gives frac <= 0 or NaN, so the lane is not ok,
// and a lane with a too large is dropped (codes8 lets drop win over ok).
DISCO_AVX2_FMA inline __m256 index8(__m256 a, __m256 margin, __m256 margin_hi, __m256& ok) {
    const __m256 i = _mm256_round_ps(a, _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
    const __m256 frac = _mm256_sub_ps(a, i);
    ok = _mm256_and_ps(_mm256_cmp_ps(frac, margin, _CMP_GT_OQ),
                       _mm256_cmp_ps(frac, margin_hi, _CMP_LT_OQ));
    return i;
}

DISCO_AVX2_FMA inline __m256i codes8(__m256 x, __m256 y, __m256 z, const Binning8& s) {
    const __m256 r2 = _mm256_fmadd_ps(x, x, _mm256_mul_ps(y, y));
    const __m256 a_ring = _mm256_mul_ps(_mm256_sqrt_ps(r2), s.ring_scale);
    const __m256 a_height = _mm256_mul_ps(_mm256_sub_ps(z, s.z_min), s.height_scale);

    const __m256 abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
    const __m256 ax = _mm256_and_ps(x, abs_mask);
    const __m256 ay = _mm256_and_ps(y, abs_mask);
    const __m256 t = _mm256_div_ps(_mm256_min_ps(ax, ay), _mm256_max_ps(ax, ay));
    const __m256 u = _mm256_mul_ps(t, t);
    // Estrin's scheme: a shorter dependency chain than Horner's, so more points are
    // in flight at once.
    const __m256 u2 = _mm256_mul_ps(u, u);
    const __m256 u4 = _mm256_mul_ps(u2, u2);
    const __m256 q01 = _mm256_fmadd_ps(_mm256_set1_ps(kA1), u, _mm256_set1_ps(kA0));
    const __m256 q23 = _mm256_fmadd_ps(_mm256_set1_ps(kA3), u, _mm256_set1_ps(kA2));
    const __m256 q45 = _mm256_fmadd_ps(_mm256_set1_ps(kA5), u, _mm256_set1_ps(kA4));
    const __m256 q456 = _mm256_fmadd_ps(_mm256_set1_ps(kA6), u2, q45);
    const __m256 q0123 = _mm256_fmadd_ps(q23, u2, q01);
    const __m256 p = _mm256_mul_ps(_mm256_fmadd_ps(q456, u4, q0123), t);
    __m256 theta = select8(_mm256_cmp_ps(ay, ax, _CMP_GT_OQ),
                           _mm256_sub_ps(_mm256_set1_ps(static_cast<float>(kPi / 2.0)), p), p);
    // blendv reads only the sign bit, so x and y serve as their own masks (a -0.0
    // lands on an edge, which the margins send to the exact path).
    theta = select8(x, _mm256_sub_ps(_mm256_set1_ps(static_cast<float>(kPi)), theta), theta);
    theta = select8(y, _mm256_sub_ps(_mm256_set1_ps(static_cast<float>(kTwoPi)), theta), theta);
    const __m256 a_sector = _mm256_mul_ps(theta, s.sector_scale);

    __m256 ok_ring, ok_sector, ok_height;
    const __m256 ring = index8(a_ring, s.ring_margin, s.ring_margin_hi, ok_ring);
    // theta <= 2 pi (+ float error), so a_sector > sectors only right at the edge,
    // where frac < margin: no separate bound is needed.
    const __m256 sector = index8(a_sector, s.sector_margin, s.sector_margin_hi, ok_sector);
    const __m256 height = index8(a_height, s.height_margin, s.height_margin_hi, ok_height);
    const __m256 ring_in = _mm256_cmp_ps(a_ring, s.ring_hi, _CMP_GT_OQ);
    const __m256 ok =
        _mm256_and_ps(_mm256_and_ps(ok_ring, ring_in), _mm256_and_ps(ok_sector, ok_height));
    const __m256 drop =
        _mm256_or_ps(_mm256_or_ps(_mm256_cmp_ps(a_ring, s.ring_lo, _CMP_LT_OQ),
                                  _mm256_cmp_ps(a_ring, s.ring_max_out, _CMP_GT_OQ)),
                     _mm256_or_ps(_mm256_cmp_ps(a_height, s.height_lo_out, _CMP_LT_OQ),
                                  _mm256_cmp_ps(a_height, s.height_max_out, _CMP_GT_OQ)));
    const __m256 cell_f =
        _mm256_fmadd_ps(_mm256_fmadd_ps(height, s.rings, ring), s.sectors, sector);
    const __m256i cell = _mm256_cvttps_epi32(cell_f);
    // ok ? cell : kExact, then kDrop (all ones) wherever surely outside.
    const __m256i code =
        _mm256_blendv_epi8(_mm256_set1_epi32(kExact), cell, _mm256_castps_si256(ok));
    return _mm256_or_si256(code, _mm256_castps_si256(drop));
}

DISCO_AVX2_FMA int fast_codes_simd8(const float* xs, const float* ys, const float* zs, int n,
                                    const Binning& b, int32_t* codes, int32_t* where) {
    const Binning8 s(b);
    int i = 0, kept = 0;
    for (; i + 8 <= n; i += 8) {
        const __m256 x = _mm256_load_ps(xs + i), y = _mm256_load_ps(ys + i);
        const __m256 z = _mm256_load_ps(zs + i);
        if (!any8(x, y, z, s)) continue;
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(codes + kGroup * kept), codes8(x, y, z, s));
        where[kept++] = i / kGroup;
        where[kept++] = i / kGroup + 1;
    }
    if (i < n) fast_codes(xs + i, ys + i, zs + i, n - i, b, codes + kGroup * kept);
    return append_tail(i, n, kept, where);
}

DISCO_AVX2_FMA int fast_codes_xyzw8(const float* rows, int n, const Binning& b, int32_t* codes,
                                    int32_t* where) {
    // Lanes come out as points 0 2 4 6 | 1 3 5 7; this puts them back in order.
    const __m256i unshuffle = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    const Binning8 s(b);
    int i = 0, kept = 0;
    for (; i + 8 <= n; i += 8) {
        const float* r = rows + 4 * i;
        const __m256 a0 = _mm256_loadu_ps(r);            // p0 | p1
        const __m256 a1 = _mm256_loadu_ps(r + 8);        // p2 | p3
        const __m256 a2 = _mm256_loadu_ps(r + 16);       // p4 | p5
        const __m256 a3 = _mm256_loadu_ps(r + 24);       // p6 | p7
        const __m256 lo01 = _mm256_unpacklo_ps(a0, a1);  // x0 x2 y0 y2 | x1 x3 y1 y3
        const __m256 lo23 = _mm256_unpacklo_ps(a2, a3);  // x4 x6 y4 y6 | x5 x7 y5 y7
        const __m256 hi01 = _mm256_unpackhi_ps(a0, a1);  // z0 z2 w0 w2 | ...
        const __m256 hi23 = _mm256_unpackhi_ps(a2, a3);
        const __m256 x = _mm256_shuffle_ps(lo01, lo23, _MM_SHUFFLE(1, 0, 1, 0));
        const __m256 y = _mm256_shuffle_ps(lo01, lo23, _MM_SHUFFLE(3, 2, 3, 2));
        const __m256 z = _mm256_shuffle_ps(hi01, hi23, _MM_SHUFFLE(1, 0, 1, 0));
        if (!any8(x, y, z, s)) continue;
        const __m256i c = _mm256_permutevar8x32_epi32(codes8(x, y, z, s), unshuffle);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(codes + kGroup * kept), c);
        where[kept++] = i / kGroup;
        where[kept++] = i / kGroup + 1;
    }
    for (int j = i; j < n; ++j) {
        const float* r = rows + 4 * j;
        fast_codes(r, r + 1, r + 2, 1, b, codes + kGroup * kept + (j - i));
    }
    return append_tail(i, n, kept, where);
}
#endif

#if DISCO_BEV_AVX2
// Sixteen points at once with AVX-512 (F only), chosen at run time. Mask
// registers replace the blends, and one instruction covers twice the points, so
// more points are in flight in the out-of-order window, which is what limits
// the AVX2 kernel.
#define DISCO_AVX512 __attribute__((target("avx512f")))
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
// GCC 12 warns inside its own avx512fintrin.h (_mm512_undefined_ps): a false positive.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif

DISCO_AVX512 inline __mmask16 ok16(__m512 a, __m512& i, float margin) {
    i = _mm512_roundscale_ps(a, _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
    const __m512 frac = _mm512_sub_ps(a, i);
    const __mmask16 above = _mm512_cmp_ps_mask(frac, _mm512_set1_ps(margin), _CMP_GT_OQ);
    return _mm512_mask_cmp_ps_mask(above, frac, _mm512_set1_ps(1.0f - margin), _CMP_LT_OQ);
}

// Whether any of the sixteen points might be in the grid (see any4).
DISCO_AVX512 inline bool any16(__m512 x, __m512 y, __m512 z, const Binning& b) {
    const __m512 r2 = _mm512_add_ps(_mm512_mul_ps(x, x), _mm512_mul_ps(y, y));
    const __m512 a_height =
        _mm512_mul_ps(_mm512_sub_ps(z, _mm512_set1_ps(b.z_min_f)), _mm512_set1_ps(b.height_scale));
    const __mmask16 keep =
        _mm512_cmp_ps_mask(r2, _mm512_set1_ps(b.r2_lo), _CMP_GE_OQ) &
        _mm512_cmp_ps_mask(r2, _mm512_set1_ps(b.r2_hi), _CMP_LE_OQ) &
        _mm512_cmp_ps_mask(a_height, _mm512_set1_ps(-b.height_margin), _CMP_GE_OQ) &
        _mm512_cmp_ps_mask(a_height, _mm512_set1_ps(b.heights_f + b.height_margin), _CMP_LE_OQ);
    return keep != 0;
}

DISCO_AVX512 inline __m512i codes16(__m512 x, __m512 y, __m512 z, const Binning& b) {
    const __m512 r2 = _mm512_fmadd_ps(x, x, _mm512_mul_ps(y, y));
    const __m512 a_ring = _mm512_mul_ps(_mm512_sqrt_ps(r2), _mm512_set1_ps(b.ring_scale));
    const __m512 a_height =
        _mm512_mul_ps(_mm512_sub_ps(z, _mm512_set1_ps(b.z_min_f)), _mm512_set1_ps(b.height_scale));

    const __m512 ax = _mm512_abs_ps(x);
    const __m512 ay = _mm512_abs_ps(y);
    const __m512 t = _mm512_div_ps(_mm512_min_ps(ax, ay), _mm512_max_ps(ax, ay));
    const __m512 u = _mm512_mul_ps(t, t);
    const __m512 u2 = _mm512_mul_ps(u, u);
    const __m512 u4 = _mm512_mul_ps(u2, u2);
    const __m512 q01 = _mm512_fmadd_ps(_mm512_set1_ps(kA1), u, _mm512_set1_ps(kA0));
    const __m512 q23 = _mm512_fmadd_ps(_mm512_set1_ps(kA3), u, _mm512_set1_ps(kA2));
    const __m512 q45 = _mm512_fmadd_ps(_mm512_set1_ps(kA5), u, _mm512_set1_ps(kA4));
    const __m512 q456 = _mm512_fmadd_ps(_mm512_set1_ps(kA6), u2, q45);
    const __m512 q0123 = _mm512_fmadd_ps(q23, u2, q01);
    const __m512 p = _mm512_mul_ps(_mm512_fmadd_ps(q456, u4, q0123), t);
    const __m512 zero = _mm512_setzero_ps();
    __m512 theta = _mm512_mask_sub_ps(p, _mm512_cmp_ps_mask(ay, ax, _CMP_GT_OQ),
                                      _mm512_set1_ps(static_cast<float>(kPi / 2.0)), p);
    theta = _mm512_mask_sub_ps(theta, _mm512_cmp_ps_mask(x, zero, _CMP_LT_OQ),
                               _mm512_set1_ps(static_cast<float>(kPi)), theta);
    theta = _mm512_mask_sub_ps(theta, _mm512_cmp_ps_mask(y, zero, _CMP_LT_OQ),
                               _mm512_set1_ps(static_cast<float>(kTwoPi)), theta);
    const __m512 a_sector = _mm512_mul_ps(theta, _mm512_set1_ps(b.sector_scale));

    // As in codes8: no clamps (a negative, NaN or huge value is not ok), and a
    // drop wins over ok.
    __m512 ring, sector, height;
    const __mmask16 ok =
        ok16(a_ring, ring, b.ring_margin) & ok16(a_sector, sector, b.sector_margin) &
        ok16(a_height, height, b.height_margin) &
        _mm512_cmp_ps_mask(a_ring, _mm512_set1_ps(b.ring_min + b.ring_margin), _CMP_GT_OQ);
    const __mmask16 drop =
        _mm512_cmp_ps_mask(a_ring, _mm512_set1_ps(b.ring_min - b.ring_margin), _CMP_LT_OQ) |
        _mm512_cmp_ps_mask(a_ring, _mm512_set1_ps(b.rings_f + b.ring_margin), _CMP_GT_OQ) |
        _mm512_cmp_ps_mask(a_height, _mm512_set1_ps(-b.height_margin), _CMP_LT_OQ) |
        _mm512_cmp_ps_mask(a_height, _mm512_set1_ps(b.heights_f + b.height_margin), _CMP_GT_OQ);
    const __m512 cell_f = _mm512_fmadd_ps(_mm512_fmadd_ps(height, _mm512_set1_ps(b.rings_f), ring),
                                          _mm512_set1_ps(static_cast<float>(b.sectors)), sector);
    const __m512i cell = _mm512_cvttps_epi32(cell_f);
    const __m512i code = _mm512_mask_mov_epi32(_mm512_set1_epi32(kExact), ok, cell);
    return _mm512_mask_mov_epi32(code, drop, _mm512_set1_epi32(kDrop));
}

DISCO_AVX512 int fast_codes_simd16(const float* xs, const float* ys, const float* zs, int n,
                                   const Binning& b, int32_t* codes, int32_t* where) {
    int i = 0, kept = 0;
    for (; i + 16 <= n; i += 16) {
        const __m512 x = _mm512_load_ps(xs + i), y = _mm512_load_ps(ys + i);
        const __m512 z = _mm512_load_ps(zs + i);
        if (!any16(x, y, z, b)) continue;
        _mm512_storeu_si512(codes + kGroup * kept, codes16(x, y, z, b));
        for (int g = 0; g < 16 / kGroup; ++g) where[kept++] = i / kGroup + g;
    }
    if (i < n) fast_codes(xs + i, ys + i, zs + i, n - i, b, codes + kGroup * kept);
    return append_tail(i, n, kept, where);
}

DISCO_AVX512 int fast_codes_xyzw16(const float* rows, int n, const Binning& b, int32_t* codes,
                                   int32_t* where) {
    // Two-source permutes pick x and y (then z) of 8 points out of 2 registers of
    // 4 points each; 256-bit halves are then joined. Point order is kept.
    const __m512i pick_xy =
        _mm512_setr_epi32(0, 4, 8, 12, 16, 20, 24, 28, 1, 5, 9, 13, 17, 21, 25, 29);
    const __m512i pick_z =
        _mm512_setr_epi32(2, 6, 10, 14, 18, 22, 26, 30, 3, 7, 11, 15, 19, 23, 27, 31);
    int i = 0, kept = 0;
    for (; i + 16 <= n; i += 16) {
        const float* r = rows + 4 * i;
        const __m512 a0 = _mm512_loadu_ps(r);
        const __m512 a1 = _mm512_loadu_ps(r + 16);
        const __m512 a2 = _mm512_loadu_ps(r + 32);
        const __m512 a3 = _mm512_loadu_ps(r + 48);
        const __m512 xy0 = _mm512_permutex2var_ps(a0, pick_xy, a1);  // x0..x7 y0..y7
        const __m512 xy1 = _mm512_permutex2var_ps(a2, pick_xy, a3);  // x8..x15 y8..y15
        const __m512 zw0 = _mm512_permutex2var_ps(a0, pick_z, a1);
        const __m512 zw1 = _mm512_permutex2var_ps(a2, pick_z, a3);
        const __m512 x = _mm512_shuffle_f32x4(xy0, xy1, _MM_SHUFFLE(1, 0, 1, 0));
        const __m512 y = _mm512_shuffle_f32x4(xy0, xy1, _MM_SHUFFLE(3, 2, 3, 2));
        const __m512 z = _mm512_shuffle_f32x4(zw0, zw1, _MM_SHUFFLE(1, 0, 1, 0));
        if (!any16(x, y, z, b)) continue;
        _mm512_storeu_si512(codes + kGroup * kept, codes16(x, y, z, b));
        for (int g = 0; g < 16 / kGroup; ++g) where[kept++] = i / kGroup + g;
    }
    for (int j = i; j < n; ++j) {
        const float* r = rows + 4 * j;
        fast_codes(r, r + 1, r + 2, 1, b, codes + kGroup * kept + (j - i));
    }
    return append_tail(i, n, kept, where);
}
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
#endif

#if DISCO_BEV_NEON
// Four points at once with aarch64 Advanced SIMD (NEON): the arithmetic of codes8
// (FMA, truncation by rounding toward zero, no clamps, a drop wins over ok), with
// the cell index formed in float (exact below 2^24 cells).
struct BinningNeon {
    float32x4_t ring_scale, sector_scale, height_scale, z_min;
    float32x4_t ring_lo, ring_hi, ring_max_out, height_lo_out, height_max_out;
    float32x4_t rings, sectors;
    float32x4_t ring_margin, ring_margin_hi, sector_margin, sector_margin_hi, height_margin,
        height_margin_hi;
    float32x4_t r2_lo, r2_hi;

    explicit BinningNeon(const Binning& b)
        : ring_scale(vdupq_n_f32(b.ring_scale)),
          sector_scale(vdupq_n_f32(b.sector_scale)),
          height_scale(vdupq_n_f32(b.height_scale)),
          z_min(vdupq_n_f32(b.z_min_f)),
          ring_lo(vdupq_n_f32(b.ring_min - b.ring_margin)),
          ring_hi(vdupq_n_f32(b.ring_min + b.ring_margin)),
          ring_max_out(vdupq_n_f32(b.rings_f + b.ring_margin)),
          height_lo_out(vdupq_n_f32(-b.height_margin)),
          height_max_out(vdupq_n_f32(b.heights_f + b.height_margin)),
          rings(vdupq_n_f32(b.rings_f)),
          sectors(vdupq_n_f32(static_cast<float>(b.sectors))),
          ring_margin(vdupq_n_f32(b.ring_margin)),
          ring_margin_hi(vdupq_n_f32(1.0f - b.ring_margin)),
          sector_margin(vdupq_n_f32(b.sector_margin)),
          sector_margin_hi(vdupq_n_f32(1.0f - b.sector_margin)),
          height_margin(vdupq_n_f32(b.height_margin)),
          height_margin_hi(vdupq_n_f32(1.0f - b.height_margin)),
          r2_lo(vdupq_n_f32(b.r2_lo)),
          r2_hi(vdupq_n_f32(b.r2_hi)) {}
};

// Whether any of the four points might be in the grid (see any4).
inline bool any_neon(float32x4_t x, float32x4_t y, float32x4_t z, const BinningNeon& s) {
    const float32x4_t r2 = vaddq_f32(vmulq_f32(x, x), vmulq_f32(y, y));
    const float32x4_t a_height = vmulq_f32(vsubq_f32(z, s.z_min), s.height_scale);
    const uint32x4_t keep =
        vandq_u32(vandq_u32(vcgeq_f32(r2, s.r2_lo), vcleq_f32(r2, s.r2_hi)),
                  vandq_u32(vcgeq_f32(a_height, s.height_lo_out),
                            vcleq_f32(a_height, s.height_max_out)));
    return vmaxvq_u32(keep) != 0;
}

// trunc(a) and the lanes where it is certainly the index (NaN, Inf and huge values
// give frac NaN or 0: not ok).
inline float32x4_t index_neon(float32x4_t a, float32x4_t margin, float32x4_t margin_hi,
                              uint32x4_t& ok) {
    const float32x4_t i = vrndq_f32(a);
    const float32x4_t frac = vsubq_f32(a, i);
    ok = vandq_u32(vcgtq_f32(frac, margin), vcltq_f32(frac, margin_hi));
    return i;
}

inline int32x4_t codes_neon(float32x4_t x, float32x4_t y, float32x4_t z, const BinningNeon& s) {
    const float32x4_t zero = vdupq_n_f32(0.0f);
    const float32x4_t r2 = vfmaq_f32(vmulq_f32(y, y), x, x);
    const float32x4_t a_ring = vmulq_f32(vsqrtq_f32(r2), s.ring_scale);
    const float32x4_t a_height = vmulq_f32(vsubq_f32(z, s.z_min), s.height_scale);

    const float32x4_t ax = vabsq_f32(x);
    const float32x4_t ay = vabsq_f32(y);
    const float32x4_t t = vdivq_f32(vminq_f32(ax, ay), vmaxq_f32(ax, ay));
    const float32x4_t u = vmulq_f32(t, t);
    const float32x4_t u2 = vmulq_f32(u, u);
    const float32x4_t u4 = vmulq_f32(u2, u2);
    const float32x4_t q01 = vfmaq_f32(vdupq_n_f32(kA0), vdupq_n_f32(kA1), u);
    const float32x4_t q23 = vfmaq_f32(vdupq_n_f32(kA2), vdupq_n_f32(kA3), u);
    const float32x4_t q45 = vfmaq_f32(vdupq_n_f32(kA4), vdupq_n_f32(kA5), u);
    const float32x4_t q456 = vfmaq_f32(q45, vdupq_n_f32(kA6), u2);
    const float32x4_t q0123 = vfmaq_f32(q01, q23, u2);
    const float32x4_t p = vmulq_f32(vfmaq_f32(q0123, q456, u4), t);
    float32x4_t theta =
        vbslq_f32(vcgtq_f32(ay, ax), vsubq_f32(vdupq_n_f32(static_cast<float>(kPi / 2.0)), p), p);
    theta = vbslq_f32(vcltq_f32(x, zero),
                      vsubq_f32(vdupq_n_f32(static_cast<float>(kPi)), theta), theta);
    theta = vbslq_f32(vcltq_f32(y, zero),
                      vsubq_f32(vdupq_n_f32(static_cast<float>(kTwoPi)), theta), theta);
    const float32x4_t a_sector = vmulq_f32(theta, s.sector_scale);

    uint32x4_t ok_ring, ok_sector, ok_height;
    const float32x4_t ring = index_neon(a_ring, s.ring_margin, s.ring_margin_hi, ok_ring);
    const float32x4_t sector =
        index_neon(a_sector, s.sector_margin, s.sector_margin_hi, ok_sector);
    const float32x4_t height =
        index_neon(a_height, s.height_margin, s.height_margin_hi, ok_height);
    const uint32x4_t ok = vandq_u32(vandq_u32(ok_ring, vcgtq_f32(a_ring, s.ring_hi)),
                                    vandq_u32(ok_sector, ok_height));
    const uint32x4_t drop =
        vorrq_u32(vorrq_u32(vcltq_f32(a_ring, s.ring_lo), vcgtq_f32(a_ring, s.ring_max_out)),
                  vorrq_u32(vcltq_f32(a_height, s.height_lo_out),
                            vcgtq_f32(a_height, s.height_max_out)));
    const float32x4_t cell_f = vfmaq_f32(sector, vfmaq_f32(ring, height, s.rings), s.sectors);
    const int32x4_t cell = vcvtq_s32_f32(cell_f);
    // ok ? cell : kExact, then kDrop (all ones) wherever surely outside.
    const int32x4_t code = vbslq_s32(ok, cell, vdupq_n_s32(kExact));
    return vorrq_s32(code, vreinterpretq_s32_u32(drop));
}

int fast_codes_neon(const float* xs, const float* ys, const float* zs, int n, const Binning& b,
                    int32_t* codes, int32_t* where) {
    const BinningNeon s(b);
    int i = 0, kept = 0;
    for (; i + 4 <= n; i += 4) {
        const float32x4_t x = vld1q_f32(xs + i), y = vld1q_f32(ys + i), z = vld1q_f32(zs + i);
        if (!any_neon(x, y, z, s)) continue;
        vst1q_s32(codes + kGroup * kept, codes_neon(x, y, z, s));
        where[kept++] = i / kGroup;
    }
    if (i < n) fast_codes(xs + i, ys + i, zs + i, n - i, b, codes + kGroup * kept);
    return append_tail(i, n, kept, where);
}

// Packed x, y, z, w float rows: one de-interleaving load (LD4) per four points.
int fast_codes_xyzw_neon(const float* rows, int n, const Binning& b, int32_t* codes,
                         int32_t* where) {
    const BinningNeon s(b);
    int i = 0, kept = 0;
    for (; i + 4 <= n; i += 4) {
        const float32x4x4_t p = vld4q_f32(rows + 4 * i);
        if (!any_neon(p.val[0], p.val[1], p.val[2], s)) continue;
        vst1q_s32(codes + kGroup * kept, codes_neon(p.val[0], p.val[1], p.val[2], s));
        where[kept++] = i / kGroup;
    }
    for (int j = i; j < n; ++j) {
        const float* r = rows + 4 * j;
        fast_codes(r, r + 1, r + 2, 1, b, codes + kGroup * kept + (j - i));
    }
    return append_tail(i, n, kept, where);
}
#endif

// Which fast-path kernel runs: the best the CPU has, capped by set_bev_kernel_level.
std::atomic<int> g_level_cap{3};

int detected_level() {
#if DISCO_BEV_AVX2
    static const int level = __builtin_cpu_supports("avx512f") ? 3
                             : (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
                                 ? 2
                                 : 1;
    return level;
#elif DISCO_BEV_SSE2 || DISCO_BEV_NEON
    return 1;
#else
    return 0;
#endif
}

// Stage 1 for one chunk, codes for the rows row[0 .. m) in groups of kGroup: returns
// the number of groups that hold codes (the others are surely dropped);
// codes[k * kGroup + l] belongs to row where[k] * kGroup + l (ignored past m).
template <typename T>
int chunk_codes(int level, bool small, const T* row, Eigen::Index rs, Eigen::Index cs, int m,
                const Binning& b, float* xs, float* ys, float* zs, int32_t* codes,
                int32_t* where) {
    if constexpr (std::is_same_v<T, float>) {
        if (rs == 4 && cs == 1 && level >= 1) {
            const float* rows = row;
#if DISCO_BEV_AVX2
            if (level == 3) return fast_codes_xyzw16(rows, m, b, codes, where);
            if (level == 2) return fast_codes_xyzw8(rows, m, b, codes, where);
#endif
#if DISCO_BEV_SSE2
            return fast_codes_xyzw(rows, m, b, SimdBinning(b), codes, where);
#endif
#if DISCO_BEV_NEON
            return fast_codes_xyzw_neon(rows, m, b, codes, where);
#endif
        }
    }
    if (rs == 4 && cs == 1) {
        // The KITTI layout with constant strides, so the compiler vectorizes the copy.
        for (int i = 0; i < m; ++i) {
            xs[i] = static_cast<float>(row[4 * i]);
            ys[i] = static_cast<float>(row[4 * i + 1]);
            zs[i] = static_cast<float>(row[4 * i + 2]);
        }
    } else if (rs == 3 && cs == 1) {
        for (int i = 0; i < m; ++i) {
            xs[i] = static_cast<float>(row[3 * i]);
            ys[i] = static_cast<float>(row[3 * i + 1]);
            zs[i] = static_cast<float>(row[3 * i + 2]);
        }
    } else {
        for (int i = 0; i < m; ++i, row += rs) {
            xs[i] = static_cast<float>(row[0]);
            ys[i] = static_cast<float>(row[cs]);
            zs[i] = static_cast<float>(row[2 * cs]);
        }
    }
#if DISCO_BEV_AVX2
    if (level == 3) return fast_codes_simd16(xs, ys, zs, m, b, codes, where);
    if (level == 2) return fast_codes_simd8(xs, ys, zs, m, b, codes, where);
#endif
#if DISCO_BEV_SSE2
    if (level == 1) return fast_codes_simd(xs, ys, zs, m, b, SimdBinning(b), codes, where);
#endif
#if DISCO_BEV_NEON
    if (level == 1) return fast_codes_neon(xs, ys, zs, m, b, codes, where);
#endif
    if (small) return fast_codes_plain_skip<true>(xs, ys, zs, m, b, codes, where);
    return fast_codes_plain_skip<false>(xs, ys, zs, m, b, codes, where);
}

template <BEVMode Mode, typename T>
// Returns the largest cell value in density mode (the count to divide by), else 0.
float voxelize(const BEVPointsView<T>& points, const Binning& b, float* out) {
    const Eigen::Index n = points.rows();
    const T* base = points.data();
    const Eigen::Index rs = points.outerStride();
    const Eigen::Index cs = points.innerStride();
    alignas(64) float xs[kChunk];
    alignas(64) float ys[kChunk];
    alignas(64) float zs[kChunk];
    alignas(64) int32_t codes[kChunk];
    int32_t where[kChunk / kGroup];
    float sink = 0.0f;  // occupancy: dropped points write here, so the scatter has no branch
    float peak = 0.0f;
    // Density and max_height read-modify-write a cell, and consecutive points of a
    // scan often share one: combining a run of them in a register and writing once
    // avoids a chain of dependent loads and stores through memory.
    int32_t run_cell = kDrop;
    float run = 0.0f;
    auto flush = [&]() {
        if (run_cell < 0) return;
        float& cell = out[run_cell];
        if constexpr (Mode == BEVMode::kDensity) {
            cell += run;  // exact: small integers
            peak = std::max(peak, cell);
        } else {
            cell = std::max(cell, run);
        }
    };
    // The SIMD kernels form the cell index in float, exact below 2^24 cells.
    const bool small = static_cast<std::size_t>(b.heights) * b.rings * b.sectors < (1u << 24);
    const int level = small ? std::min(detected_level(), g_level_cap.load()) : 0;
    for (Eigen::Index start = 0; start < n; start += kChunk) {
        const int m = static_cast<int>(std::min<Eigen::Index>(kChunk, n - start));
        const T* row = base + start * rs;
        const int kept = chunk_codes(level, small, row, rs, cs, m, b, xs, ys, zs, codes, where);
        for (int k = 0; k < kept; ++k) {
            const int first = where[k] * kGroup;
            const int end = std::min(m, first + kGroup);
            const int32_t* code = codes + k * kGroup - first;
            row = base + (start + first) * rs;
            if constexpr (Mode == BEVMode::kOccupancy) {
                for (int i = first; i < end; ++i, row += rs) {
                    int32_t c = code[i];
                    if (c == kExact) {
                        c = exact_cell(static_cast<double>(row[0]), static_cast<double>(row[cs]),
                                       static_cast<double>(row[2 * cs]), b);
                    }
                    float* dst = c >= 0 ? out + c : &sink;
                    *dst = 1.0f;
                }
                continue;  // the loop below is for density and max_height
            }
            for (int i = first; i < end; ++i, row += rs) {
                int32_t c = code[i];
                if (c == kExact) {
                    c = exact_cell(static_cast<double>(row[0]), static_cast<double>(row[cs]),
                                   static_cast<double>(row[2 * cs]), b);
                }
                if (c < 0) continue;
                float v = 1.0f;
                if constexpr (Mode == BEVMode::kMaxHeight) {
                    // z - z_min of the top point; rounding to float keeps the order.
                    v = static_cast<float>(static_cast<double>(row[2 * cs]) - b.z_min);
                }
                if (c == run_cell) {
                    run = Mode == BEVMode::kDensity ? run + v : std::max(run, v);
                } else {
                    flush();
                    run_cell = c;
                    run = v;
                }
            }
        }
    }
    if constexpr (Mode != BEVMode::kOccupancy) flush();
    return peak;
}

template <typename T>
void polar_bev_impl(const BEVPointsView<T>& points, const BEVConfig& config, float* out) {
    config.validate();
    const Binning b = make_binning(config);
    const std::size_t cells = config.cells();
    std::memset(out, 0, cells * sizeof(float));
    switch (config.mode) {
        case BEVMode::kOccupancy:
            voxelize<BEVMode::kOccupancy>(points, b, out);
            break;
        case BEVMode::kDensity: {
            // A dropped point raises the peak to 1 at most, and then no cell holds a
            // point, so dividing the zeros changes nothing.
            const float peak = voxelize<BEVMode::kDensity>(points, b, out);
            if (peak > 1.0f) {
                for (std::size_t i = 0; i < cells; ++i) out[i] /= peak;
            }
            break;
        }
        case BEVMode::kMaxHeight:
            voxelize<BEVMode::kMaxHeight>(points, b, out);
            break;
    }
}

}  // namespace

void BEVConfig::validate() const {
    auto fail = [](const std::string& what) { throw std::invalid_argument("BEVConfig: " + what); };
    constexpr int kMaxCells = 1 << 30;  // flat indices are int32
    constexpr double kMaxAbs = 1e9;     // keeps the float fast path meaningful
    if (rings < 1 || sectors < 1 || heights < 1) fail("rings, sectors and heights must be >= 1");
    if (static_cast<double>(rings) * sectors * heights > kMaxCells)
        fail("too many cells (over 2^30)");
    for (double v : {max_range, min_range, z_min, z_max}) {
        if (!std::isfinite(v) || std::abs(v) > kMaxAbs)
            fail("ranges and heights must be finite, |value| <= 1e9");
    }
    if (!(min_range >= 0.0 && min_range < max_range)) fail("need 0 <= min_range < max_range");
    if (!(z_min < z_max)) fail("need z_min < z_max");
    const int m = static_cast<int>(mode);
    if (m < 0 || m > 2) fail("unknown mode");
}

int set_bev_kernel_level(int cap) {
    const int previous = g_level_cap.exchange(std::max(0, std::min(cap, 3)));
    return previous;
}

int bev_kernel_level() { return std::min(detected_level(), g_level_cap.load()); }

const char* bev_kernel_name(int level) {
    if (level < 0) level = bev_kernel_level();
    if (level > detected_level()) return "";
    switch (level) {
        case 0:
            return "plain";
        case 1:
#if DISCO_BEV_NEON
            return "neon";
#else
            return "sse2";
#endif
        case 2:
            return "avx2";
        case 3:
            return "avx512";
        default:
            return "";
    }
}

const char* wide_kernel_name(int level) {
    switch (level) {
        case 3:
            return "avx512";
        case 2:
            return "avx2";
        default:
            return "plain";
    }
}

void polar_bev(const BEVPointsView<float>& points, const BEVConfig& config, float* out) {
    polar_bev_impl(points, config, out);
}

void polar_bev(const BEVPointsView<double>& points, const BEVConfig& config, float* out) {
    polar_bev_impl(points, config, out);
}

void polar_bev_batch(const std::vector<AnyBEVPointsView>& scans, const BEVConfig& config,
                     float* out, int threads) {
    config.validate();
    const std::size_t cells = config.cells();
    const std::size_t count = scans.size();
    if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
    threads = static_cast<int>(std::min<std::size_t>(static_cast<std::size_t>(threads), count));
    std::atomic<std::size_t> next{0};
    auto work = [&]() {
        for (std::size_t i = next++; i < count; i = next++) {
            std::visit([&](const auto& view) { polar_bev_impl(view, config, out + i * cells); },
                       scans[i]);
        }
    };
    if (threads <= 1) {
        work();
        return;
    }
    std::vector<std::thread> pool;
    pool.reserve(static_cast<std::size_t>(threads - 1));
    try {
        for (int t = 1; t < threads; ++t) pool.emplace_back(work);
    } catch (const std::system_error&) {
        // No more threads to be had: the ones started (and this one) share the work.
    }
    work();
    for (auto& th : pool) th.join();
}

}  // namespace disco
