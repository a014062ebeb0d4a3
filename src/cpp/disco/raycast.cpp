#include "disco/raycast.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <thread>

namespace disco {
namespace {

constexpr double kEps = 1e-6;
constexpr double kInf = std::numeric_limits<double>::infinity();

// SplitMix64 finalizer: a cheap, well-mixed hash for per-ray random decisions.
std::uint64_t mix(std::uint64_t z) {
    z += 0x9e3779b97f4a7c15ULL;
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
}

double uniform01(std::uint64_t seed, std::uint64_t ray, std::uint64_t prim) {
    const std::uint64_t h = mix(mix(mix(seed) ^ ray) ^ (prim * 0x632be59bd9b4e019ULL));
    return static_cast<double>(h >> 11) * (1.0 / 9007199254740992.0);
}

// The cell of coordinate offset `v` (in cells) clamped to [0, n - 1], with the clamp
// done in double: an int cast of a far or NaN value is undefined (NaN: cell 0).
int cell_index(double v, int n) {
    if (!(v > 0.0)) return 0;
    if (!(v < static_cast<double>(n - 1))) return n - 1;
    return static_cast<int>(v);
}

// Smallest root t > eps of a t^2 + 2 b t + c = 0, or inf.
double first_root(double a, double b, double c) {
    const double disc = b * b - a * c;
    if (disc < 0 || a <= 0) return kInf;
    const double s = std::sqrt(disc);
    const double t0 = (-b - s) / a;
    if (t0 > kEps) return t0;
    const double t1 = (-b + s) / a;
    return t1 > kEps ? t1 : kInf;
}

}  // namespace

RaycastWorld::RaycastWorld(std::vector<Primitive> primitives, GroundPlane ground, double cell_size)
    : prims_(std::move(primitives)), ground_(ground), cell_(cell_size) {
    if (!(cell_ > 0)) throw std::invalid_argument("cell_size must be positive");
    for (const Primitive& p : prims_) {
        for (double v : {p.cx, p.cy, p.cz, p.hx, p.hy, p.hz, p.yaw, p.hit_prob})
            if (!std::isfinite(v)) throw std::invalid_argument("primitive values must be finite");
    }
    const std::size_t m = prims_.size();
    cos_yaw_.resize(m);
    sin_yaw_.resize(m);
    // x, y bounding boxes of every primitive.
    std::vector<double> bx0(m), by0(m), bx1(m), by1(m);
    double xmin = kInf, ymin = kInf, xmax = -kInf, ymax = -kInf;
    z_max_ = -kInf;
    for (std::size_t k = 0; k < m; ++k) {
        const Primitive& p = prims_[k];
        cos_yaw_[k] = std::cos(p.yaw);
        sin_yaw_[k] = std::sin(p.yaw);
        double ex = p.hx, ey = p.hx;
        if (p.kind == PrimitiveKind::Box) {
            const double c = std::abs(cos_yaw_[k]), s = std::abs(sin_yaw_[k]);
            ex = c * p.hx + s * p.hy;
            ey = s * p.hx + c * p.hy;
        }
        bx0[k] = p.cx - ex;
        bx1[k] = p.cx + ex;
        by0[k] = p.cy - ey;
        by1[k] = p.cy + ey;
        xmin = std::min(xmin, bx0[k]);
        xmax = std::max(xmax, bx1[k]);
        ymin = std::min(ymin, by0[k]);
        ymax = std::max(ymax, by1[k]);
        z_max_ = std::max(z_max_, p.cz + p.hz);
    }
    if (m == 0) {
        xmin = ymin = 0;
        xmax = ymax = cell_;
        z_max_ = -kInf;
    }
    x0_ = xmin - 1e-3;
    y0_ = ymin - 1e-3;
    // Sizes checked in double before the casts to int: a far or non-finite primitive
    // would overflow them.
    const double fx = std::max(1.0, std::ceil((xmax - x0_ + 1e-3) / cell_));
    const double fy = std::max(1.0, std::ceil((ymax - y0_ + 1e-3) / cell_));
    if (!(fx * fy <= 50'000'000.0))
        throw std::invalid_argument("world too large for this cell size");
    nx_ = static_cast<int>(fx);
    ny_ = static_cast<int>(fy);
    const std::size_t cells = static_cast<std::size_t>(nx_) * ny_;

    // Two passes into compressed rows: count, then fill.
    std::vector<std::int32_t> count(cells + 1, 0);
    cell_zmax_.assign(cells, -std::numeric_limits<float>::infinity());
    auto span = [&](std::size_t k, int& i0, int& i1, int& j0, int& j1) {
        i0 = cell_index((bx0[k] - x0_) / cell_, nx_);
        i1 = cell_index((bx1[k] - x0_) / cell_, nx_);
        j0 = cell_index((by0[k] - y0_) / cell_, ny_);
        j1 = cell_index((by1[k] - y0_) / cell_, ny_);
    };
    for (std::size_t k = 0; k < m; ++k) {
        int i0, i1, j0, j1;
        span(k, i0, i1, j0, j1);
        const float top = static_cast<float>(prims_[k].cz + prims_[k].hz);
        for (int j = j0; j <= j1; ++j)
            for (int i = i0; i <= i1; ++i) {
                const std::size_t c = static_cast<std::size_t>(j) * nx_ + i;
                ++count[c + 1];
                cell_zmax_[c] = std::max(cell_zmax_[c], top);
            }
    }
    for (std::size_t c = 0; c < cells; ++c) count[c + 1] += count[c];
    cell_start_ = count;
    cell_items_.resize(static_cast<std::size_t>(count[cells]));
    std::vector<std::int32_t> fill(count.begin(), count.end() - 1);
    for (std::size_t k = 0; k < m; ++k) {
        int i0, i1, j0, j1;
        span(k, i0, i1, j0, j1);
        for (int j = j0; j <= j1; ++j)
            for (int i = i0; i <= i1; ++i)
                cell_items_[fill[static_cast<std::size_t>(j) * nx_ + i]++] =
                    static_cast<std::int32_t>(k);
    }
}

bool RaycastWorld::intersect(std::size_t k, const Eigen::Vector3d& o, const Eigen::Vector3d& d,
                             double t_max, double& t, Eigen::Vector3d& normal) const {
    const Primitive& p = prims_[k];
    const Eigen::Vector3d rel(o.x() - p.cx, o.y() - p.cy, o.z() - p.cz);
    switch (p.kind) {
        case PrimitiveKind::Box: {
            // Into the box's frame (turn by -yaw), then the slab test.
            const double c = cos_yaw_[k], s = sin_yaw_[k];
            const double lo[3] = {c * rel.x() + s * rel.y(), -s * rel.x() + c * rel.y(), rel.z()};
            const double ld[3] = {c * d.x() + s * d.y(), -s * d.x() + c * d.y(), d.z()};
            const double h[3] = {p.hx, p.hy, p.hz};
            double t0 = -kInf, t1 = kInf;
            int axis0 = 0, axis1 = 0;
            double sign0 = 1, sign1 = 1;
            for (int a = 0; a < 3; ++a) {
                if (std::abs(ld[a]) < 1e-12) {
                    if (std::abs(lo[a]) > h[a]) return false;
                    continue;
                }
                const double inv = 1.0 / ld[a];
                double ta = (-h[a] - lo[a]) * inv, tb = (h[a] - lo[a]) * inv;
                double sa = -1;
                if (ta > tb) {
                    std::swap(ta, tb);
                    sa = 1;
                }
                if (ta > t0) {
                    t0 = ta;
                    axis0 = a;
                    sign0 = sa;
                }
                if (tb < t1) {
                    t1 = tb;
                    axis1 = a;
                    sign1 = -sa;
                }
                if (t0 > t1) return false;
            }
            int axis = axis0;
            double sign = sign0;
            t = t0;
            if (t <= kEps) {  // starts inside: the exit face
                t = t1;
                axis = axis1;
                sign = sign1;
            }
            if (t <= kEps || t >= t_max) return false;
            Eigen::Vector3d nl = Eigen::Vector3d::Zero();
            nl[axis] = sign;
            normal = Eigen::Vector3d(c * nl.x() - s * nl.y(), s * nl.x() + c * nl.y(), nl.z());
            return true;
        }
        case PrimitiveKind::Cylinder: {
            const double r = p.hx;
            double best = kInf;
            Eigen::Vector3d n_best;
            const double a = d.x() * d.x() + d.y() * d.y();
            if (a > 1e-12) {
                const double b = rel.x() * d.x() + rel.y() * d.y();
                const double cc = rel.x() * rel.x() + rel.y() * rel.y() - r * r;
                const double disc = b * b - a * cc;
                if (disc >= 0) {
                    const double sq = std::sqrt(disc);
                    for (double tc : {(-b - sq) / a, (-b + sq) / a}) {
                        if (tc <= kEps || tc >= best) continue;
                        const double z = rel.z() + tc * d.z();
                        if (std::abs(z) <= p.hz) {
                            best = tc;
                            n_best = Eigen::Vector3d(rel.x() + tc * d.x(), rel.y() + tc * d.y(), 0);
                        }
                    }
                }
            }
            if (std::abs(d.z()) > 1e-12) {  // the flat top and bottom
                for (double zc : {p.hz, -p.hz}) {
                    const double tc = (zc - rel.z()) / d.z();
                    if (tc <= kEps || tc >= best) continue;
                    const double x = rel.x() + tc * d.x(), y = rel.y() + tc * d.y();
                    if (x * x + y * y <= r * r) {
                        best = tc;
                        n_best = Eigen::Vector3d(0, 0, zc > 0 ? 1 : -1);
                    }
                }
            }
            if (best >= t_max) return false;
            t = best;
            normal = n_best;
            return true;
        }
        case PrimitiveKind::Ellipsoid: {
            // Scale to the unit sphere; t is unchanged by the scaling.
            const Eigen::Vector3d s(1.0 / p.hx, 1.0 / p.hx, 1.0 / p.hz);
            const Eigen::Vector3d so = rel.cwiseProduct(s), sd = d.cwiseProduct(s);
            const double tc = first_root(sd.squaredNorm(), so.dot(sd), so.squaredNorm() - 1.0);
            if (tc >= t_max) return false;
            t = tc;
            normal = (rel + tc * d).cwiseProduct(s).cwiseProduct(s);
            return true;
        }
    }
    return false;
}

void RaycastWorld::cast(const Eigen::Vector3d& origin, const float* dirs, std::int64_t n,
                        double max_range, std::uint64_t seed, float* range, std::int32_t* id,
                        float* cos_incidence) const {
    cast_from(origin.data(), 0, dirs, n, max_range, seed, range, id, cos_incidence);
}

void RaycastWorld::cast_from(const double* origins, int origin_stride, const float* dirs,
                             std::int64_t n, double max_range, std::uint64_t seed, float* range,
                             std::int32_t* id, float* cos_incidence) const {
    // Per-call mailbox: a primitive spanning several cells is tested once per ray.
    std::vector<std::uint32_t> stamp(prims_.size(), 0);
    std::uint32_t ray_stamp = 0;
    const Eigen::Vector3d ground_n(-ground_.a, -ground_.b, 1.0);
    const double gx1 = x0_ + nx_ * cell_, gy1 = y0_ + ny_ * cell_;

    for (std::int64_t r = 0; r < n; ++r) {
        const double* o = origins + origin_stride * r;
        const Eigen::Vector3d origin(o[0], o[1], o[2]);
        Eigen::Vector3d d(dirs[3 * r], dirs[3 * r + 1], dirs[3 * r + 2]);
        d.normalize();
        double t_best = max_range;
        std::int32_t hit = kMiss;
        Eigen::Vector3d n_best = Eigen::Vector3d::UnitZ();

        // The ground plane first: it bounds the walk through the grid.
        const double denom = d.z() - ground_.a * d.x() - ground_.b * d.y();
        if (denom < 0) {
            const double tg =
                (ground_.a * origin.x() + ground_.b * origin.y() + ground_.c - origin.z()) / denom;
            if (tg > kEps && tg < t_best) {
                t_best = tg;
                hit = kGround;
                n_best = ground_n;
            }
        }

        if (!prims_.empty()) {
            if (++ray_stamp == 0) {  // wrapped: clear the mailbox
                std::fill(stamp.begin(), stamp.end(), 0);
                ray_stamp = 1;
            }
            // Clip the ray's x, y footprint to the grid.
            double t_enter = 0, t_exit = t_best;
            const double o2[2] = {origin.x(), origin.y()}, d2[2] = {d.x(), d.y()};
            const double lo2[2] = {x0_, y0_}, hi2[2] = {gx1, gy1};
            bool inside = true;
            for (int a = 0; a < 2 && inside; ++a) {
                if (std::abs(d2[a]) < 1e-12) {
                    inside = o2[a] >= lo2[a] && o2[a] <= hi2[a];
                    continue;
                }
                double ta = (lo2[a] - o2[a]) / d2[a], tb = (hi2[a] - o2[a]) / d2[a];
                if (ta > tb) std::swap(ta, tb);
                t_enter = std::max(t_enter, ta);
                t_exit = std::min(t_exit, tb);
                inside = t_enter <= t_exit;
            }
            if (inside) {
                const double px = origin.x() + t_enter * d.x(), py = origin.y() + t_enter * d.y();
                int i = cell_index((px - x0_) / cell_, nx_);
                int j = cell_index((py - y0_) / cell_, ny_);
                const int step_i = d.x() > 0 ? 1 : -1, step_j = d.y() > 0 ? 1 : -1;
                const double dti = std::abs(d.x()) > 1e-12 ? cell_ / std::abs(d.x()) : kInf;
                const double dtj = std::abs(d.y()) > 1e-12 ? cell_ / std::abs(d.y()) : kInf;
                double tmi = kInf, tmj = kInf;  // t at the next x / y cell boundary
                if (std::abs(d.x()) > 1e-12)
                    tmi = (x0_ + (i + (step_i > 0 ? 1 : 0)) * cell_ - origin.x()) / d.x();
                if (std::abs(d.y()) > 1e-12)
                    tmj = (y0_ + (j + (step_j > 0 ? 1 : 0)) * cell_ - origin.y()) / d.y();
                double t_cell_in = t_enter;
                while (true) {
                    const double t_cell_out = std::min({tmi, tmj, t_exit});
                    // Skip cells whose objects all lie below the ray here.
                    const std::size_t c = static_cast<std::size_t>(j) * nx_ + i;
                    const double z_low =
                        origin.z() + std::min(t_cell_in * d.z(), t_cell_out * d.z());
                    if (z_low <= cell_zmax_[c]) {
                        for (std::int32_t q = cell_start_[c]; q < cell_start_[c + 1]; ++q) {
                            const std::int32_t k = cell_items_[q];
                            if (stamp[k] == ray_stamp) continue;
                            stamp[k] = ray_stamp;
                            double t;
                            Eigen::Vector3d nrm;
                            if (!intersect(k, origin, d, t_best, t, nrm)) continue;
                            const double p = prims_[k].hit_prob;
                            if (p < 1.0 && uniform01(seed, static_cast<std::uint64_t>(r),
                                                     static_cast<std::uint64_t>(k)) >= p)
                                continue;
                            t_best = t;
                            hit = k;
                            n_best = nrm;
                        }
                    }
                    if (t_best <= t_cell_out || t_cell_out >= t_exit) break;
                    if (d.z() > 0 && origin.z() + t_cell_out * d.z() > z_max_) break;  // above all
                    if (tmi < tmj) {
                        i += step_i;
                        tmi += dti;
                        if (i < 0 || i >= nx_) break;
                    } else {
                        j += step_j;
                        tmj += dtj;
                        if (j < 0 || j >= ny_) break;
                    }
                    t_cell_in = t_cell_out;
                }
            }
        }

        if (hit == kMiss) {
            range[r] = 0.0f;
            id[r] = kMiss;
            cos_incidence[r] = 0.0f;
        } else {
            range[r] = static_cast<float>(t_best);
            id[r] = hit;
            cos_incidence[r] = static_cast<float>(std::abs(n_best.normalized().dot(d)));
        }
    }
}

void cast_scans(const RaycastWorld& world, const double* poses, std::int64_t b, const float* dirs,
                std::int64_t n, double max_range, const std::uint64_t* seeds, int threads,
                float* range, std::int32_t* id, float* cos_incidence, const double* poses_end,
                const float* fractions) {
    auto work = [&](std::int64_t s, std::vector<float>& wdirs, std::vector<double>& origins) {
        const double* T = poses + 16 * s;
        const double* T1 = poses_end ? poses_end + 16 * s : T;
        for (std::int64_t r = 0; r < n; ++r) {
            const double x = dirs[3 * r], y = dirs[3 * r + 1], z = dirs[3 * r + 2];
            // A moving sensor: this ray leaves from where the sensor is when it fires.
            const double f = poses_end ? static_cast<double>(fractions[r]) : 0.0;
            for (int a = 0; a < 3; ++a) {
                const double d0 = T[4 * a] * x + T[4 * a + 1] * y + T[4 * a + 2] * z;
                const double d1 = T1[4 * a] * x + T1[4 * a + 1] * y + T1[4 * a + 2] * z;
                wdirs[3 * r + a] = static_cast<float>(d0 + f * (d1 - d0));
                origins[3 * r + a] = T[4 * a + 3] + f * (T1[4 * a + 3] - T[4 * a + 3]);
            }
        }
        world.cast_from(origins.data(), poses_end ? 3 : 0, wdirs.data(), n, max_range, seeds[s],
                        range + s * n, id + s * n, cos_incidence + s * n);
    };
    if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
    threads = static_cast<int>(std::min<std::int64_t>(threads, b));
    if (threads <= 1) {
        std::vector<float> wdirs(3 * n);
        std::vector<double> origins(3 * n);
        for (std::int64_t s = 0; s < b; ++s) work(s, wdirs, origins);
        return;
    }
    std::vector<std::thread> pool;
    for (int w = 0; w < threads; ++w)
        pool.emplace_back([&, w] {
            std::vector<float> wdirs(3 * n);
            std::vector<double> origins(3 * n);
            for (std::int64_t s = w; s < b; s += threads) work(s, wdirs, origins);
        });
    for (auto& th : pool) th.join();
}

}  // namespace disco
