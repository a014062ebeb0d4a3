#include "disco/int8_search.hpp"

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <mutex>
#include <thread>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define DISCO_X86 1
#endif

namespace disco {
namespace {

std::int32_t dot_scalar(const std::int8_t* c, const std::int16_t* g, std::int64_t d) {
    std::int32_t acc = 0;
    for (std::int64_t j = 0; j < d; ++j) acc += static_cast<std::int32_t>(c[j]) * g[j];
    return acc;
}

#ifdef DISCO_X86
// 16 codes at a time: widen int8 to int16, multiply-add pairs into int32 lanes.
__attribute__((target("avx2"))) std::int32_t dot_avx2(const std::int8_t* c, const std::int16_t* g,
                                                      std::int64_t d) {
    __m256i acc = _mm256_setzero_si256();
    std::int64_t j = 0;
    for (; j + 16 <= d; j += 16) {
        const __m128i c8 = _mm_loadu_si128(reinterpret_cast<const __m128i*>(c + j));
        const __m256i c16 = _mm256_cvtepi8_epi16(c8);
        const __m256i g16 = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(g + j));
        acc = _mm256_add_epi32(acc, _mm256_madd_epi16(c16, g16));
    }
    __m128i s = _mm_add_epi32(_mm256_castsi256_si128(acc), _mm256_extracti128_si256(acc, 1));
    s = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0x4E));
    s = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0xB1));
    std::int32_t total = _mm_cvtsi128_si32(s);
    for (; j < d; ++j) total += static_cast<std::int32_t>(c[j]) * g[j];
    return total;
}

bool have_avx2() {
    static const bool yes = __builtin_cpu_supports("avx2");
    return yes;
}
#endif

// Whether the AVX2 kernels run: the CPU has them and the level cap that the BEV
// kernels share (set_bev_kernel_level) allows level 2, so tests can force the plain
// kernels. Read once per call, never per row.
bool use_avx2() {
#ifdef DISCO_X86
    return bev_kernel_level() >= 2 && have_avx2();
#else
    return false;
#endif
}

using DotFn = std::int32_t (*)(const std::int8_t*, const std::int16_t*, std::int64_t);

DotFn pick_dot() {
#ifdef DISCO_X86
    if (use_avx2()) return dot_avx2;
#endif
    return dot_scalar;
}

// Runs body(begin, end) over [0, n) split into `threads` contiguous parts.
void parallel_rows(std::int64_t n, int threads,
                   const std::function<void(std::int64_t, std::int64_t)>& body) {
    // At least 4096 rows per thread: below that, starting a thread costs more than it saves.
    const auto most = static_cast<int>(std::max<std::int64_t>(1, n / 4096));
    threads = std::max(1, std::min(threads, most));
    if (threads == 1) {
        body(0, n);
        return;
    }
    std::vector<std::thread> pool;
    const std::int64_t part = (n + threads - 1) / threads;
    for (int t = 0; t < threads; ++t) {
        const std::int64_t a = t * part, b = std::min(n, a + part);
        if (a < b) pool.emplace_back(body, a, b);
    }
    for (auto& th : pool) th.join();
}

}  // namespace

int int8_query_limit(std::int64_t d) {
    // |c_j| <= 127; the sum of d products must stay within int32.
    const double cap = static_cast<double>(std::numeric_limits<std::int32_t>::max()) /
                       (127.0 * static_cast<double>(std::max<std::int64_t>(d, 1)));
    return static_cast<int>(std::max(1.0, std::min(32767.0, std::floor(cap))));
}

namespace {

// One row's codes and sums. `inline` body shared by the plain and the AVX2 build
// (where nearbyint becomes one rounding instruction and the loop vectorizes).
#define DISCO_ENCODE_ROW_BODY                                                 \
    double sq = 0.0, norm = 0.0, e = 0.0;                                     \
    for (std::int64_t j = 0; j < d; ++j) {                                    \
        const double centred = static_cast<double>(row[j]) - mean[j];         \
        const double v = std::min(127.0, std::max(-127.0, centred * inv[j])); \
        const double c = std::nearbyint(v);                                   \
        out[j] = static_cast<std::int8_t>(c);                                 \
        const double sc = c * scale[j];                                       \
        sq += sc * sc;                                                        \
        norm += c * c;                                                        \
        e += (centred - sc) * (centred - sc);                                 \
    }                                                                         \
    *code_sq = sq;                                                            \
    *code_norm = std::sqrt(norm);                                             \
    *err = std::sqrt(e);

using EncodeFn = void (*)(const float*, std::int64_t, const double*, const double*, const double*,
                          std::int8_t*, double*, double*, double*);

void encode_row_plain(const float* row, std::int64_t d, const double* mean, const double* scale,
                      const double* inv, std::int8_t* out, double* code_sq, double* code_norm,
                      double* err) {
    DISCO_ENCODE_ROW_BODY
}

#ifdef DISCO_X86
__attribute__((target("avx2,fma"))) void encode_row_avx2(const float* row, std::int64_t d,
                                                         const double* mean, const double* scale,
                                                         const double* inv, std::int8_t* out,
                                                         double* code_sq, double* code_norm,
                                                         double* err){DISCO_ENCODE_ROW_BODY}
#endif
#undef DISCO_ENCODE_ROW_BODY

EncodeFn pick_encode() {
#ifdef DISCO_X86
    if (use_avx2()) return encode_row_avx2;
#endif
    return encode_row_plain;
}

}  // namespace

void int8_encode(const float* x, std::int64_t n, std::int64_t d, const double* mean,
                 const double* scale, std::int8_t* codes, double* code_sq, double* code_norm,
                 double* err, int threads) {
    // Codes need not be the nearest: the error is measured from the code chosen.
    std::vector<double> inv(static_cast<std::size_t>(d));
    for (std::int64_t j = 0; j < d; ++j) inv[j] = 1.0 / scale[j];
    const EncodeFn encode = pick_encode();
    parallel_rows(n, threads, [&](std::int64_t a, std::int64_t b) {
        for (std::int64_t r = a; r < b; ++r)
            encode(x + r * d, d, mean, scale, inv.data(), codes + r * d, code_sq + r, code_norm + r,
                   err + r);
    });
}

std::vector<std::int32_t> int8_dots(const Int8Rows& rows, const std::int16_t* g, int threads) {
    std::vector<std::int32_t> out(static_cast<std::size_t>(rows.n));
    const DotFn dot = pick_dot();
    parallel_rows(rows.n, threads, [&](std::int64_t a, std::int64_t b) {
        for (std::int64_t r = a; r < b; ++r) out[r] = dot(rows.codes + r * rows.d, g, rows.d);
    });
    return out;
}

std::vector<std::int64_t> int8_candidates(const Int8Rows& rows, const Int8Query& query, int k,
                                          std::int64_t limit, const std::uint8_t* exclude,
                                          int threads) {
    const std::int64_t n = std::min(rows.n, std::max<std::int64_t>(limit, 0));
    std::vector<std::int64_t> out;
    if (n == 0 || k <= 0) return out;
    const DotFn dot = pick_dot();
    const double inf = std::numeric_limits<double>::infinity();
    // Rounding in the double arithmetic below is far under this relative margin.
    constexpr double kRel = 1e-9;
    // Per row: the squared lower bound of |q - x_hat| (inf when excluded). Reused across
    // calls so that a query allocates and faults in no fresh pages.
    static thread_local std::vector<double> low_sq;
    if (low_sq.size() < static_cast<std::size_t>(n)) low_sq.resize(static_cast<std::size_t>(n));
    double* lo = low_sq.data();
    // Each part keeps the k smallest upper bounds it saw (a max-heap), merged below.
    std::vector<double> all;
    std::mutex all_lock;
    parallel_rows(n, threads, [&](std::int64_t a, std::int64_t b) {
        std::vector<double> heap;
        heap.reserve(static_cast<std::size_t>(k) + 1);
        for (std::int64_t r = a; r < b; ++r) {
            if (exclude && exclude[r]) {
                lo[r] = inf;
                continue;
            }
            const double G = dot(rows.codes + r * rows.d, query.g, rows.d);
            const double A = query.u_sq - 2.0 * query.step * G + rows.code_sq[r];
            const double scale = query.u_sq + rows.code_sq[r] + 2.0 * std::abs(query.step * G);
            const double beta = 2.0 * query.delta_norm * rows.code_norm[r] + kRel * scale;
            lo[r] = std::max(A - beta, 0.0);
            const double up = std::sqrt(std::max(A + beta, 0.0)) + rows.err[r];
            if (static_cast<int>(heap.size()) < k) {
                heap.push_back(up);
                std::push_heap(heap.begin(), heap.end());
            } else if (up < heap.front()) {
                std::pop_heap(heap.begin(), heap.end());
                heap.back() = up;
                std::push_heap(heap.begin(), heap.end());
            }
        }
        const std::lock_guard<std::mutex> guard(all_lock);
        all.insert(all.end(), heap.begin(), heap.end());
    });
    if (all.empty()) return out;
    // Fewer than k allowed rows: every allowed row is a candidate.
    double cap = inf;
    if (static_cast<int>(all.size()) >= k) {
        std::nth_element(all.begin(), all.begin() + (k - 1), all.end());
        cap = all[static_cast<std::size_t>(k - 1)];
    }
    // Lower bound sqrt(lo) - err <= cap, squared on both sides (cap + err >= 0).
    for (std::int64_t r = 0; r < n; ++r) {
        if (lo[r] == inf) continue;
        const double reach = cap + rows.err[r];
        if (lo[r] <= reach * reach) out.push_back(r);
    }
    return out;
}

}  // namespace disco
