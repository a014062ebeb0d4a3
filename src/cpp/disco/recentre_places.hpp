#pragma once
// Where each view of a polar image re-centred on a position reads it
// (disco_cli/model/yaw_refine.py: _places): per cell, the fractional ring and sector of
// the padded table, computed as NumPy computes them in float32 except for the arctan2,
// which is this file's own (relative error under 1e-12, in double, then rounded to float32).
#include <cstdint>

namespace disco {

struct PlacesGrid {
    // The cells' Cartesian centres (m), float32 [cells] each, in the order the places
    // are written (ring-major for NumPy's layout, sector-major for recentre_curves').
    const float* x;
    const float* y;
    std::int64_t cells;
    float ring_scale;    // float32(rings / max_range)
    float ring_cap;      // float32(rings + 1)
    float sector_scale;  // float32(sectors / (2 pi))
    float sector_shift;  // float32(sectors - 0.5)
};

// out [count][2][cells]: for position m (positions float32 [count][2], m) and cell c, with
// x = grid.x[c] + px and y = grid.y[c] + py in float32,
//   ring   = min(sqrt(x x + y y) ring_scale + 0.5, ring_cap)   (float32, in that order)
//   sector = float32(atan2(y, x)) sector_scale + sector_shift  (atan2 in double).
// Every SIMD level gives the same bits (only IEEE-rounded operations, no fusing).
void recentre_places(const PlacesGrid& grid, const float* positions, std::int64_t count,
                     float* out);

}  // namespace disco
