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
    : points_(&points), radius_(radius), inv_cell_(1.0 / radius), index_(points.size()) {
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
    for (std::size_t i = 0; i < points.size(); ++i)
        order_[fill[slot_of[i]]++] = static_cast<int>(i);
}

template <typename Visit>
void NeighborGrid::visit_cells(const Eigen::Vector3d& q, const double* bound2,
                               Visit&& visit) const {
    // Cells have edge r, so the ball of radius r around q lies in the 3 x 3 x 3
    // block around q's cell. q's own cell goes first; a neighbour is skipped when
    // its box is farther from q than *bound2 (which `visit` may shrink).
    const Eigen::Vector3d c = q * inv_cell_;
    const Eigen::Vector3d f = c.array().floor();
    const Eigen::Vector3d frac = c - f;
    const int bx = voxel_index(c.x()), by = voxel_index(c.y()), bz = voxel_index(c.z());
    const double cell2 = radius_ * radius_;
    // Squared gap from q to the neighbouring slab on each side, per axis (in cells^2 * cell2).
    double gap[3][3];
    for (int a = 0; a < 3; ++a) {
        gap[a][0] = frac[a] * frac[a] * cell2;
        gap[a][1] = 0.0;
        gap[a][2] = (1.0 - frac[a]) * (1.0 - frac[a]) * cell2;
    }
    auto scan = [&](int x, int y, int z) {
        const int slot = index_.find(pack_voxel(bx + x, by + y, bz + z));
        if (slot < 0) return;
        for (int k = start_[slot]; k < start_[slot + 1]; ++k) visit(order_[k]);
    };
    scan(0, 0, 0);
    for (int x = -1; x <= 1; ++x)
        for (int y = -1; y <= 1; ++y)
            for (int z = -1; z <= 1; ++z) {
                if (x == 0 && y == 0 && z == 0) continue;
                if (gap[0][x + 1] + gap[1][y + 1] + gap[2][z + 1] > *bound2) continue;
                scan(x, y, z);
            }
}

int NeighborGrid::nearest(const Eigen::Vector3d& q, double* d2) const {
    int best = -1;
    double best_d2 = radius_ * radius_;
    visit_cells(q, &best_d2, [&](int i) {
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
    visit_cells(q, &r2, [&](int i) {
        if (((*points_)[i] - q).squaredNorm() <= r2) out->push_back(i);
    });
}

}  // namespace disco
