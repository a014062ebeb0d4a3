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

// The query's g as the kernels read it: int16 for the plain and AVX2 kernels; for the
// VNNI one also split as g = 256 hi + lo (both int8), since its instruction multiplies
// unsigned by signed bytes: it reads each code as c + 128 (c ^ 0x80) and takes
// 128 * sum(g) off again, so that G = 256 (hi . (c + 128)) + lo . (c + 128) - 128 sum(g),
// exactly the same integer.
struct DotQuery {
    const std::int16_t* g = nullptr;
    std::vector<std::int8_t> hi, lo;
    std::int64_t sum = 0;
};

// g . c for the rows [a, b) of codes [*, d] into out[r] (0 for an excluded row): one
// call per block of rows, so that the row kernel inlines into its loop.
using DotsFn = void (*)(const std::int8_t*, std::int64_t, std::int64_t, std::int64_t,
                        const std::uint8_t*, const DotQuery&, std::int32_t*);

void dots_scalar(const std::int8_t* codes, std::int64_t d, std::int64_t a, std::int64_t b,
                 const std::uint8_t* exclude, const DotQuery& q, std::int32_t* out) {
    for (std::int64_t r = a; r < b; ++r) {
        // Unsigned: the wrap of int32 (never reached within int8_query_limit) is defined.
        std::uint32_t acc = 0;
        if (!(exclude && exclude[r])) {
            const std::int8_t* c = codes + r * d;
            for (std::int64_t j = 0; j < d; ++j)
                acc += static_cast<std::uint32_t>(static_cast<std::int32_t>(c[j]) * q.g[j]);
        }
        out[r] = static_cast<std::int32_t>(acc);
    }
}

#ifdef DISCO_X86
// The SIMD kernels read this many rows, spaced evenly over the block, at a time: more
// streams in flight than one row's keep a single core nearer its memory bandwidth
// when the codes are not in cache, and in it too (four rows of the 10,000-scan map:
// 0.52 ms cold and 0.20 warm for the VNNI scan, against 0.79 and 0.28 one at a time).
constexpr int kStreams = 4;

// 16 codes at a time: widen int8 to int16, multiply-add pairs into int32 lanes; the
// rows r + s * h for s < S.
template <int S>
__attribute__((target("avx2"))) inline void rows_avx2(const std::int8_t* codes, std::int64_t d,
                                                      std::int64_t r, std::int64_t h,
                                                      const std::int16_t* g, std::int32_t* out) {
    __m256i acc[S];
    for (auto& v : acc) v = _mm256_setzero_si256();
    std::int64_t j = 0;
    for (; j + 16 <= d; j += 16) {
        const __m256i g16 = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(g + j));
        for (int s = 0; s < S; ++s) {
            const std::int8_t* c = codes + (r + s * h) * d + j;
            const __m256i c16 = _mm256_cvtepi8_epi16(
                _mm_loadu_si128(reinterpret_cast<const __m128i*>(c)));
            acc[s] = _mm256_add_epi32(acc[s], _mm256_madd_epi16(c16, g16));
        }
    }
    for (int s = 0; s < S; ++s) {
        __m128i v = _mm_add_epi32(_mm256_castsi256_si128(acc[s]),
                                  _mm256_extracti128_si256(acc[s], 1));
        v = _mm_add_epi32(v, _mm_shuffle_epi32(v, 0x4E));
        v = _mm_add_epi32(v, _mm_shuffle_epi32(v, 0xB1));
        auto total = static_cast<std::uint32_t>(_mm_cvtsi128_si32(v));
        const std::int8_t* c = codes + (r + s * h) * d;
        for (std::int64_t t = j; t < d; ++t)
            total += static_cast<std::uint32_t>(static_cast<std::int32_t>(c[t]) * g[t]);
        out[r + s * h] = static_cast<std::int32_t>(total);
    }
}

__attribute__((target("avx2"))) void dots_avx2(const std::int8_t* codes, std::int64_t d,
                                               std::int64_t a, std::int64_t b,
                                               const std::uint8_t* exclude, const DotQuery& q,
                                               std::int32_t* out) {
    const std::int64_t h = (b - a) / kStreams;
    for (std::int64_t r = a; r < a + h; ++r) rows_avx2<kStreams>(codes, d, r, h, q.g, out);
    for (std::int64_t r = a + kStreams * h; r < b; ++r) rows_avx2<1>(codes, d, r, 0, q.g, out);
    if (exclude)
        for (std::int64_t r = a; r < b; ++r)
            if (exclude[r]) out[r] = 0;
}

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
// GCC 12 warns inside its own avx512fintrin.h (_mm512_undefined_epi32): a false positive.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#endif
#define DISCO_VNNI __attribute__((target("avx512f,avx512bw,avx512vnni")))
// 64 codes at a time, two VPDPBUSD (unsigned codes times the signed halves of g) into
// int32 lanes; a last partial block through masked loads (zeros past d). All sums
// wrap modulo 2^32 and G itself lies within int32 (int8_query_limit), so the lanes
// may combine as 256 hi + lo before the one horizontal sum. The rows r + s * h, s < S.
template <int S>
DISCO_VNNI inline void rows_vnni(const std::int8_t* codes, std::int64_t d, std::int64_t r,
                                 std::int64_t h, const DotQuery& q, std::int32_t* out) {
    const __m512i flip = _mm512_set1_epi8(static_cast<char>(0x80));
    const std::int8_t* hi = q.hi.data();
    const std::int8_t* lo = q.lo.data();
    __m512i acc_hi[S], acc_lo[S];
    for (int s = 0; s < S; ++s) acc_hi[s] = acc_lo[s] = _mm512_setzero_si512();
    std::int64_t j = 0;
    for (; j + 64 <= d; j += 64) {
        const __m512i h8 = _mm512_loadu_si512(hi + j), l8 = _mm512_loadu_si512(lo + j);
        for (int s = 0; s < S; ++s) {
            const __m512i cu =
                _mm512_xor_si512(_mm512_loadu_si512(codes + (r + s * h) * d + j), flip);
            acc_hi[s] = _mm512_dpbusd_epi32(acc_hi[s], cu, h8);
            acc_lo[s] = _mm512_dpbusd_epi32(acc_lo[s], cu, l8);
        }
    }
    if (j < d) {
        const __mmask64 m = (__mmask64{1} << (d - j)) - 1;
        const __m512i h8 = _mm512_maskz_loadu_epi8(m, hi + j);
        const __m512i l8 = _mm512_maskz_loadu_epi8(m, lo + j);
        for (int s = 0; s < S; ++s) {
            const __m512i cu = _mm512_xor_si512(
                _mm512_maskz_loadu_epi8(m, codes + (r + s * h) * d + j), flip);
            acc_hi[s] = _mm512_dpbusd_epi32(acc_hi[s], cu, h8);
            acc_lo[s] = _mm512_dpbusd_epi32(acc_lo[s], cu, l8);
        }
    }
    const auto bias = static_cast<std::uint32_t>(128 * static_cast<std::uint64_t>(q.sum));
    for (int s = 0; s < S; ++s) {
        const __m512i v = _mm512_add_epi32(_mm512_slli_epi32(acc_hi[s], 8), acc_lo[s]);
        const __m256i v8 =
            _mm256_add_epi32(_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64(v, 1));
        __m128i t = _mm_add_epi32(_mm256_castsi256_si128(v8), _mm256_extracti128_si256(v8, 1));
        t = _mm_add_epi32(t, _mm_shuffle_epi32(t, 0x4E));
        t = _mm_add_epi32(t, _mm_shuffle_epi32(t, 0xB1));
        out[r + s * h] =
            static_cast<std::int32_t>(static_cast<std::uint32_t>(_mm_cvtsi128_si32(t)) - bias);
    }
}

DISCO_VNNI void dots_vnni(const std::int8_t* codes, std::int64_t d, std::int64_t a,
                          std::int64_t b, const std::uint8_t* exclude, const DotQuery& q,
                          std::int32_t* out) {
    const std::int64_t h = (b - a) / kStreams;
    for (std::int64_t r = a; r < a + h; ++r) rows_vnni<kStreams>(codes, d, r, h, q, out);
    for (std::int64_t r = a + kStreams * h; r < b; ++r) rows_vnni<1>(codes, d, r, 0, q, out);
    if (exclude)
        for (std::int64_t r = a; r < b; ++r)
            if (exclude[r]) out[r] = 0;
}
#undef DISCO_VNNI
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

bool have_avx2() {
    static const bool yes = __builtin_cpu_supports("avx2");
    return yes;
}

bool have_vnni() {
    static const bool yes = __builtin_cpu_supports("avx512f") &&
                            __builtin_cpu_supports("avx512bw") &&
                            __builtin_cpu_supports("avx512vnni");
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

// |g_j| up to this splits into int8 halves hi, lo (hi = round(g / 256)).
constexpr int kVnniMaxG = 127 * 256 + 127;

// The kernel for g: VNNI at level 3 where the CPU has it and g splits (always so
// within int8_query_limit), else AVX2 at level 2, else plain. Fills q's halves for
// the VNNI kernel.
DotsFn pick_dots(DotQuery& q, std::int64_t d) {
#ifdef DISCO_X86
    if (bev_kernel_level() >= 3 && have_vnni()) {
        bool fits = true;
        for (std::int64_t j = 0; j < d && fits; ++j) fits = std::abs(int{q.g[j]}) <= kVnniMaxG;
        if (fits) {
            q.hi.resize(static_cast<std::size_t>(d));
            q.lo.resize(static_cast<std::size_t>(d));
            q.sum = 0;
            for (std::int64_t j = 0; j < d; ++j) {
                const int g = q.g[j];
                const int hi = (g >= 0 ? g + 128 : g - 127) / 256;  // rounds half away
                q.hi[j] = static_cast<std::int8_t>(hi);
                q.lo[j] = static_cast<std::int8_t>(g - 256 * hi);
                q.sum += g;
            }
            return dots_vnni;
        }
    }
    if (use_avx2()) return dots_avx2;
#else
    (void)d;
#endif
    return dots_scalar;
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
    // |c_j| <= 127; the sum of d products must stay within int32, and g_j must split
    // into the VNNI kernel's two int8 halves.
    const double cap = static_cast<double>(std::numeric_limits<std::int32_t>::max()) /
                       (127.0 * static_cast<double>(std::max<std::int64_t>(d, 1)));
    return static_cast<int>(std::max(1.0, std::min(double{kVnniMaxG}, std::floor(cap))));
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

const char* int8_kernel_name() {
#ifdef DISCO_X86
    if (bev_kernel_level() >= 3 && have_vnni()) return "avx512vnni";
    if (use_avx2()) return "avx2";
#endif
    return "plain";
}

std::vector<std::int32_t> int8_dots(const Int8Rows& rows, const std::int16_t* g, int threads) {
    std::vector<std::int32_t> out(static_cast<std::size_t>(rows.n));
    DotQuery dq;
    dq.g = g;
    const DotsFn dots = pick_dots(dq, rows.d);
    parallel_rows(rows.n, threads, [&](std::int64_t a, std::int64_t b) {
        dots(rows.codes, rows.d, a, b, nullptr, dq, out.data());
    });
    return out;
}

Int8Query int8_query(const float* q, const double* offset, const double* scale, std::int64_t d,
                     int g_max, std::int16_t* g) {
    std::vector<double> w(static_cast<std::size_t>(d));
    double u_sq = 0.0, top = 0.0;
    for (std::int64_t j = 0; j < d; ++j) {
        const double u = static_cast<double>(q[j]) - offset[j];
        u_sq += u * u;
        w[j] = u * scale[j];
        top = std::max(top, std::abs(w[j]));
    }
    const double step = top > 0.0 ? top / g_max : 1.0, most = g_max;
    double delta_sq = 0.0, w_sq = 0.0;
    for (std::int64_t j = 0; j < d; ++j) {
        const double c = std::min(most, std::max(-most, std::nearbyint(w[j] / step)));
        g[j] = static_cast<std::int16_t>(c);
        const double delta = w[j] - step * c;
        delta_sq += delta * delta;
        w_sq += w[j] * w[j];
    }
    // The rounding of delta itself is far below 1e-12 |w|; of its norm, below 1e-9.
    const double delta_norm = std::sqrt(delta_sq) * (1 + 1e-9) + 1e-12 * std::sqrt(w_sq);
    return Int8Query{g, u_sq, step, delta_norm};
}

std::vector<std::int64_t> int8_candidates(const Int8Rows& rows, const Int8Query& query, int k,
                                          std::int64_t limit, const std::uint8_t* exclude,
                                          int threads) {
    const std::int64_t n = std::min(rows.n, std::max<std::int64_t>(limit, 0));
    std::vector<std::int64_t> out;
    if (n == 0 || k <= 0) return out;
    DotQuery dq;
    dq.g = query.g;
    const DotsFn dots = pick_dots(dq, rows.d);
    const double inf = std::numeric_limits<double>::infinity();
    // Rounding in the double arithmetic below is far under this relative margin.
    constexpr double kRel = 1e-9;
    // Per row: g . c, the squared lower bound of |q - x_hat| and the upper bound of
    // |q - x| (both inf when excluded). Reused across calls so that a query allocates
    // and faults in no fresh pages.
    static thread_local std::vector<std::int32_t> dot_buf;
    static thread_local std::vector<double> low_sq, up_buf;
    if (low_sq.size() < static_cast<std::size_t>(n)) {
        dot_buf.resize(static_cast<std::size_t>(n));
        low_sq.resize(static_cast<std::size_t>(n));
        up_buf.resize(static_cast<std::size_t>(n));
    }
    std::int32_t* dot = dot_buf.data();
    double* lo = low_sq.data();
    double* up = up_buf.data();
    // Each part keeps the k smallest upper bounds it saw (a max-heap), merged below.
    std::vector<double> all;
    std::mutex all_lock;
    parallel_rows(n, threads, [&](std::int64_t a, std::int64_t b) {
        dots(rows.codes, rows.d, a, b, exclude, dq, dot);
        // Without branches, so that the compiler vectorizes it; excluded rows after.
        for (std::int64_t r = a; r < b; ++r) {
            const double G = dot[r];
            const double A = query.u_sq - 2.0 * query.step * G + rows.code_sq[r];
            const double scale = query.u_sq + rows.code_sq[r] + 2.0 * std::abs(query.step * G);
            const double beta = 2.0 * query.delta_norm * rows.code_norm[r] + kRel * scale;
            lo[r] = std::max(A - beta, 0.0);
            up[r] = std::sqrt(std::max(A + beta, 0.0)) + rows.err[r];
        }
        if (exclude)
            for (std::int64_t r = a; r < b; ++r)
                if (exclude[r]) lo[r] = up[r] = inf;
        std::vector<double> heap;
        heap.reserve(static_cast<std::size_t>(k) + 1);
        for (std::int64_t r = a; r < b; ++r) {
            if (up[r] == inf) continue;
            if (static_cast<int>(heap.size()) < k) {
                heap.push_back(up[r]);
                std::push_heap(heap.begin(), heap.end());
            } else if (up[r] < heap.front()) {
                std::pop_heap(heap.begin(), heap.end());
                heap.back() = up[r];
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
