#pragma once
// Views of a polar image re-centred on other sensor positions (disco_cli/model/
// yaw_refine.py): every cell of a view is a bilinear read of the image at a place worked
// out beforehand in Python, where each position's places are computed once and kept.
#include <cstdint>
#include <vector>

namespace disco {

// One view's places: for each of `cells` output cells, where it reads in the padded
// image of rows of `width` as a fractional ring and sector, float32 [2, cells].
using ResamplePlaces = const float*;

// out[v, c] for every view v of `places` and cell c, with (ring, sector) its place:
//   r0 = int(ring), s0 = int(sector), fr = ring - r0, fs = sector - s0,
//   i0 = r0 * width + s0,
//   near = p[i0] + (p[i0 + 1] - p[i0]) * fs,  far = the same one ring (`width`) further,
//   out  = near + (far - near) * fr,
// in float32 with each operation rounded as written (the same values as NumPy's).
// `padded` holds `padded_size` floats (rows of `width`); a place that is negative, not
// finite, at ring >= rows - 1 or at sector >= width - 1 throws std::out_of_range.
void resample_views(const float* padded, std::int64_t padded_size, std::int64_t width,
                    const std::vector<ResamplePlaces>& places, std::int64_t cells, float* out);

}  // namespace disco
