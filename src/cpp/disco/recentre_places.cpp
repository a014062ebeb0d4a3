#include "disco/recentre_places.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include "disco/sector_fft.hpp"  // the SIMD level the kernels run at (capped)

namespace disco {

namespace {

// atan(t) / t as a polynomial in s = t^2 on [0, tan^2(pi / 8)]: a least-squares fit on
// Chebyshev nodes (degree 7), relative error under 1e-12 there (a float32 ulp is 6e-8).
constexpr double kAtan[8] = {
    0.9999999999992708,   -0.333333332783841,   0.19999993188867157, -0.14285391259099367,
    0.11103534915801425,  -0.08993217313907109, 0.06977005517995481, -0.03770174479052323};
constexpr double kTanPi8 = 0.41421356237309503;
constexpr double kPi = 3.141592653589793, kHalfPi = 1.5707963267948966;
constexpr double kQuarterPi = 0.7853981633974483;

// All ones where c holds, else 0; v where the mask is all ones, else +0; v negated
// where it is all ones.
inline __attribute__((always_inline)) std::uint64_t mask(bool c) {
    return std::uint64_t{0} - static_cast<std::uint64_t>(c);
}
inline __attribute__((always_inline)) double keep(double v, std::uint64_t m) {
    std::uint64_t b;
    std::memcpy(&b, &v, sizeof b);
    b &= m;
    std::memcpy(&v, &b, sizeof b);
    return v;
}
inline __attribute__((always_inline)) double flip(double v, std::uint64_t m) {
    std::uint64_t b;
    std::memcpy(&b, &v, sizeof b);
    b ^= m & (std::uint64_t{1} << 63);
    std::memcpy(&v, &b, sizeof b);
    return v;
}

// Branch-free, so that the loops below vectorize: the smaller of |x|, |y| over the
// larger, past tan(pi / 8) taken as pi / 4 + atan((n - d) / (n + d)) (one division
// either way), then the octant and the quadrant put back. Every step is an IEEE-rounded
// operation (no fusing: -ffp-contract=off), so every level gives the same bits.
inline __attribute__((always_inline)) double atan2_of(float yf, float xf) {
    const double x = xf, y = yf;
    const double ax = std::fabs(x), ay = std::fabs(y);
    // The octant's and quadrant's choices as bit masks on the terms they add (a chosen
    // sum as a select, GCC turns into a branch, which keeps the loops from vectorizing).
    const bool steep = ay > ax;
    const double n = std::min(ax, ay), d = std::max(ax, ay);
    const std::uint64_t far = mask(n > kTanPi8 * d);
    // At the origin 0 / DBL_MIN: 0 (any other denominator is at least a float's least).
    const double den = std::max(d + keep(n, far), std::numeric_limits<double>::min());
    const double t = (n - keep(d, far)) / den;
    const double s = t * t;
    const double s2 = s * s, s4 = s2 * s2;
    const double p = ((kAtan[0] + kAtan[1] * s) + (kAtan[2] + kAtan[3] * s) * s2) +
                     ((kAtan[4] + kAtan[5] * s) + (kAtan[6] + kAtan[7] * s) * s2) * s4;
    const double octant = t * p + keep(kQuarterPi, far);
    const std::uint64_t up = mask(steep), left = mask(std::copysign(1.0, x) < 0.0);
    const double half = keep(kHalfPi, up) + flip(octant, up);
    const double r = keep(kPi, left) + flip(half, left);
    return std::copysign(r, y);
}

inline __attribute__((always_inline)) void places_body(const PlacesGrid& g, float px, float py,
                                                       float* ring, float* sector) {
    for (std::int64_t c = 0; c < g.cells; ++c) {
        const float x = g.x[c] + px, y = g.y[c] + py;
        const float rf = std::sqrt(x * x + y * y) * g.ring_scale + 0.5f;
        ring[c] = g.ring_cap < rf ? g.ring_cap : rf;  // np.minimum (neither is NaN)
        sector[c] = static_cast<float>(atan2_of(y, x)) * g.sector_scale + g.sector_shift;
    }
}

using Body = void (*)(const PlacesGrid&, float, float, float*, float*);

// The plain and SSE2 levels (and other machines'): the baseline target, vectorized as
// the compiler can. (An optimize attribute to keep the plain level scalar would drop
// -ffp-contract=off for it, which could fuse on aarch64.)
void places_base(const PlacesGrid& g, float px, float py, float* ring, float* sector) {
    places_body(g, px, py, ring, sector);
}

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define DISCO_PLACES_X86 1
__attribute__((target("avx2"))) void places_avx2(const PlacesGrid& g, float px, float py,
                                                 float* ring, float* sector) {
    places_body(g, px, py, ring, sector);
}

__attribute__((target("avx512f"))) void places_avx512(const PlacesGrid& g, float px, float py,
                                                     float* ring, float* sector) {
    places_body(g, px, py, ring, sector);
}
#endif

}  // namespace

void recentre_places(const PlacesGrid& grid, const float* positions, std::int64_t count,
                     float* out) {
    Body body = places_base;
    switch (sector_fft_level()) {
#if DISCO_PLACES_X86
        case 3: body = places_avx512; break;
        case 2: body = places_avx2; break;
#endif
        default: break;
    }
    for (std::int64_t m = 0; m < count; ++m) {
        float* ring = out + m * 2 * grid.cells;
        body(grid, positions[2 * m], positions[2 * m + 1], ring, ring + grid.cells);
    }
}

}  // namespace disco
