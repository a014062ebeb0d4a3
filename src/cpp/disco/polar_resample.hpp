#pragma once
// Views of a polar image re-centred on other sensor positions (disco_cli/model/
// yaw_refine.py): every cell of a view is a bilinear read of the image at a place worked
// out beforehand in Python, where each position's places are computed once and kept.
#include <cstdint>
#include <vector>

namespace disco {

// One view's places: for each of `cells` output cells, the flat index i0 of its corner
// (ring r0, sector s0) in the padded image, and the fractions fs (along sectors) and
// fr (along rings) as float32 bit patterns, stored as int32 [3, cells].
using ResamplePlaces = const std::int32_t*;

// out[v, c] for every view v of `places` and cell c:
//   near = p[i0] + (p[i0 + 1] - p[i0]) * fs,  far = the same one ring (`width`) further,
//   out  = near + (far - near) * fr,
// in float32 with each operation rounded as written (the same values as NumPy's).
// `padded` holds `padded_size` floats; an index outside it throws std::out_of_range.
void resample_views(const float* padded, std::int64_t padded_size, std::int64_t width,
                    const std::vector<ResamplePlaces>& places, std::int64_t cells, float* out);

}  // namespace disco
