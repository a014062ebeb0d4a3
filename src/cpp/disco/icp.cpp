#include "disco/icp.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>

namespace disco {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// exp of a twist (rotation vector w, translation v) as a rigid transform; the
// first-order translation is enough for the small steps of Gauss-Newton.
Eigen::Matrix4d twist_exp(const Eigen::Matrix<double, 6, 1>& d) {
    Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
    const Eigen::Vector3d w = d.head<3>();
    const double angle = w.norm();
    if (angle > 1e-12) T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(angle, w / angle).matrix();
    T.topRightCorner<3, 1>() = d.tail<3>();
    return T;
}

// Keep the rotation orthonormal after many small updates.
void reorthonormalize(Eigen::Matrix4d* T) {
    Eigen::Quaterniond q(Eigen::Matrix3d(T->topLeftCorner<3, 3>()));
    q.normalize();
    T->topLeftCorner<3, 3>() = q.toRotationMatrix();
}

}  // namespace

Points3d crop_points(const CloudView& points, double max_range) {
    Points3d out;
    out.reserve(static_cast<std::size_t>(points.rows()));
    const double r2 =
        max_range > 0.0 ? max_range * max_range : std::numeric_limits<double>::infinity();
    for (Eigen::Index i = 0; i < points.rows(); ++i) {
        const Eigen::Vector3d p(points(i, 0), points(i, 1), points(i, 2));
        if (!p.allFinite() || p.squaredNorm() > r2) continue;
        out.push_back(p);
    }
    return out;
}

Points3d prepare_source(const CloudView& points, const IcpConfig& config) {
    return voxel_downsample(crop_points(points, config.max_range), config.source_voxel);
}

PlaneTarget::PlaneTarget(const CloudView& points, const IcpConfig& config) : config_(config) {
    const Points3d cropped = crop_points(points, config.max_range);
    points_ = voxel_downsample(cropped, config.target_voxel);

    // Normals from the covariance of the full-resolution points in each cell of
    // edge normal_radius: one small eigenproblem per cell rather than a
    // neighbour search per point, and many more points behind each normal.
    const double inv = 1.0 / config.normal_radius;
    VoxelIndex cells(cropped.size() / 8);
    struct Moments {
        Eigen::Vector3d sum = Eigen::Vector3d::Zero();
        Eigen::Matrix3d outer = Eigen::Matrix3d::Zero();
        int n = 0;
    };
    std::vector<Moments> moments;
    const auto key_of = [inv](const Eigen::Vector3d& p) {
        const Eigen::Vector3i v = voxel_of(p, inv);
        return pack_voxel(v.x(), v.y(), v.z());
    };
    for (const auto& p : cropped) {
        const int slot = cells.insert(key_of(p));
        if (slot == static_cast<int>(moments.size())) moments.emplace_back();
        // Moments about the cell's corner keep the sums small and well conditioned.
        const Eigen::Vector3d d = p - (p * inv).array().floor().matrix() * config.normal_radius;
        moments[slot].sum += d;
        moments[slot].outer.noalias() += d * d.transpose();
        ++moments[slot].n;
    }
    std::vector<Eigen::Vector3d> cell_normal(moments.size(), Eigen::Vector3d::Constant(kNaN));
    for (std::size_t c = 0; c < moments.size(); ++c) {
        const Moments& m = moments[c];
        if (m.n < config.normal_min_neighbors) continue;
        const Eigen::Vector3d mean = m.sum / m.n;
        const Eigen::Matrix3d cov = m.outer / m.n - mean * mean.transpose();
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
        eig.computeDirect(cov);
        // A line of points (one scan ring) has no defined normal: two tiny eigenvalues.
        if (eig.eigenvalues()(1) < 1e-3 * eig.eigenvalues()(2)) continue;
        cell_normal[c] = eig.eigenvectors().col(0);
    }
    normals_.resize(points_.size());
    for (std::size_t i = 0; i < points_.size(); ++i) {
        const int slot = cells.find(key_of(points_[i]));
        normals_[i] = slot >= 0 ? cell_normal[slot] : Eigen::Vector3d::Constant(kNaN);
    }

    stage_grids_.reserve(config.stages.size());
    for (double d : config.stages) stage_grids_.emplace_back(points_, d);
    inlier_grid_ = NeighborGrid(points_, config.inlier_distance);
}

IcpResult PlaneTarget::align(const Points3d& source, const Eigen::Matrix4d& initial,
                             int first_stage, int last_stage, int max_iterations) const {
    IcpResult result;
    result.transform = initial;
    result.source_points = static_cast<int>(source.size());
    result.target_points = static_cast<int>(points_.size());
    if (source.empty() || points_.empty()) return result;

    Eigen::Matrix4d T = initial;
    using Vec6 = Eigen::Matrix<double, 6, 1>;
    using Mat6 = Eigen::Matrix<double, 6, 6>;
    const int n_stages = static_cast<int>(stage_grids_.size());
    const int end = last_stage < 0 ? n_stages : std::min(last_stage, n_stages);
    for (int s = std::max(first_stage, 0); s < end; ++s) {
        const NeighborGrid& grid = stage_grids_[s];
        // Geman-McClure scale: a third of the stage's correspondence distance.
        const double k2 = std::pow(config_.stages[s] / 3.0, 2);
        const int iterations = max_iterations < 0 ? config_.max_iterations : max_iterations;
        for (int it = 0; it < iterations; ++it) {
            ++result.iterations;
            const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
            const Eigen::Vector3d t = T.topRightCorner<3, 1>();
            Mat6 H = Mat6::Zero();
            Vec6 b = Vec6::Zero();
            int used = 0;
            for (const auto& p : source) {
                const Eigen::Vector3d q = R * p + t;
                double d2 = 0.0;
                const int j = grid.nearest(q, &d2);
                if (j < 0) continue;
                const Eigen::Vector3d& n = normals_[j];
                if (!n.allFinite()) continue;
                const double r = n.dot(q - points_[j]);
                const double w = std::pow(k2 / (k2 + r * r), 2);
                Vec6 J;
                J.head<3>() = q.cross(n);  // d(n . (exp(dw) q + dv)) / dw = q x n
                J.tail<3>() = n;
                H.noalias() += w * J * J.transpose();
                b.noalias() += w * r * J;
                ++used;
            }
            if (used < 6) break;
            // A touch of Levenberg damping keeps degenerate scenes (corridors) solvable.
            H.diagonal().array() += 1e-6 * H.trace() / 6.0 + 1e-9;
            const Vec6 delta = H.ldlt().solve(-b);
            if (!delta.allFinite()) break;
            T = twist_exp(delta) * T;
            reorthonormalize(&T);
            if (delta.head<3>().norm() < config_.convergence &&
                delta.tail<3>().norm() < config_.convergence)
                break;
        }
    }
    result.transform = T;

    // Score: inliers within inlier_distance; ground-like landing surfaces are
    // judged with the coarsest grid, so that points on flat ground count
    // as ground whether or not they are inliers.
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    const Eigen::Vector3d t = T.topRightCorner<3, 1>();
    const NeighborGrid& coarse = stage_grids_.empty() ? inlier_grid_ : stage_grids_.front();
    int structure = 0, structure_inliers = 0;
    double sq = 0.0;
    for (const auto& p : source) {
        const Eigen::Vector3d q = R * p + t;
        const int c = coarse.nearest(q, nullptr);
        const bool ground =
            c >= 0 && normals_[c].allFinite() && std::abs(normals_[c].z()) > config_.horizontal_cos;
        structure += ground ? 0 : 1;
        double d2 = 0.0;
        const int j = inlier_grid_.nearest(q, &d2);
        if (j < 0) continue;
        ++result.inliers;
        structure_inliers += ground ? 0 : 1;
        const Eigen::Vector3d& n = normals_[j];
        const double r = n.allFinite() ? n.dot(q - points_[j]) : std::sqrt(d2);
        sq += r * r;
    }
    result.fitness_all = static_cast<double>(result.inliers) / static_cast<double>(source.size());
    result.fitness = structure > 0 ? static_cast<double>(structure_inliers) / structure : 0.0;
    result.rmse = result.inliers > 0 ? std::sqrt(sq / result.inliers) : kNaN;
    return result;
}

Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> height_image(
    const CloudView& points, double yaw, double cell, double half_extent) {
    const int n = std::max(1, static_cast<int>(std::lround(2.0 * half_extent / cell)));
    Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> lo(n, n), hi(n, n);
    lo.setConstant(std::numeric_limits<float>::infinity());
    hi.setConstant(-std::numeric_limits<float>::infinity());
    const double c = std::cos(yaw), s = std::sin(yaw), inv = 1.0 / cell;
    for (Eigen::Index i = 0; i < points.rows(); ++i) {
        const double x = points(i, 0), y = points(i, 1);
        const float z = points(i, 2);
        if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) continue;
        const double u = (c * x - s * y + half_extent) * inv;
        const double v = (s * x + c * y + half_extent) * inv;
        if (!(u >= 0.0 && u < n && v >= 0.0 && v < n)) continue;
        const auto r = static_cast<Eigen::Index>(u), k = static_cast<Eigen::Index>(v);
        lo(r, k) = std::min(lo(r, k), z);
        hi(r, k) = std::max(hi(r, k), z);
    }
    // The extent in double, saturated to float's range: z of +-3e38 in one cell must
    // not make an Inf that the phase correlation would spread over the whole image.
    const auto extent = (hi.array().cast<double>() - lo.array().cast<double>())
                            .min(static_cast<double>(std::numeric_limits<float>::max()))
                            .cast<float>();
    Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> out =
        (hi.array() > lo.array()).select(extent, 0.0f).matrix();
    return out;
}

}  // namespace disco
