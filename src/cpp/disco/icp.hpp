#pragma once
// Point-to-plane ICP for the relative pose between two scans, plus the
// Cartesian height image that seeds its translation by phase correlation.
//
// The target (the match scan) is prepared once: cropped, voxel-downsampled,
// normals from the covariance of the full-resolution points in each point's
// cell, one neighbour grid per correspondence distance. Each alignment of a source (the query scan)
// then runs Gauss-Newton on SE(3) with a Geman-McClure kernel, coarse to fine
// over the correspondence distances, and scores the result.

#include <Eigen/Core>
#include <vector>

#include "disco/voxel_grid.hpp"

namespace disco {

// N x C float32 points (C >= 3; x, y, z first) with any strides: a NumPy view.
using CloudView =
    Eigen::Map<const Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>, 0,
               Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>>;

struct IcpConfig {
    double source_voxel = 1.0;     // query downsampling (m)
    double target_voxel = 0.5;     // match downsampling (m)
    double max_range = 60.0;       // drop points farther from the sensor (m); <= 0 keeps all
    double normal_radius = 1.0;    // cell edge for the target normals (m)
    int normal_min_neighbors = 5;  // fewer points in a cell: no normal there
    // Maximum correspondence distance of each coarse-to-fine stage (m).
    std::vector<double> stages = {2.0, 1.0, 0.5};
    int max_iterations = 15;       // per stage
    double convergence = 5e-4;     // stop a stage when the update is smaller (rad and m)
    double inlier_distance = 0.5;  // a source point is an inlier within this distance (m)
    // A surface with |normal_z| above this is ground-like: left out of `fitness`,
    // since any two flat grounds overlap whether the places match or not.
    double horizontal_cos = 0.9;
};

struct IcpResult {
    Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  // target <- source
    double fitness = 0.0;      // inlier ratio over the source points not on ground-like surfaces
    double fitness_all = 0.0;  // inlier ratio over all source points
    double rmse = 0.0;         // RMS point-to-plane distance of the inliers (m)
    int iterations = 0;
    int source_points = 0;  // after cropping and downsampling
    int target_points = 0;
    int inliers = 0;
};

// Finite points within the range, as doubles (the first three columns).
Points3d crop_points(const CloudView& points, double max_range);

class PlaneTarget {
  public:
    PlaneTarget(const CloudView& points, const IcpConfig& config);

    // Align the (cropped, downsampled) source to the target, starting from
    // `initial`, through stages [first_stage, last_stage) (-1: to the last) of at most
    // max_iterations each (-1: the config's), then score.
    IcpResult align(const Points3d& source, const Eigen::Matrix4d& initial, int first_stage = 0,
                    int last_stage = -1, int max_iterations = -1) const;

    const Points3d& points() const { return points_; }
    const Points3d& normals() const { return normals_; }  // NaN where too few neighbours

  private:
    IcpConfig config_;
    Points3d points_;
    Points3d normals_;
    std::vector<NeighborGrid> stage_grids_;
    NeighborGrid inlier_grid_;
};

// Source preparation with the same rules as the target's: crop, then downsample.
Points3d prepare_source(const CloudView& points, const IcpConfig& config);

// Bird's-eye height image of the points turned by `yaw` (rad) about z: an
// n x n grid of `cell`-metre cells over [-half_extent, half_extent)^2 (row = x,
// column = y), each cell holding max z - min z of its points (0 when empty).
// Vertical extent rather than occupancy, so that the ground rings around the
// sensor, which move with the sensor and not with the scene, stay dark.
Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> height_image(
    const CloudView& points, double yaw, double cell, double half_extent);

}  // namespace disco
