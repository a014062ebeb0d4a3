// Each row's k smallest values (row_selection.hpp). A strided sample first gives a
// threshold that, on any row whose values are not laid out against the sample, at
// least k values stay under: only those few are selected from, and ties go to the lower
// column. Where fewer than k stay under it, the whole row is selected from.
#include "disco/row_selection.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

namespace disco {

namespace {

using Entry = std::pair<float, std::int64_t>;  // (value, column): compared in that order

constexpr std::int64_t kStride = 16;  // every 16th value is sampled
constexpr std::int64_t kMargin = 4;   // the sample's threshold aims at 4 k values under it

// The finite values of row[0, n) at or below `limit`, as entries.
void collect(const float* row, std::int64_t n, float limit, std::vector<Entry>& out) {
    out.clear();
    for (std::int64_t j = 0; j < n; ++j)
        if (row[j] <= limit && row[j] > -std::numeric_limits<float>::infinity())
            out.emplace_back(row[j], j);
}

}  // namespace

void smallest_per_row(const float* values, std::int64_t b, std::int64_t n, std::int64_t k,
                      std::int64_t* out) {
    if (k <= 0) return;
    const float inf = std::numeric_limits<float>::infinity();
    const std::int64_t take = kMargin * k / kStride + 1;
    std::vector<float> sample;
    std::vector<Entry> found;
    for (std::int64_t i = 0; i < b; ++i) {
        const float* row = values + i * n;
        float limit = std::numeric_limits<float>::max();  // every finite value
        if (n >= 4 * kStride * take) {
            sample.clear();
            for (std::int64_t j = 0; j < n; j += kStride)
                sample.push_back(std::isfinite(row[j]) ? row[j] : inf);
            std::nth_element(sample.begin(), sample.begin() + (take - 1), sample.end());
            if (std::isfinite(sample[take - 1])) limit = sample[take - 1];
        }
        collect(row, n, limit, found);
        if (static_cast<std::int64_t>(found.size()) < k && limit < std::numeric_limits<float>::max())
            collect(row, n, std::numeric_limits<float>::max(), found);  // the sample misled
        const auto kept = std::min<std::int64_t>(k, static_cast<std::int64_t>(found.size()));
        if (kept < static_cast<std::int64_t>(found.size()))
            std::nth_element(found.begin(), found.begin() + (kept - 1), found.end());
        std::sort(found.begin(), found.begin() + kept);
        std::int64_t* dst = out + i * k;
        for (std::int64_t c = 0; c < k; ++c) dst[c] = c < kept ? found[c].second : -1;
    }
}

}  // namespace disco
