#include "disco/projected_search.hpp"

#include <algorithm>
#include <cmath>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define DISCO_X86 1
#endif

namespace disco {
namespace {

constexpr int kTile = kProjectedTile;

// One tile (columns c < width of tile t) for the queries q[0 .. nq), out rows of n.
void tile_plain(const float* tile, std::int64_t p, const float* q, int nq, const float* sq,
                std::int64_t col0, int width, std::int64_t n, float* out) {
    for (int i = 0; i < nq; ++i)
        for (int c = 0; c < width; ++c) {
            float acc = 0.0f;
            for (std::int64_t k = 0; k < p; ++k)
                acc = std::fma(q[i * p + k], tile[k * kTile + c], acc);
            out[i * n + col0 + c] = acc * -2.0f + sq[col0 + c];
        }
}

#ifdef DISCO_X86
// Four queries by 64 columns: 16 accumulators of 16 lanes.
template <int NQ>
__attribute__((target("avx512f"))) void tile_avx512(const float* tile, std::int64_t p,
                                                    const float* q, const float* sq,
                                                    std::int64_t col0, int width, std::int64_t n,
                                                    float* out) {
    __m512 acc[NQ][4];
    for (auto& row : acc)
        for (auto& v : row) v = _mm512_setzero_ps();
    for (std::int64_t k = 0; k < p; ++k) {
        const float* t = tile + k * kTile;
        const __m512 x0 = _mm512_loadu_ps(t), x1 = _mm512_loadu_ps(t + 16);
        const __m512 x2 = _mm512_loadu_ps(t + 32), x3 = _mm512_loadu_ps(t + 48);
        for (int i = 0; i < NQ; ++i) {
            const __m512 w = _mm512_set1_ps(q[i * p + k]);
            acc[i][0] = _mm512_fmadd_ps(w, x0, acc[i][0]);
            acc[i][1] = _mm512_fmadd_ps(w, x1, acc[i][1]);
            acc[i][2] = _mm512_fmadd_ps(w, x2, acc[i][2]);
            acc[i][3] = _mm512_fmadd_ps(w, x3, acc[i][3]);
        }
    }
    const __m512 minus2 = _mm512_set1_ps(-2.0f);
    for (int i = 0; i < NQ; ++i)
        for (int v = 0; v < 4; ++v) {
            const int c = 16 * v;
            if (c >= width) break;
            const int left = width - c;
            const auto m = static_cast<__mmask16>(left >= 16 ? 0xFFFFu : (1u << left) - 1);
            const __m512 s = _mm512_maskz_loadu_ps(m, sq + col0 + c);
            _mm512_mask_storeu_ps(out + i * n + col0 + c, m,
                                  _mm512_add_ps(_mm512_mul_ps(acc[i][v], minus2), s));
        }
}

// Four queries by 16 columns (8 accumulators of 8 lanes), four times per tile.
template <int NQ>
__attribute__((target("avx2,fma"))) void tile_avx2(const float* tile, std::int64_t p,
                                                   const float* q, const float* sq,
                                                   std::int64_t col0, int width, std::int64_t n,
                                                   float* out) {
    const __m256 minus2 = _mm256_set1_ps(-2.0f);
    for (int c = 0; c < width; c += 16) {
        __m256 acc[NQ][2];
        for (auto& row : acc) row[0] = row[1] = _mm256_setzero_ps();
        for (std::int64_t k = 0; k < p; ++k) {
            const float* t = tile + k * kTile + c;
            const __m256 x0 = _mm256_loadu_ps(t), x1 = _mm256_loadu_ps(t + 8);
            for (int i = 0; i < NQ; ++i) {
                const __m256 w = _mm256_set1_ps(q[i * p + k]);
                acc[i][0] = _mm256_fmadd_ps(w, x0, acc[i][0]);
                acc[i][1] = _mm256_fmadd_ps(w, x1, acc[i][1]);
            }
        }
        for (int i = 0; i < NQ; ++i) {
            alignas(32) float v[16];
            _mm256_store_ps(v, _mm256_mul_ps(acc[i][0], minus2));
            _mm256_store_ps(v + 8, _mm256_mul_ps(acc[i][1], minus2));
            const int m = std::min(16, width - c);
            for (int e = 0; e < m; ++e) out[i * n + col0 + c + e] = v[e] + sq[col0 + c + e];
        }
    }
}
#endif

int level_now() {
#ifdef DISCO_X86
    static const bool avx512 = __builtin_cpu_supports("avx512f");
    static const bool avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    const int cap = bev_kernel_level();
    if (cap >= 3 && avx512) return 3;
    if (cap >= 2 && avx2) return 2;
#endif
    return 0;
}

}  // namespace

void projected_approx(const float* tiles, std::int64_t p, std::int64_t n, const float* sq,
                      const float* q, std::int64_t b, float* out) {
    const int level = level_now();
    const std::int64_t ntiles = (n + kTile - 1) / kTile;
    // Four queries at a time share each tile's read.
    for (std::int64_t i0 = 0; i0 < b; i0 += 4) {
        const int nq = static_cast<int>(std::min<std::int64_t>(4, b - i0));
        const float* qi = q + i0 * p;
        float* oi = out + i0 * n;
        for (std::int64_t t = 0; t < ntiles; ++t) {
            const float* tile = tiles + t * p * kTile;
            const std::int64_t col0 = t * kTile;
            const int width = static_cast<int>(std::min<std::int64_t>(kTile, n - col0));
#ifdef DISCO_X86
            if (level == 3) {
                switch (nq) {
                    case 4: tile_avx512<4>(tile, p, qi, sq, col0, width, n, oi); break;
                    case 3: tile_avx512<3>(tile, p, qi, sq, col0, width, n, oi); break;
                    case 2: tile_avx512<2>(tile, p, qi, sq, col0, width, n, oi); break;
                    default: tile_avx512<1>(tile, p, qi, sq, col0, width, n, oi); break;
                }
                continue;
            }
            if (level == 2) {
                switch (nq) {
                    case 4: tile_avx2<4>(tile, p, qi, sq, col0, width, n, oi); break;
                    case 3: tile_avx2<3>(tile, p, qi, sq, col0, width, n, oi); break;
                    case 2: tile_avx2<2>(tile, p, qi, sq, col0, width, n, oi); break;
                    default: tile_avx2<1>(tile, p, qi, sq, col0, width, n, oi); break;
                }
                continue;
            }
#else
            (void)level;
#endif
            tile_plain(tile, p, qi, nq, sq, col0, width, n, oi);
        }
    }
}

const char* projected_kernel_name() {
    return wide_kernel_name(level_now());
}

}  // namespace disco
