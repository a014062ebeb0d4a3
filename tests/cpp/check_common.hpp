// What check_core.cpp and check_kernels.cpp share: the seeded generator and the hash
// of output bytes, both the same on every platform.
#pragma once
#include <cstddef>
#include <cstdint>

namespace disco_check {

struct Rng {  // splitmix64: the same sequence on every platform
    std::uint64_t s;
    std::uint64_t next() {
        std::uint64_t z = (s += 0x9E3779B97F4A7C15ull);
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
        z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
        return z ^ (z >> 31);
    }
    // A multiple of 2^-16 in [lo, hi): exact in float for |value| < 256.
    double uniform(double lo, double hi) {
        const auto steps = static_cast<std::uint64_t>((hi - lo) * 65536.0);
        return lo + static_cast<double>(next() % steps) / 65536.0;
    }
};

inline std::uint64_t fnv1a(const void* data, std::size_t bytes,
                           std::uint64_t h = 1469598103934665603ull) {
    const auto* p = static_cast<const unsigned char*>(data);
    for (std::size_t i = 0; i < bytes; ++i) h = (h ^ p[i]) * 1099511628211ull;
    return h;
}

// check_kernels.cpp's checks: prints their lines, returns the number of failures and
// folds every printed hash into *checksum.
int check_kernels(std::uint64_t* checksum);

}  // namespace disco_check
