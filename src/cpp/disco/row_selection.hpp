#pragma once
// Picking each row's few smallest values out of many: the views' first pass keeps the
// k rows of the map whose approximate distances are smallest
// (disco_cli.maps.signature_index.finite_smallest_per_row), in a few microseconds a
// row of 10,000 where NumPy's partition of the whole row takes several times that.
#include <cstdint>

namespace disco {

// For each of b rows of values [b, n] (float32, row-major): the column indices of its
// k smallest finite values, ascending by (value, column), written to out [b, k];
// -1 past the finite values where a row has fewer than k. Infinities and NaN are
// never selected (they mark excluded columns).
void smallest_per_row(const float* values, std::int64_t b, std::int64_t n, std::int64_t k,
                      std::int64_t* out);

}  // namespace disco
