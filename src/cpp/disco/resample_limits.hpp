#pragma once

#include <cstdint>

namespace disco {

// The limits that keep all four reads of a bilinear corner inside a polar image of `rows`
// x `width`: ring < rows - 1 and sector < width - 1. The places are checked as floats
// (NaN fails every comparison) before any cast. Shared by polar_resample.cpp and
// recentre_curves.cpp, whose reads must refuse the same places.
struct Limits {
    float ring, sector;

    static Limits of(std::int64_t rows, std::int64_t width) {
        return {static_cast<float>(rows - 1), static_cast<float>(width - 1)};
    }
    bool holds(float rf, float sf) const {
        return rf >= 0.0f && rf < ring && sf >= 0.0f && sf < sector;
    }
};

// Throws the out_of_range of a read outside the limits, `kernel` naming the caller in the
// message (polar_resample.cpp; out of line, so the kernels' loops carry only a call).
[[noreturn]] void outside(const char* kernel);

}  // namespace disco
