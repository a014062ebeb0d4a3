#include "disco/polar_resample.hpp"

#include <cstring>
#include <stdexcept>

namespace disco {

namespace {
float float_of_bits(std::int32_t bits) {
    float f;
    std::memcpy(&f, &bits, sizeof f);
    return f;
}
}  // namespace

void resample_views(const float* padded, std::int64_t padded_size, std::int64_t width,
                    const std::vector<ResamplePlaces>& places, std::int64_t cells, float* out) {
    // The largest corner index whose four reads stay inside the image.
    const std::int64_t last = padded_size - width - 2;
    for (std::size_t v = 0; v < places.size(); ++v) {
        const std::int32_t* i0 = places[v];
        const std::int32_t* fs = i0 + cells;
        const std::int32_t* fr = i0 + 2 * cells;
        float* o = out + static_cast<std::int64_t>(v) * cells;
        for (std::int64_t c = 0; c < cells; ++c) {
            const std::int64_t k = i0[c];
            if (k < 0 || k > last) throw std::out_of_range("resample_views: index outside the image");
            const float s = float_of_bits(fs[c]);
            const float a0 = padded[k], a1 = padded[k + 1];
            const float b0 = padded[k + width], b1 = padded[k + width + 1];
            const float near = a0 + (a1 - a0) * s;
            const float far = b0 + (b1 - b0) * s;
            o[c] = near + (far - near) * float_of_bits(fr[c]);
        }
    }
}

}  // namespace disco
