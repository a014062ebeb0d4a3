#pragma once
// Voxel hashing for the ICP: voxel-grid downsampling and a nearest-neighbour
// grid. A point's voxel is (floor(x / s), floor(y / s), floor(z / s)) packed
// into one 64-bit key; an open-addressing table maps keys to slots, so a lookup
// is a hash and a short linear probe, with no allocation per query.

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace disco {

using Points3d = std::vector<Eigen::Vector3d>;

// 21 bits per axis: +-1,048,576 voxels, i.e. +-100 km at 0.1 m.
inline std::int64_t pack_voxel(std::int64_t ix, std::int64_t iy, std::int64_t iz) {
    constexpr std::int64_t mask = (std::int64_t{1} << 21) - 1;
    return ((ix & mask) << 42) | ((iy & mask) << 21) | (iz & mask);
}

// floor(v) as an int, saturated at +-2^30 (NaN: the low end): a cast of a value
// beyond int's range is undefined, and pack_voxel keeps 21 bits of it anyway.
inline int voxel_index(double v) {
    constexpr double kLimit = 1 << 30;
    const double f = std::floor(v);
    if (!(f > -kLimit)) return -(1 << 30);
    if (!(f < kLimit)) return 1 << 30;
    return static_cast<int>(f);
}

inline Eigen::Vector3i voxel_of(const Eigen::Vector3d& p, double inv_size) {
    return {voxel_index(p.x() * inv_size), voxel_index(p.y() * inv_size),
            voxel_index(p.z() * inv_size)};
}

// Open-addressing hash table from a packed voxel key to a dense slot 0..size-1.
class VoxelIndex {
  public:
    explicit VoxelIndex(std::size_t expected = 0) { reserve(expected); }

    void reserve(std::size_t expected) {
        std::size_t capacity = 16;
        while (capacity < 2 * expected + 1) capacity <<= 1;
        keys_.assign(capacity, kEmpty);
        slots_.assign(capacity, -1);
        set_capacity(capacity);
        size_ = 0;
    }

    // The slot of `key`, inserting a new one (== size() before the call) when absent.
    int insert(std::int64_t key) {
        if (2 * (size_ + 1) > keys_.size()) grow();
        std::size_t i = hash(key);
        while (keys_[i] != kEmpty) {
            if (keys_[i] == key) return slots_[i];
            i = (i + 1) & mask_;
        }
        keys_[i] = key;
        slots_[i] = static_cast<int>(size_);
        return static_cast<int>(size_++);
    }

    // The slot of `key`, or -1.
    int find(std::int64_t key) const {
        std::size_t i = hash(key);
        while (keys_[i] != kEmpty) {
            if (keys_[i] == key) return slots_[i];
            i = (i + 1) & mask_;
        }
        return -1;
    }

    std::size_t size() const { return size_; }

  private:
    static constexpr std::int64_t kEmpty = std::numeric_limits<std::int64_t>::min();

    // Fibonacci hashing: the top bits of key * 2^64 / phi, which depend on every
    // bit of the key (the low bits of a product would see only the z index).
    std::size_t hash(std::int64_t key) const {
        return static_cast<std::size_t>((static_cast<std::uint64_t>(key) * 0x9E3779B97F4A7C15ull) >>
                                        shift_);
    }

    void set_capacity(std::size_t capacity) {
        mask_ = capacity - 1;
        shift_ = 64;
        while (capacity > 1) {
            capacity >>= 1;
            --shift_;
        }
    }

    void grow() {
        std::vector<std::int64_t> old_keys = std::move(keys_);
        std::vector<int> old_slots = std::move(slots_);
        keys_.assign(old_keys.size() * 2, kEmpty);
        slots_.assign(old_keys.size() * 2, -1);
        set_capacity(keys_.size());
        for (std::size_t j = 0; j < old_keys.size(); ++j) {
            if (old_keys[j] == kEmpty) continue;
            std::size_t i = hash(old_keys[j]);
            while (keys_[i] != kEmpty) i = (i + 1) & mask_;
            keys_[i] = old_keys[j];
            slots_[i] = old_slots[j];
        }
    }

    std::vector<std::int64_t> keys_;
    std::vector<int> slots_;
    std::size_t mask_ = 0;
    int shift_ = 64;
    std::size_t size_ = 0;
};

// The centroid of the points in each occupied voxel of edge `voxel`.
Points3d voxel_downsample(const Points3d& points, double voxel);

// Points bucketed by voxels of edge `radius`, so that every point within
// `radius` of a query lies in the 3 x 3 x 3 block of voxels around it.
class NeighborGrid {
  public:
    NeighborGrid() = default;
    NeighborGrid(const Points3d& points, double radius);

    // Index of the nearest point within the radius (squared distance in *d2), or -1.
    int nearest(const Eigen::Vector3d& q, double* d2) const;

    // Indices of all points within `radius` of q (cleared first).
    void within(const Eigen::Vector3d& q, std::vector<int>* out) const;

    double radius() const { return radius_; }

  private:
    template <typename Visit>
    void visit_cells(const Eigen::Vector3d& q, const double* bound2, Visit&& visit) const;

    const Points3d* points_ = nullptr;
    double radius_ = 0.0;
    double inv_cell_ = 0.0;
    VoxelIndex index_;
    std::vector<int> start_;  // cell slot -> first entry in order_
    std::vector<int> order_;  // point indices grouped by cell
};

}  // namespace disco
