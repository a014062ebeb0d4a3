// Checks of the C++ core that need no Python, built natively and for aarch64 by
// `make check-aarch64` (tests/cpp/CMakeLists.txt), whose outputs must be equal line
// for line.
//
// - The polar BEV of seeded random scans and of edge cases, at every kernel level
//   this CPU has, must equal an independent reference written here from the
//   definition (double precision, std::atan2); each case prints a hash of its BEV.
// - voxel_downsample, int8_encode and ray casting print hashes of their outputs,
//   which must not depend on the CPU either (no FMA fusing, no fast-math).
// - check_kernels.cpp (called last) checks the sector, search and convolution kernels.
// Lines starting with '#' (the kernels this machine has) are left out of the
// comparison. Exit status 1 on any mismatch with the reference.
//
// Inputs are made from integers by exact float arithmetic (no libm), so both
// builds see the same bits. `check_core --bench` times the kernels instead.
#include <Eigen/Core>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "disco/icp.hpp"
#include "disco/int8_search.hpp"
#include "disco/polar_bev.hpp"
#include "disco/polar_resample.hpp"
#include "disco/raycast.hpp"
#include "disco/voxel_grid.hpp"
#include "check_common.hpp"

namespace {

int g_failures = 0;
std::uint64_t g_checksum = 1469598103934665603ull;  // over every printed hash

using disco_check::fnv1a;
using disco_check::Rng;

unsigned long long reported(std::uint64_t h) {
    g_checksum = fnv1a(&h, sizeof h, g_checksum);
    return static_cast<unsigned long long>(h);
}

// The definition of docs/bev.md, written independently of polar_bev.cpp.
std::vector<float> reference_bev(const std::vector<double>& xyz, const disco::BEVConfig& c) {
    const int layers = c.layers();
    std::vector<float> out(c.cells(), 0.0f);
    std::vector<double> count(c.cells(), 0.0);
    const double two_pi = 2.0 * 3.14159265358979323846;
    for (std::size_t i = 0; i + 2 < xyz.size(); i += 3) {
        const double x = xyz[i], y = xyz[i + 1], z = xyz[i + 2];
        if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) continue;
        const double r = std::sqrt(x * x + y * y);
        if (!(r >= c.min_range && r < c.max_range && z >= c.z_min && z < c.z_max)) continue;
        double theta = std::atan2(y, x);
        if (theta < 0) theta += two_pi;
        const int ring = std::min(static_cast<int>(std::floor(r / (c.max_range / c.rings))),
                                  c.rings - 1);
        const int sector = std::min(
            static_cast<int>(std::floor(theta / (two_pi / c.sectors))), c.sectors - 1);
        const int height = std::min(
            static_cast<int>(std::floor((z - c.z_min) / ((c.z_max - c.z_min) / layers))),
            layers - 1);
        const std::size_t cell =
            (static_cast<std::size_t>(height) * c.rings + ring) * c.sectors + sector;
        if (c.mode == disco::BEVMode::kOccupancy) {
            out[cell] = 1.0f;
        } else if (c.mode == disco::BEVMode::kDensity) {
            count[cell] += 1.0;
        } else {
            out[cell] = std::max(out[cell], static_cast<float>(z - c.z_min));
        }
    }
    if (c.mode == disco::BEVMode::kDensity) {
        double peak = 0.0;
        for (double v : count) peak = std::max(peak, v);
        const auto peak_f = static_cast<float>(peak);
        for (std::size_t k = 0; k < out.size(); ++k) {
            out[k] = static_cast<float>(count[k]);
            if (peak_f > 1.0f) out[k] /= peak_f;
        }
    }
    return out;
}

template <typename T>
std::vector<float> run_bev(const std::vector<T>& rows, int cols, const disco::BEVConfig& c) {
    const auto n = static_cast<Eigen::Index>(rows.size() / cols);
    disco::BEVPointsView<T> view(rows.data(), n, 3, Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>(cols, 1));
    std::vector<float> out(c.cells());
    disco::polar_bev(view, c, out.data());
    return out;
}

// Every kernel level this machine has, on float32 rows of 4 and 3 columns and on
// float64 rows, must give the reference. Prints one line per case.
void check_bev(const std::string& name, const std::vector<double>& xyz, const disco::BEVConfig& c) {
    const std::size_t n = xyz.size() / 3;
    std::vector<float> f4(4 * n), f3(3 * n);
    std::vector<double> xyz_f(3 * n);  // the float32 points, as the reference sees them
    for (std::size_t i = 0; i < n; ++i) {
        for (int k = 0; k < 3; ++k) {
            const auto v = static_cast<float>(xyz[3 * i + k]);
            f4[4 * i + k] = v;
            f3[3 * i + k] = v;
            xyz_f[3 * i + k] = v;
        }
        f4[4 * i + 3] = 0.5f;
    }
    const std::vector<float> expected = reference_bev(xyz_f, c);
    const std::vector<float> expected64 = reference_bev(xyz, c);
    const int best = disco::bev_kernel_level();
    for (int level = best; level >= 0; --level) {
        disco::set_bev_kernel_level(level);
        const bool ok = run_bev(f4, 4, c) == expected && run_bev(f3, 3, c) == expected &&
                        run_bev(xyz, 3, c) == expected64;
        if (!ok) {
            std::fprintf(stderr, "FAIL %s: kernel %s differs from the reference\n", name.c_str(),
                         disco::bev_kernel_name(level));
            ++g_failures;
        }
    }
    disco::set_bev_kernel_level(3);
    std::size_t filled = 0;
    for (float v : expected) filled += v != 0.0f;
    std::uint64_t h = fnv1a(expected.data(), expected.size() * sizeof(float));
    h = fnv1a(expected64.data(), expected64.size() * sizeof(float), h);
    std::printf("bev %-28s points %7zu cells %6zu hash %016llx\n", name.c_str(), n, filled,
                reported(h));
}

std::vector<double> random_scan(std::uint64_t seed, std::size_t n) {
    Rng rng{seed};
    std::vector<double> xyz(3 * n);
    for (std::size_t i = 0; i < n; ++i) {
        xyz[3 * i] = rng.uniform(-90, 90);
        xyz[3 * i + 1] = rng.uniform(-90, 90);
        xyz[3 * i + 2] = rng.uniform(-3, 21);
    }
    return xyz;
}

// Points on the grid's edges (exact, or one float step either side) and values a
// fast path must not misread: signed zeros, NaN, Inf, huge and tiny numbers.
std::vector<double> edge_points(const disco::BEVConfig& c) {
    std::vector<double> xyz;
    auto add = [&](double x, double y, double z) { xyz.insert(xyz.end(), {x, y, z}); };
    const double ring_w = c.max_range / c.rings;
    const double height_w = (c.z_max - c.z_min) / c.heights;
    for (int k = 0; k <= c.rings; ++k) {
        const double r = k * ring_w;
        for (double s : {-1.0, 0.0, 1.0}) {
            const auto rf = static_cast<double>(std::nextafter(static_cast<float>(r), s * 1e9f));
            add(rf, 0.0, 0.25);
            add(0.0, -rf, 0.25);
            add(-rf, 0.0, 7.5);
        }
    }
    for (double r : {c.min_range, c.max_range}) {
        add(r, 0.0, 1.0);
        add(std::nextafter(r, 0.0), 0.0, 1.0);
    }
    for (int k = 0; k <= c.heights; ++k) {
        const double z = c.z_min + k * height_w;
        add(10.0, 10.0, z);
        add(-10.0, 4.0, std::nextafter(z, -1e9));
        add(-10.0, -4.0, std::nextafter(z, 1e9));
    }
    // Diagonals (45 degrees: a sector edge of the default grid) and axes.
    for (double d : {5.0, 17.0, 33.25, 60.0}) {
        for (double sx : {-1.0, 1.0}) {
            for (double sy : {-1.0, 1.0}) {
                add(sx * d, sy * d, 2.0);
                add(sx * d, sy * std::nextafter(d, 0.0), 2.0);
                add(sx * 0.0, sy * d, 2.0);
                add(sx * d, sy * 0.0, 2.0);
            }
        }
    }
    const double inf = std::numeric_limits<double>::infinity();
    const double nan = std::numeric_limits<double>::quiet_NaN();
    for (double v : {nan, inf, -inf, 1e30, -1e30, 1e-40, -1e-40, 0.0, -0.0}) {
        add(v, 10.0, 1.0);
        add(10.0, v, 1.0);
        add(10.0, 10.0, v);
        add(v, v, v);
    }
    return xyz;
}

// Points just inside and just outside the ring and height windows, each repeated
// 16 times in a row, so that whole SIMD vectors and groups of the kernels hold only
// such points: a window test that skipped one surely-dropped group too many (its
// r^2 bounds too tight) would lose them all.
std::vector<double> window_runs(const disco::BEVConfig& c) {
    std::vector<double> xyz;
    auto add = [&](double x, double y, double z) {
        for (int k = 0; k < 16; ++k) xyz.insert(xyz.end(), {x, y, z});
    };
    const double zs[] = {c.z_min, c.z_max};
    for (double rel : {0.0, 1e-8, 1e-7, 1e-6, 5e-6, 1e-5, 2e-5, 3e-5, 1e-4}) {
        for (double s : {-1.0, 1.0}) {
            for (double bound : {c.min_range, c.max_range}) {
                const double r = bound * (1.0 + s * rel);
                add(r, 0.0, 1.0);
                add(0.0, -r, 1.0);
                add(-0.6 * r, 0.8 * r, 1.0);
                add(0.28 * r, -0.96 * r, 1.0);
            }
            for (double z : zs) {
                const double dz = s * rel * std::max(1.0, std::abs(z));
                add(10.0, 3.0, z + dz);
                add(-7.0, -20.0, z + dz);
            }
        }
    }
    for (double bound : {c.min_range, c.max_range}) {
        for (double s : {-1.0, 1.0}) {
            const auto f = static_cast<double>(std::nextafter(static_cast<float>(bound), s * 1e9f));
            add(f, 0.0, 1.0);
            add(0.0, f, 1.0);
        }
    }
    for (double z : zs) {
        for (double s : {-1.0, 1.0}) {
            add(10.0, 3.0, static_cast<double>(std::nextafter(static_cast<float>(z), s * 1e9f)));
        }
    }
    return xyz;
}

void check_voxel_downsample() {
    Rng rng{42};
    disco::Points3d points;
    for (int i = 0; i < 50000; ++i) {
        // One draw per statement: the order of a call's arguments is unspecified.
        const double x = rng.uniform(-50, 50);
        const double y = rng.uniform(-50, 50);
        const double z = rng.uniform(-2, 8);
        points.emplace_back(x, y, z);
    }
    for (double voxel : {0.25, 1.0}) {
        const disco::Points3d out = disco::voxel_downsample(points, voxel);
        std::uint64_t h = 1469598103934665603ull;
        for (const auto& p : out) h = fnv1a(p.data(), 3 * sizeof(double), h);
        std::printf("voxel_downsample %.2f      points %7zu hash %016llx\n", voxel, out.size(),
                    reported(h));
    }
}

void check_int8_encode() {
    Rng rng{7};
    const std::int64_t n = 3000, d = 256;
    std::vector<float> x(static_cast<std::size_t>(n * d));
    for (auto& v : x) v = static_cast<float>(rng.uniform(-1, 1));
    std::vector<double> mean(d), scale(d);
    for (std::int64_t j = 0; j < d; ++j) {
        mean[j] = rng.uniform(-0.1, 0.1);
        scale[j] = rng.uniform(0.005, 0.01);
    }
    std::vector<std::int8_t> codes(x.size());
    std::vector<double> code_sq(n), code_norm(n), err(n);
    disco::int8_encode(x.data(), n, d, mean.data(), scale.data(), codes.data(), code_sq.data(),
                       code_norm.data(), err.data(), 2);
    std::uint64_t h = fnv1a(codes.data(), codes.size());
    h = fnv1a(code_sq.data(), n * sizeof(double), h);
    h = fnv1a(code_norm.data(), n * sizeof(double), h);
    h = fnv1a(err.data(), n * sizeof(double), h);
    std::printf("int8_encode                  rows %9lld hash %016llx\n",
                static_cast<long long>(n), reported(h));
}

void check_raycast() {
    // Axis-aligned boxes, cylinders and ellipsoids (yaw 0, so no libm sin/cos
    // enters), rays along directions made of integers.
    Rng rng{99};
    std::vector<disco::Primitive> prims;
    for (int k = 0; k < 300; ++k) {
        disco::Primitive p;
        p.kind = static_cast<disco::PrimitiveKind>(k % 3);
        p.cx = rng.uniform(-60, 60);
        p.cy = rng.uniform(-60, 60);
        p.cz = rng.uniform(0, 5);
        p.hx = rng.uniform(0.2, 4);
        p.hy = rng.uniform(0.2, 4);
        p.hz = rng.uniform(0.5, 6);
        p.hit_prob = k % 5 == 0 ? 0.5 : 1.0;
        prims.push_back(p);
    }
    const disco::RaycastWorld world(prims, disco::GroundPlane{0.01, -0.02, -1.7}, 4.0);
    const std::int64_t n = 20000;
    std::vector<float> dirs(3 * n);
    for (std::int64_t i = 0; i < n; ++i) {
        const float dx = static_cast<float>(rng.uniform(-1, 1));
        const float dy = static_cast<float>(rng.uniform(-1, 1));
        const float dz = static_cast<float>(rng.uniform(-0.4, 0.1));
        const float len = std::sqrt(dx * dx + dy * dy + dz * dz);
        dirs[3 * i] = dx / len;
        dirs[3 * i + 1] = dy / len;
        dirs[3 * i + 2] = dz / len;
    }
    std::vector<float> range(n), cosi(n);
    std::vector<std::int32_t> id(n);
    world.cast(Eigen::Vector3d(0.5, -0.25, 0.0), dirs.data(), n, 100.0, 1234, range.data(),
               id.data(), cosi.data());
    std::uint64_t h = fnv1a(range.data(), n * sizeof(float));
    h = fnv1a(id.data(), n * sizeof(std::int32_t), h);
    h = fnv1a(cosi.data(), n * sizeof(float), h);
    std::printf("raycast                      rays %9lld hash %016llx\n",
                static_cast<long long>(n), reported(h));
}


// Hostile input for every entry point: empty and one-point clouds, NaN, Inf, values far
// beyond any grid (float -> int casts must not overflow), degenerate rays, worlds and
// searches. Run under `make check-sanitize`, any out-of-bounds access, overflow or bad
// cast stops the program; here each case must also end in a sane result.
void expect(bool ok, const char* what) {
    if (!ok) {
        std::fprintf(stderr, "FAIL hostile: %s\n", what);
        ++g_failures;
    }
}

std::vector<float> hostile_cloud() {
    const float inf = std::numeric_limits<float>::infinity();
    const float nan = std::numeric_limits<float>::quiet_NaN();
    const float big = std::numeric_limits<float>::max();
    std::vector<float> rows;
    for (float v : {nan, inf, -inf, big, -big, 1e30f, -1e30f, 3e9f, -3e9f, 1e-40f, 0.0f, -0.0f}) {
        rows.insert(rows.end(), {v, 1.0f, 0.5f, 0.0f});
        rows.insert(rows.end(), {1.0f, v, 0.5f, 0.0f});
        rows.insert(rows.end(), {2.0f, 3.0f, v, 0.0f});
        rows.insert(rows.end(), {v, v, v, v});
    }
    // A plane of ordinary points, so that the ICP has something to align.
    for (int i = -20; i <= 20; ++i)
        for (int j = -20; j <= 20; ++j)
            rows.insert(rows.end(), {0.5f * static_cast<float>(i), 0.5f * static_cast<float>(j),
                                     static_cast<float>((i * j) % 3) * 0.25f, 0.0f});
    return rows;
}

disco::CloudView view_of(const std::vector<float>& rows) {
    return disco::CloudView(rows.data(), static_cast<Eigen::Index>(rows.size() / 4), 3,
                            Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>(4, 1));
}

void check_hostile_voxels() {
    const double inf = std::numeric_limits<double>::infinity();
    const double nan = std::numeric_limits<double>::quiet_NaN();
    disco::Points3d points;
    expect(disco::voxel_downsample(points, 0.5).empty(), "voxel_downsample of no points");
    points.emplace_back(1.0, 2.0, 3.0);
    const disco::Points3d one = disco::voxel_downsample(points, 0.5);
    expect(one.size() == 1 && one[0] == points[0], "voxel_downsample of one point");
    for (double v : {nan, inf, -inf, 1e300, -1e300, 3e9, -3e9, 0.5, -0.5, 0.0})
        points.emplace_back(v, v, 1.0);
    for (double voxel : {0.5, 1e-300, 1e300}) {
        const disco::Points3d out = disco::voxel_downsample(points, voxel);
        expect(!out.empty() && out.size() <= points.size(), "voxel_downsample of hostile points");
    }
    // A grid over points on cell edges and far away: lookups anywhere return a point
    // within the radius or -1, never an index out of range.
    disco::Points3d grid_points = {{0, 0, 0}, {1, 0, 0}, {-1, -1, -1}, {1e12, 0, 0}, {0, -1e12, 5}};
    const disco::NeighborGrid grid(grid_points, 1.0);
    int found = 0;
    for (double q : {0.0, 1.0, -1.0, 0.999999, 1e12, -1e12, 1e300, -1e300, nan, inf}) {
        double d2 = 0.0;
        const int i = grid.nearest(Eigen::Vector3d(q, 0.0, 0.0), &d2);
        expect(i >= -1 && i < static_cast<int>(grid_points.size()), "nearest index in range");
        if (i >= 0) {
            expect((grid_points[i] - Eigen::Vector3d(q, 0, 0)).squaredNorm() <= 1.0,
                   "nearest within the radius");
            ++found;
        }
        std::vector<int> within;
        grid.within(Eigen::Vector3d(q, q, q), &within);
        for (int w : within) expect(w >= 0 && w < static_cast<int>(grid_points.size()), "within");
    }
    std::printf("hostile voxels               found %d\n", found);
}

void check_hostile_icp() {
    const std::vector<float> rows = hostile_cloud();
    const std::vector<float> empty;
    const std::vector<float> one = {1.0f, 2.0f, 0.5f, 0.0f};
    int results = 0;
    for (double max_range : {60.0, 0.0}) {  // 0: keep every finite point, however far
        disco::IcpConfig config;
        config.max_range = max_range;
        for (const std::vector<float>* target : {&rows, &empty, &one}) {
            const disco::PlaneTarget plane(view_of(*target), config);
            for (const std::vector<float>* source : {&rows, &empty, &one}) {
                const disco::Points3d src = disco::prepare_source(view_of(*source), config);
                for (double shift : {0.0, 0.25, 1e12, std::numeric_limits<double>::quiet_NaN()}) {
                    Eigen::Matrix4d initial = Eigen::Matrix4d::Identity();
                    initial(0, 3) = shift;
                    const disco::IcpResult r = plane.align(src, initial);
                    expect(r.fitness >= 0.0 && r.fitness <= 1.0 && r.inliers >= 0 &&
                               r.inliers <= r.source_points,
                           "icp result in range");
                    ++results;
                }
            }
        }
    }
    for (double yaw : {0.0, 1.0}) {
        const auto image = disco::height_image(view_of(rows), yaw, 0.5, 20.0);
        expect(image.rows() == 80 && image.allFinite(), "height image of hostile points");
    }
    std::printf("hostile icp                  results %d\n", results);
}

void check_hostile_int8() {
    const std::int64_t d = 8;
    std::vector<float> x = {std::numeric_limits<float>::quiet_NaN(),
                            std::numeric_limits<float>::infinity(),
                            -std::numeric_limits<float>::infinity(),
                            3e38f, -3e38f, 0.0f, 1.0f, -1.0f};
    for (int i = 0; i < 8; ++i) x.push_back(static_cast<float>(i) * 0.25f);
    std::vector<double> mean(d, 0.0), scale(d, 0.01);
    std::vector<std::int8_t> codes(16);
    std::vector<double> code_sq(2), code_norm(2), err(2);
    disco::int8_encode(x.data(), 2, d, mean.data(), scale.data(), codes.data(), code_sq.data(),
                       code_norm.data(), err.data(), 1);
    disco::int8_encode(x.data(), 0, d, mean.data(), scale.data(), codes.data(), code_sq.data(),
                       code_norm.data(), err.data(), 4);
    for (std::int8_t c : codes) expect(c != -128, "int8 codes in -127..127");
    disco::Int8Rows table{codes.data(), 2, d, code_sq.data(), code_norm.data(), err.data()};
    const int limit = disco::int8_query_limit(d);
    std::vector<std::int16_t> g(d, static_cast<std::int16_t>(limit));
    disco::Int8Query query{g.data(), 1.0, 0.001, 0.0};
    const std::uint8_t exclude[2] = {1, 0};
    std::size_t total = 0;
    for (int k : {-1, 0, 1, 2, 5}) {
        for (std::int64_t lim : {std::int64_t{-3}, std::int64_t{0}, std::int64_t{1},
                                 std::int64_t{2}, std::int64_t{1} << 40}) {
            for (const std::uint8_t* ex : {static_cast<const std::uint8_t*>(nullptr), exclude}) {
                const auto rows = disco::int8_candidates(table, query, k, lim, ex, 3);
                for (std::int64_t r : rows) expect(r >= 0 && r < 2, "candidate row in range");
                total += rows.size();
            }
        }
    }
    disco::Int8Rows none{codes.data(), 0, d, code_sq.data(), code_norm.data(), err.data()};
    expect(disco::int8_candidates(none, query, 3, 10, nullptr, 2).empty(), "no rows, no candidates");
    // At d = 1 int32 allows any int16 g: the bound is the VNNI kernel's split of g into
    // two int8 halves, 256 hi + lo with both at most 127.
    expect(disco::int8_query_limit(0) >= 1 && disco::int8_query_limit(1) == 127 * 256 + 127 &&
               disco::int8_query_limit(std::int64_t{1} << 40) == 1,
           "int8 query limit");
    std::printf("hostile int8                 candidates %zu\n", total);
}

void check_hostile_raycast() {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const double inf = std::numeric_limits<double>::infinity();
    int refused = 0;
    // Worlds too large for the cell size, or with non-finite primitives: refused.
    for (double v : {1e12, 1e300, inf, nan}) {
        disco::Primitive p;
        p.cx = v;
        p.hx = p.hy = p.hz = 1.0;
        disco::Primitive q;
        q.hx = q.hy = q.hz = 1.0;
        try {
            const disco::RaycastWorld world({p, q}, disco::GroundPlane{}, 1.0);
        } catch (const std::invalid_argument&) {
            ++refused;
        }
    }
    for (double cell : {0.0, -1.0, nan}) {
        try {
            const disco::RaycastWorld world({}, disco::GroundPlane{}, cell);
        } catch (const std::invalid_argument&) {
            ++refused;
        }
    }
    // Rays of zero, NaN and huge directions, from far and non-finite origins.
    disco::Primitive box;
    box.cx = 5.0;
    box.hx = box.hy = box.hz = 1.0;
    const float fnan = std::numeric_limits<float>::quiet_NaN();
    const std::vector<float> dirs = {1, 0, 0,  0, 0, 0,  fnan, 0, 0,  0, 0, -1,
                                     3e38f, 3e38f, 0,  -1, 0, 0,  0, 1, 0};
    const auto n = static_cast<std::int64_t>(dirs.size() / 3);
    int hits = 0;
    for (const auto& prims : {std::vector<disco::Primitive>{}, std::vector<disco::Primitive>{box}}) {
        const disco::RaycastWorld world(prims, disco::GroundPlane{0.0, 0.0, -1.7}, 2.0);
        for (const Eigen::Vector3d& origin :
             {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(1e12, -1e12, 0),
              Eigen::Vector3d(nan, 0, 0), Eigen::Vector3d(inf, 0, 0), Eigen::Vector3d(5, 0, 0)}) {
            for (double max_range : {0.0, 100.0, 1e300}) {
                std::vector<float> range(n), cosi(n);
                std::vector<std::int32_t> id(n);
                world.cast(origin, dirs.data(), n, max_range, 7, range.data(), id.data(),
                           cosi.data());
                for (std::int64_t i = 0; i < n; ++i) {
                    expect(id[i] >= disco::kMiss && id[i] < static_cast<int>(prims.size()),
                           "ray hit id in range");
                    hits += id[i] >= 0;
                }
            }
        }
    }
    std::printf("hostile raycast              refused %d hits %d\n", refused, hits);
}

// Times each kernel on 30k points: random ones within +-45 m, or the first 30k
// of a KITTI .bin file (float32 x, y, z, intensity) given after --bench.
int bench(const char* path, int level_only) {
    std::vector<float> rows;
    if (path) {
        std::FILE* f = std::fopen(path, "rb");
        if (!f) {
            std::perror(path);
            return 1;
        }
        rows.resize(4 * 200000);
        rows.resize(4 * (std::fread(rows.data(), 16, 200000, f)));
        std::fclose(f);
        // Every 4th point: a sparser scan in the same order.
        std::vector<float> picked;
        for (std::size_t i = 0; i < rows.size() / 4 && picked.size() < 4 * 30000; i += 4)
            picked.insert(picked.end(), rows.begin() + 4 * i, rows.begin() + 4 * i + 4);
        rows = picked;
    } else {
        const std::vector<double> xyz = random_scan(3, 30000);
        rows.assign(4 * 30000, 0.0f);
        for (std::size_t i = 0; i < 30000; ++i) {
            for (int k = 0; k < 3; ++k) rows[4 * i + k] = static_cast<float>(xyz[3 * i + k] * 0.5);
        }
    }
    const disco::BEVConfig c;
    for (int level = disco::bev_kernel_level(); level >= 0; --level) {
        if (level_only >= 0 && level != level_only) continue;
        disco::set_bev_kernel_level(level);
        std::vector<double> times;
        for (int rep = 0; rep < 1000; ++rep) {
            const auto t0 = std::chrono::steady_clock::now();
            run_bev(rows, 4, c);
            times.push_back(
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0)
                    .count());
        }
        std::sort(times.begin(), times.end());
        std::printf("%-8s %zu points: median %.4f ms, min %.4f ms (1000 calls)\n",
                    disco::bev_kernel_name(level), rows.size() / 4, times[times.size() / 2],
                    times[0]);
    }
    return 0;
}

}  // namespace

// Re-centred views: bilinear reads agree with the formula by hand; a place outside the
// image (negative, past either end, NaN, huge) throws instead of reading.
void check_resample() {
    // 19 cells: two blocks of eight for the vector kernel and three for its tail.
    const std::int64_t width = 5, rows = 4, cells = 19;
    std::vector<float> padded(static_cast<std::size_t>(width * rows));
    for (std::size_t i = 0; i < padded.size(); ++i) padded[i] = static_cast<float>(i * i % 7);
    std::vector<float> places(2 * cells);  // (ring, sector) places inside the limits
    for (std::int64_t c = 0; c < cells; ++c) {
        places[c] = std::fmod(0.37f * static_cast<float>(c), 2.9f);
        places[cells + c] = std::fmod(0.53f * static_cast<float>(c), 3.9f);
    }
    std::vector<float> out(cells);
    disco::resample_views(padded.data(), static_cast<std::int64_t>(padded.size()), width,
                          {places.data()}, cells, out.data());
    for (std::int64_t c = 0; c < cells; ++c) {
        const float rf = places[c], sf = places[cells + c];
        const std::int64_t r0 = static_cast<std::int64_t>(rf), s0 = static_cast<std::int64_t>(sf);
        const float fr = rf - static_cast<float>(r0), fs = sf - static_cast<float>(s0);
        const std::int64_t k = r0 * width + s0;
        const float near = padded[k] + (padded[k + 1] - padded[k]) * fs;
        const float far = padded[k + width] + (padded[k + width + 1] - padded[k + width]) * fs;
        expect(out[c] == near + (far - near) * fr, "resample: bilinear read");
    }
    std::printf("resample                     %9.3f %9.3f %9.3f\n", out[0], out[9], out[18]);
    const float nan = std::numeric_limits<float>::quiet_NaN();
    const float inf = std::numeric_limits<float>::infinity();
    for (std::int64_t at : {std::int64_t{1}, std::int64_t{17}}) {  // vector block, tail
        for (float bad : {-0.5f, 3.0f, 4.5f, nan, 3e9f, inf, -inf}) {
            for (int which : {0, 1}) {
                std::vector<float> p = places;
                // rings stop below 3 (rows - 1), sectors below 4 (width - 1)
                p[which * cells + at] = (which == 1 && bad == 3.0f) ? 4.0f : bad;
                bool thrown = false;
                try {
                    disco::resample_views(padded.data(), static_cast<std::int64_t>(padded.size()),
                                          width, {p.data()}, cells, out.data());
                } catch (const std::out_of_range&) {
                    thrown = true;
                }
                expect(thrown, "resample: a place outside the image throws");
            }
        }
    }
}

int main(int argc, char** argv) {
    if (argc > 1 && std::strcmp(argv[1], "--bench") == 0)
        return bench(argc > 2 ? argv[2] : nullptr, argc > 3 ? std::atoi(argv[3]) : -1);
    std::printf("# kernels here:");
    for (int level = disco::bev_kernel_level(); level >= 0; --level)
        std::printf(" %s", disco::bev_kernel_name(level));
    std::printf("\n");

    const disco::BEVConfig base;
    for (int mode = 0; mode < 3; ++mode) {
        disco::BEVConfig c = base;
        c.mode = static_cast<disco::BEVMode>(mode);
        const std::string m = std::to_string(mode);
        for (std::uint64_t seed = 1; seed <= 4; ++seed)
            check_bev("random seed " + std::to_string(seed) + " mode " + m,
                      random_scan(seed, 20003), c);
        check_bev("edges mode " + m, edge_points(c), c);
        check_bev("window runs mode " + m, window_runs(c), c);
    }
    disco::BEVConfig odd;  // another grid: 7 rings, 360 sectors, 3 layers, no min range
    odd.rings = 7;
    odd.sectors = 360;
    odd.heights = 3;
    odd.max_range = 50.0;
    odd.min_range = 0.0;
    check_bev("odd grid random", random_scan(11, 10000), odd);
    check_bev("odd grid edges", edge_points(odd), odd);
    check_bev("odd grid window runs", window_runs(odd), odd);
    disco::BEVConfig big;  // >= 2^24 cells: the plain kernel's integer cell index
    big.rings = 4096;
    big.sectors = 4097;
    big.heights = 1;
    big.mode = disco::BEVMode::kDensity;
    check_bev("big grid random", random_scan(12, 5000), big);

    disco::BEVConfig c = base;
    check_bev("no points", {}, c);
    check_bev("one point", {12.5, -3.25, 1.0}, c);
    std::vector<double> far;
    for (double v : {1e300, -1e300, 3e9, -3e9, 1e20})
        far.insert(far.end(), {v, 1.0, 1.0, 1.0, v, 1.0, v, v, v});
    check_bev("far points", far, c);

    check_voxel_downsample();
    check_int8_encode();
    check_raycast();
    check_hostile_voxels();
    check_hostile_icp();
    check_hostile_int8();
    check_hostile_raycast();
    check_resample();
    g_failures += disco_check::check_kernels(&g_checksum);
    std::printf("checksum %016llx\n", static_cast<unsigned long long>(g_checksum));
    if (g_failures) {
        std::fprintf(stderr, "%d failures\n", g_failures);
        return 1;
    }
    return 0;
}
