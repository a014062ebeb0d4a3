#pragma once
// The phase-correlation curves of a polar image re-centred on many positions against
// one match (disco_cli/model/yaw_refine.py): each view resampled as polar_resample.hpp
// reads it, its spectrum along sectors taken (sector_fft.hpp), the cross-power with
// the match's spectrum whitened as yaw.curves_of_cross_power does, rings summed with
// their weights, and transformed back: one call for all the views of a search round.
// The views are read from a table of each corner's four values (recentre_table), made
// once per query.
#include <cstdint>
#include <vector>

namespace disco {

struct RecentreImage {
    // recentre_table of the query's padded table (yaw_refine._padded): rows of `width`
    // floats, `rows` of them.
    const float* quads;
    std::int64_t rows, width;
    std::int64_t rings, sectors;
    // The views' rings padded to whole vectors: a multiple of 16 (every SIMD level's
    // lanes), at least `rings`.
    std::int64_t rings_padded;
};

// The four reads of every corner of a padded table [rows][width]: quads[(s (rows - 1)
// + r) * 4 + (0, 1, 2, 3)] = p[r][s], p[r][s + 1], p[r + 1][s], p[r + 1][s + 1], for
// r < rows - 1 and s < width - 1 ((rows - 1) (width - 1) * 4 floats): one 16-byte read
// per cell instead of gathers, sector-major as the views' cells are, so that the rings
// of one sector read neighbouring memory.
void recentre_table(const float* padded, std::int64_t rows, std::int64_t width, float* quads);

// curves[v, s] (float32 [views][sectors]) for each view v of `places`. A view's places
// are float32 [2][sectors][rings]: for cell (sector, ring), the fractional ring and
// sector it reads in the padded table, as polar_resample.hpp's places but sector-major.
// Per view:
//   X[r, k] = rfft of the view's ring r along sectors, M[r, k] the match's,
//   C = X conj(M), floor = 1e-3 max |C| + 1e-12 (in float32, as NumPy rounds it),
//   Y[k] = sum over r of C weight[r] / (|C| + floor), the rings summed in 16 lanes
//          (ring r in lane r mod 16, in order) and the lanes in halves (8, 4, 2, 1),
//   curve = irfft(Y, sectors).
// `spectrum` is recentre_match's of the match, `weights` float32 [rings]. Every SIMD
// level gives the same values to the bit. A place outside the table (ring >= rows - 1,
// sector >= width - 1, negative or not finite) throws std::out_of_range.
void recentre_curves(const RecentreImage& image, const std::vector<const float*>& places,
                     const float* spectrum, const float* weights, float* curves);

// The plain normalized correlation of one view (its places as recentre_curves') turned
// by -shift sectors with the match, both centred, from sums in double precision:
// yaw_refine._aligned_ncc. `match_sectors` is the match transposed, [sectors][rings].
double recentre_ncc(const RecentreImage& image, const float* places,
                    const float* match_sectors, std::int64_t shift);

// The match's spectrum M for recentre_curves: `match` float32 [rings][sectors] in,
// 2 (sectors / 2 + 1) rings_padded floats out (the same at every level).
void recentre_match(const RecentreImage& image, const float* match, float* spectrum);

}  // namespace disco
