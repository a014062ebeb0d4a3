// The polar multi-layer bird's-eye-view (BEV) voxelizer of DiSCO.
//
// A scan's points fall into cells indexed by (height, ring, sector):
//   r      = sqrt(x^2 + y^2), kept when min_range <= r < max_range
//   ring   = floor(r / (max_range / rings))
//   theta  = atan2(y, x), plus 2*pi when negative, so theta is in [0, 2*pi]
//   sector = floor(theta / (2*pi / sectors))   (sector 0 starts at +x, counter-clockwise)
//   height = floor((z - z_min) / ((z_max - z_min) / heights)), kept when z_min <= z < z_max
// all in double precision; each index is clamped into range after the floor, so
// a point that rounds onto the far edge (theta -> 2*pi) stays in the last cell.
// Rotating a scan by +k * 360 / sectors degrees about z rolls the BEV by +k sectors.
// NaN and Inf points are dropped. Plain C++17 and Eigen; no Python here.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <variant>
#include <vector>

namespace disco {

// What each cell holds.
enum class BEVMode : int {
    kOccupancy = 0,  // 1 where a cell holds a point, else 0
    kDensity = 1,    // point count / the scan's largest cell count, in [0, 1]
    kMaxHeight = 2,  // one layer: z - z_min of the cell's top point (0 where empty)
};

struct BEVConfig {
    int rings = 40;
    int sectors = 120;
    int heights = 20;
    double max_range = 80.0;
    double min_range = 3.0;  // drops the ego vehicle
    double z_min = -1.5;
    double z_max = 18.5;
    BEVMode mode = BEVMode::kOccupancy;

    // Throws std::invalid_argument naming the bad field.
    void validate() const;
    // Layers of the output: heights, or 1 for kMaxHeight.
    int layers() const { return mode == BEVMode::kMaxHeight ? 1 : heights; }
    std::size_t cells() const {
        return static_cast<std::size_t>(layers()) * static_cast<std::size_t>(rings) *
               static_cast<std::size_t>(sectors);
    }
};

// A row-major view of points (x, y, z in the first three columns; more columns are
// ignored) with arbitrary positive strides, so a KITTI N x 4 float32 array is read
// in place.
template <typename T>
using BEVPointsView =
    Eigen::Map<const Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>,
               Eigen::Unaligned, Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>>;
using AnyBEVPointsView = std::variant<BEVPointsView<float>, BEVPointsView<double>>;

// Writes the BEV of one scan into out[layers][rings][sectors] (every cell written).
void polar_bev(const BEVPointsView<float>& points, const BEVConfig& config, float* out);
void polar_bev(const BEVPointsView<double>& points, const BEVConfig& config, float* out);

// The BEVs of many scans, out[scan][layers][rings][sectors], on `threads` threads
// (0: all cores). Each scan gives exactly what polar_bev gives.
void polar_bev_batch(const std::vector<AnyBEVPointsView>& scans, const BEVConfig& config,
                     float* out, int threads = 0);

// The fast-path kernel in use. x86-64: 3 AVX-512F, 2 AVX2+FMA (both chosen at run
// time when the CPU has them), 1 SSE2 (the x86-64 baseline); aarch64: 1 NEON (part of
// every aarch64 CPU); everywhere: 0 plain, portable C++ that the compiler vectorizes.
// Every kernel gives identical BEVs; capping the level lets tests check each one and
// benchmarks compare them. set_bev_kernel_level returns the previous cap. Grids of
// 2^24 cells or more always use the plain kernel (the others form the cell index in
// float). The cap also holds for the U-Net convolutions (conv3x3.cpp), the int8
// signature scan (int8_search.cpp) and the polar resampling (polar_resample.cpp):
// their AVX2 paths run only at level 2 or above (the convolutions' AVX-512 at 3).
int set_bev_kernel_level(int cap);
int bev_kernel_level();
// "avx512", "avx2", "sse2", "neon" or "plain": the kernel of `level` on this build and
// CPU (-1: the level in use); "" for a level that does not exist here.
const char* bev_kernel_name(int level = -1);
// "avx512" (3), "avx2" (2) or "plain" (else): the name of a kernel with only those three
// paths at `level`, the names the search and U-Net kernels report.
const char* wide_kernel_name(int level);

}  // namespace disco
