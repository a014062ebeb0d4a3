#include "disco/sector_fft.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <utility>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels
#include "disco/simd_lanes.hpp"

namespace disco {

namespace {

// exp(-2 pi i r / len) in double, rounded to float; the quarter turns exact, so that a
// real row's spectrum has the exact zeros it should.
std::pair<float, float> unit(std::int64_t r, std::int64_t len) {
    r %= len;
    if ((4 * r) % len == 0) {
        switch ((4 * r) / len) {
            case 0: return {1.0f, 0.0f};
            case 1: return {0.0f, -1.0f};
            case 2: return {-1.0f, 0.0f};
            default: return {0.0f, 1.0f};
        }
    }
    const double a = 2.0 * 3.14159265358979323846 * static_cast<double>(r) /
                     static_cast<double>(len);
    return {static_cast<float>(std::cos(a)), static_cast<float>(-std::sin(a))};
}

std::vector<SectorPlan::Stage> make_stages(int n) {
    std::vector<SectorPlan::Stage> stages;
    std::vector<int> radices;
    int rest = n;
    while (rest % 4 == 0) radices.push_back(4), rest /= 4;
    while (rest % 2 == 0) radices.push_back(2), rest /= 2;
    for (int p = 3; p * p <= rest; p += 2)
        while (rest % p == 0) radices.push_back(p), rest /= p;
    if (rest > 1) radices.push_back(rest);
    int len = n;
    for (int p : radices) {
        SectorPlan::Stage g;
        g.radix = p;
        g.len = len;
        const int m = len / p;
        for (int j = 0; j < m; ++j)
            for (int u = 1; u < p; ++u) {
                const auto w = unit(static_cast<std::int64_t>(j) * u, len);
                g.wr.push_back(w.first);
                g.wi.push_back(w.second);
            }
        for (int r = 0; r < p; ++r) {  // cos and sin (not -sin) of 2 pi r / p
            const auto w = unit(r, p);
            g.pc.push_back(w.first);
            g.ps.push_back(-w.second);
        }
        stages.push_back(std::move(g));
        len = m;
    }
    return stages;
}

SectorPlan make_plan(int n) {
    SectorPlan plan;
    plan.n = n;
    plan.stages = make_stages(n);
    if (n % 2 == 0) {
        plan.half = make_stages(n / 2);
        for (int k = 0; k <= n / 2; ++k) {
            const auto w = unit(k, n);
            plan.hr.push_back(w.first);
            plan.hi.push_back(w.second);
        }
    }
    return plan;
}

// Namespaces plain, sse2, avx2 and avx512: the body compiled at each level.
#define DISCO_LEVELS_BODY "disco/sector_fft.inc"
#include "disco/simd_levels.inc"
#undef DISCO_LEVELS_BODY

void check_length(std::int64_t n, std::int64_t rows) {
    if (n < 1 || n > (1 << 20) || rows < 0)
        throw std::invalid_argument("sector_fft: the length must be in [1, 2^20], rows >= 0");
}

}  // namespace

const SectorPlan& sector_plan(int n) {
    static std::mutex lock;
    static std::map<int, std::unique_ptr<SectorPlan>> plans;
    std::lock_guard<std::mutex> hold(lock);
    auto& slot = plans[n];
    if (!slot) slot = std::make_unique<SectorPlan>(make_plan(n));
    return *slot;
}

int sector_fft_level() {
#if DISCO_SIMD_X86
    return bev_kernel_level();  // 3 AVX-512, 2 AVX2, 1 SSE2 (x86-64's baseline), 0 plain
#else
    return 0;
#endif
}

int sector_fft_lanes(int level) {
    static const int lanes[] = {1, 4, 8, 16};
    return lanes[std::max(0, std::min(level, 3))];
}

void rfft_rows(const float* in, std::int64_t rows, std::int64_t n, float* out) {
    check_length(n, rows);
    const SectorPlan& plan = sector_plan(static_cast<int>(n));
    switch (sector_fft_level()) {
#if DISCO_SIMD_X86
        case 3: return avx512::rfft_rows(plan, in, rows, out);
        case 2: return avx2::rfft_rows(plan, in, rows, out);
        case 1: return sse2::rfft_rows(plan, in, rows, out);
#endif
        default: return plain::rfft_rows(plan, in, rows, out);
    }
}

void irfft_rows(const float* in, std::int64_t rows, std::int64_t n, float* out) {
    check_length(n, rows);
    const SectorPlan& plan = sector_plan(static_cast<int>(n));
    switch (sector_fft_level()) {
#if DISCO_SIMD_X86
        case 3: return avx512::irfft_rows(plan, in, rows, out);
        case 2: return avx2::irfft_rows(plan, in, rows, out);
        case 1: return sse2::irfft_rows(plan, in, rows, out);
#endif
        default: return plain::irfft_rows(plan, in, rows, out);
    }
}

}  // namespace disco
