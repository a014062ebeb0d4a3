// The polar BEV voxelizer. The definition (polar_bev.hpp) is in double precision;
// evaluating it per point (sqrt, two divisions, atan2 in double) would cost several
// times our budget, so each point takes a fast single-precision path with a
// polynomial atan2, and only a point that lands within a proven error margin of a
// cell edge (well under 0.1% of a real scan) is redone with the exact double
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
#include <thread>

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
    b.sector_margin = static_cast<float>(4.0 * kAngleErr * c.sectors / kTwoPi + 32.0 * eps * (c.sectors + 2.0));
    const double z_abs = std::max(std::abs(c.z_min), std::abs(c.z_max)) + b.height_w;
    b.height_margin =
        static_cast<float>(32.0 * eps * ((2.0 * z_abs + (c.z_max - c.z_min)) / b.height_w + b.heights + 2.0));
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
// ok: a is inside (0, n) and at least `margin` from every integer, so floor(a)
// is the exact index; returns floor(a) clamped into [0, n].
inline int fast_index(float a, float n, float margin, bool& ok) {
    const float clamped = std::min(a > 0.0f ? a : 0.0f, n);  // NaN -> 0
    const int i = static_cast<int>(clamped);
    const float frac = a - static_cast<float>(i);
    ok = (a < n) & (frac > margin) & (frac < 1.0f - margin);
    return i;
}

// Fast path over one chunk of deinterleaved coordinates: a cell index, kDrop or
// kExact per point. Branch-free so that the compiler vectorizes it.
void fast_codes(const float* xs, const float* ys, const float* zs, int n, const Binning& b,
                int32_t* codes) {
    const float half_pi = static_cast<float>(kPi / 2.0);
    const float pi = static_cast<float>(kPi);
    const float two_pi = static_cast<float>(kTwoPi);
    const float sectors_f = static_cast<float>(b.sectors);
    for (int i = 0; i < n; ++i) {
        const float x = xs[i];
        const float y = ys[i];
        const float z = zs[i];
        const float a_ring = std::sqrt(x * x + y * y) * b.ring_scale;
        const float a_height = (z - b.z_min_f) * b.height_scale;

        // atan2 by octant: t = min/max in [0, 1], atan(t) by polynomial, then unfold.
        const float ax = std::fabs(x);
        const float ay = std::fabs(y);
        const float t = std::min(ax, ay) / std::max(ax, ay);
        const float u = t * t;
        const float p = (((((((kA6 * u + kA5) * u + kA4) * u + kA3) * u + kA2) * u + kA1) * u) + kA0) * t;
        float theta = ay > ax ? half_pi - p : p;
        theta = x < 0.0f ? pi - theta : theta;
        theta = y < 0.0f ? two_pi - theta : theta;
        const float a_sector = theta * b.sector_scale;

        bool ok_ring, ok_sector, ok_height;
        const int ring = fast_index(a_ring, b.rings_f, b.ring_margin, ok_ring);
        const int sector = fast_index(a_sector, sectors_f, b.sector_margin, ok_sector);
        const int height = fast_index(a_height, b.heights_f, b.height_margin, ok_height);
        ok_ring &= a_ring > b.ring_min + b.ring_margin;

        const bool drop = (a_ring < b.ring_min - b.ring_margin) | (a_ring > b.rings_f + b.ring_margin) |
                          (a_height < -b.height_margin) | (a_height > b.heights_f + b.height_margin);
        const int32_t cell = (height * b.rings + ring) * b.sectors + sector;
        codes[i] = (ok_ring & ok_sector & ok_height) ? cell : (drop ? kDrop : kExact);
    }
}

template <BEVMode Mode, typename T>
void voxelize(const BEVPointsView<T>& points, const Binning& b, float* out) {
    const Eigen::Index n = points.rows();
    const T* base = points.data();
    const Eigen::Index rs = points.outerStride();
    const Eigen::Index cs = points.innerStride();
    alignas(64) float xs[kChunk];
    alignas(64) float ys[kChunk];
    alignas(64) float zs[kChunk];
    alignas(64) int32_t codes[kChunk];
    float sink = 0.0f;  // dropped points write here, so the scatter has no branch
    for (Eigen::Index start = 0; start < n; start += kChunk) {
        const int m = static_cast<int>(std::min<Eigen::Index>(kChunk, n - start));
        const T* row = base + start * rs;
        for (int i = 0; i < m; ++i, row += rs) {
            xs[i] = static_cast<float>(row[0]);
            ys[i] = static_cast<float>(row[cs]);
            zs[i] = static_cast<float>(row[2 * cs]);
        }
        fast_codes(xs, ys, zs, m, b, codes);
        row = base + start * rs;
        for (int i = 0; i < m; ++i, row += rs) {
            int32_t c = codes[i];
            if (c == kExact) {
                c = exact_cell(static_cast<double>(row[0]), static_cast<double>(row[cs]),
                               static_cast<double>(row[2 * cs]), b);
            }
            float* dst = c >= 0 ? out + c : &sink;
            if constexpr (Mode == BEVMode::kOccupancy) {
                *dst = 1.0f;
            } else if constexpr (Mode == BEVMode::kDensity) {
                *dst += 1.0f;
            } else {
                // z - z_min of the top point; rounding to float keeps the order.
                const float v = static_cast<float>(static_cast<double>(row[2 * cs]) - b.z_min);
                *dst = std::max(*dst, v);
            }
        }
    }
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
            voxelize<BEVMode::kDensity>(points, b, out);
            float peak = 0.0f;
            for (std::size_t i = 0; i < cells; ++i) peak = std::max(peak, out[i]);
            if (peak > 0.0f) {
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
    if (static_cast<double>(rings) * sectors * heights > kMaxCells) fail("too many cells (over 2^30)");
    for (double v : {max_range, min_range, z_min, z_max}) {
        if (!std::isfinite(v) || std::abs(v) > kMaxAbs) fail("ranges and heights must be finite, |value| <= 1e9");
    }
    if (!(min_range >= 0.0 && min_range < max_range)) fail("need 0 <= min_range < max_range");
    if (!(z_min < z_max)) fail("need z_min < z_max");
    const int m = static_cast<int>(mode);
    if (m < 0 || m > 2) fail("unknown mode");
}

void polar_bev(const BEVPointsView<float>& points, const BEVConfig& config, float* out) {
    polar_bev_impl(points, config, out);
}

void polar_bev(const BEVPointsView<double>& points, const BEVConfig& config, float* out) {
    polar_bev_impl(points, config, out);
}

void polar_bev_batch(const std::vector<AnyBEVPointsView>& scans, const BEVConfig& config, float* out,
                     int threads) {
    config.validate();
    const std::size_t cells = config.cells();
    const std::size_t count = scans.size();
    if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
    threads = static_cast<int>(std::min<std::size_t>(static_cast<std::size_t>(threads), count));
    std::atomic<std::size_t> next{0};
    auto work = [&]() {
        for (std::size_t i = next++; i < count; i = next++) {
            std::visit([&](const auto& view) { polar_bev_impl(view, config, out + i * cells); }, scans[i]);
        }
    };
    if (threads <= 1) {
        work();
        return;
    }
    std::vector<std::thread> pool;
    pool.reserve(static_cast<std::size_t>(threads - 1));
    for (int t = 1; t < threads; ++t) pool.emplace_back(work);
    work();
    for (auto& th : pool) th.join();
}

}  // namespace disco
