#pragma once
// The phase-correlation curves of a polar image re-centred on many positions against
// one match (disco_cli/model/yaw_refine.py): each view resampled as polar_resample.hpp
// reads it, its spectrum along sectors taken (sector_fft.hpp), the cross-power with
// the match's spectrum whitened as yaw.curves_of_cross_power does, rings summed with
// their weights, and transformed back: one call for all the views of a search round.
#include <cstdint>
#include <vector>

namespace disco {

struct RecentreImage {
    const float* padded;       // the query's padded table (yaw_refine._padded), flat
    std::int64_t padded_size;  // its floats
    std::int64_t width;        // its row length (2 * sectors + 1)
    std::int64_t rings, sectors;
    // The views' rings padded to whole vectors: a multiple of 16 (every SIMD level's
    // lanes), at least `rings`.
    std::int64_t rings_padded;
};

// curves[v, s] (float32 [views][sectors]) for each view v of `places`. A view's places
// are float32 [2][sectors][rings_padded]: for cell (sector, ring), the fractional ring
// and sector it reads in `padded`, as polar_resample.hpp's places but sector-major, the
// padding rings reading (0, 0) (the zero ring in front; they hold 0). Per view:
//   X[r, k] = rfft of the view's ring r along sectors, M[r, k] the match's,
//   C = X conj(M), floor = 1e-3 max |C| + 1e-12 (in float32, as NumPy rounds it),
//   Y[k] = sum over r = 0 .. rings - 1 in order of C weight[r] / (|C| + floor),
//   curve = irfft(Y, sectors).
// `match` is float32 [rings][sectors], `weights` float32 [rings]. Every SIMD level gives
// the same values to the bit. A place outside the table throws std::out_of_range.
void recentre_curves(const RecentreImage& image, const std::vector<const float*>& places,
                     const float* match, const float* weights, float* curves);

}  // namespace disco
