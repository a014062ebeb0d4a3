#include "disco/voxel_grid.hpp"

namespace disco {

Points3d voxel_downsample(const Points3d& points, double voxel) {
    const double inv = 1.0 / voxel;
    VoxelIndex index(points.size() / 4);
    std::vector<Eigen::Vector4d> sums;  // x, y, z, count
    sums.reserve(points.size() / 4);
    for (const auto& p : points) {
        const Eigen::Vector3i v = voxel_of(p, inv);
        const int slot = index.insert(pack_voxel(v.x(), v.y(), v.z()));
        if (slot == static_cast<int>(sums.size())) sums.emplace_back(Eigen::Vector4d::Zero());
        sums[slot] += Eigen::Vector4d(p.x(), p.y(), p.z(), 1.0);
    }
    Points3d out;
    out.reserve(sums.size());
    for (const auto& s : sums) out.emplace_back(s.head<3>() / s.w());
    return out;
}

NeighborGrid::NeighborGrid(const Points3d& points, double radius)
    : points_(&points), radius_(radius), inv_cell_(1.0 / (2.0 * radius)), index_(points.size()) {
    // Counting sort of the points by cell: slots first, then offsets.
    std::vector<int> slot_of(points.size());
    std::vector<int> count;
    for (std::size_t i = 0; i < points.size(); ++i) {
        const Eigen::Vector3i v = voxel_of(points[i], inv_cell_);
        const int slot = index_.insert(pack_voxel(v.x(), v.y(), v.z()));
        if (slot == static_cast<int>(count.size())) count.push_back(0);
        ++count[slot];
        slot_of[i] = slot;
    }
    start_.assign(count.size() + 1, 0);
    for (std::size_t s = 0; s < count.size(); ++s) start_[s + 1] = start_[s] + count[s];
    std::vector<int> fill(start_.begin(), start_.end() - 1);
    order_.resize(points.size());
    for (std::size_t i = 0; i < points.size(); ++i) order_[fill[slot_of[i]]++] = static_cast<int>(i);
}

template <typename Visit>
void NeighborGrid::visit_block(const Eigen::Vector3d& q, Visit&& visit) const {
    // With cells of edge 2r, the ball of radius r around q spans at most two
    // cells per axis: q's own and the neighbour on the side q is nearer to.
    const Eigen::Vector3d c = q * inv_cell_;
    const Eigen::Vector3d f = c.array().floor();
    int lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
        const int base = static_cast<int>(f[a]);
        if (c[a] - f[a] < 0.5) {
            lo[a] = base - 1;
            hi[a] = base;
        } else {
            lo[a] = base;
            hi[a] = base + 1;
        }
    }
    for (int x = lo[0]; x <= hi[0]; ++x)
        for (int y = lo[1]; y <= hi[1]; ++y)
            for (int z = lo[2]; z <= hi[2]; ++z) {
                const int slot = index_.find(pack_voxel(x, y, z));
                if (slot < 0) continue;
                for (int k = start_[slot]; k < start_[slot + 1]; ++k) visit(order_[k]);
            }
}

int NeighborGrid::nearest(const Eigen::Vector3d& q, double* d2) const {
    int best = -1;
    double best_d2 = radius_ * radius_;
    visit_block(q, [&](int i) {
        const double d = ((*points_)[i] - q).squaredNorm();
        if (d <= best_d2) {
            best_d2 = d;
            best = i;
        }
    });
    if (d2 != nullptr) *d2 = best_d2;
    return best;
}

void NeighborGrid::within(const Eigen::Vector3d& q, std::vector<int>* out) const {
    out->clear();
    const double r2 = radius_ * radius_;
    visit_block(q, [&](int i) {
        if (((*points_)[i] - q).squaredNorm() <= r2) out->push_back(i);
    });
}

}  // namespace disco
