#pragma once
// Ray casting for the synthetic LiDAR world (disco_cli.simulator).
//
// The world is a tilted ground plane plus a list of simple primitives: boxes
// turned about z (buildings, walls, cars, signs), vertical cylinders (poles,
// trunks) and vertical ellipsoids (tree crowns, bushes). A primitive may be
// partly see-through: a ray crossing it hits with probability `hit_prob`, decided
// by a hash of (scan seed, ray, primitive) so that the result does not depend on
// the order of work or the number of threads.
//
// Primitives are binned into a uniform 2D grid over x, y; a ray walks the cells
// it crosses (Amanatides-Woo DDA) and stops at the first cell whose far edge
// lies beyond the nearest hit found so far.

#include <Eigen/Core>
#include <cstdint>
#include <vector>

namespace disco {

enum class PrimitiveKind : int { Box = 0, Cylinder = 1, Ellipsoid = 2 };

struct Primitive {
    PrimitiveKind kind = PrimitiveKind::Box;
    // Centre; half sizes (box: x, y, z in its own frame; cylinder: radius, -, half
    // height; ellipsoid: horizontal radius, -, vertical radius); yaw about z (box).
    double cx = 0, cy = 0, cz = 0;
    double hx = 0, hy = 0, hz = 0;
    double yaw = 0;
    double hit_prob = 1.0;  // < 1: partly see-through (crowns, fences)
};

// z = a x + b y + c
struct GroundPlane {
    double a = 0, b = 0, c = 0;
};

// What one ray found. `id` is the primitive index, kGround or kMiss.
constexpr std::int32_t kGround = -1;
constexpr std::int32_t kMiss = -2;

class RaycastWorld {
  public:
    RaycastWorld(std::vector<Primitive> primitives, GroundPlane ground, double cell_size);

    // Casts `n` rays from `origin` along unit directions `dirs` (n x 3, world frame,
    // row-major). Writes the range (0 where nothing within max_range), the hit id
    // and |cos| of the incidence angle.
    void cast(const Eigen::Vector3d& origin, const float* dirs, std::int64_t n, double max_range,
              std::uint64_t seed, float* range, std::int32_t* id, float* cos_incidence) const;

    // The same with one origin per ray (`origins`, n x 3, row-major; stride 0: one
    // origin for all).
    void cast_from(const double* origins, int origin_stride, const float* dirs, std::int64_t n,
                   double max_range, std::uint64_t seed, float* range, std::int32_t* id,
                   float* cos_incidence) const;

    std::size_t size() const { return prims_.size(); }
    int grid_nx() const { return nx_; }
    int grid_ny() const { return ny_; }

  private:
    bool intersect(std::size_t k, const Eigen::Vector3d& o, const Eigen::Vector3d& d, double t_max,
                   double& t, Eigen::Vector3d& normal) const;

    std::vector<Primitive> prims_;
    std::vector<double> cos_yaw_, sin_yaw_;
    GroundPlane ground_;
    double cell_ = 4.0;
    double x0_ = 0, y0_ = 0;
    int nx_ = 0, ny_ = 0;
    double z_max_ = 0;                      // highest point of any primitive
    std::vector<std::int32_t> cell_start_;  // CSR: cell -> [start, end) in cell_items_
    std::vector<std::int32_t> cell_items_;
    std::vector<float> cell_zmax_;
};

// Casts the same ray pattern (sensor frame, n x 3) from `b` sensor poses (b x 4 x 4,
// row-major, sensor -> world); outputs are b x n. Scans are shared out over
// `threads` threads (0: all cores); scan i uses seeds[i].
// With `poses_end` (b x 4 x 4) and `fractions` (n), the sensor moves during the
// sweep: ray r leaves from the pose a fraction fractions[r] of the way from
// poses[i] to poses_end[i] (translation and ray direction interpolated linearly,
// fine for the few centimetres and tenths of a degree of one sweep).
void cast_scans(const RaycastWorld& world, const double* poses, std::int64_t b, const float* dirs,
                std::int64_t n, double max_range, const std::uint64_t* seeds, int threads,
                float* range, std::int32_t* id, float* cos_incidence,
                const double* poses_end = nullptr, const float* fractions = nullptr);

}  // namespace disco
