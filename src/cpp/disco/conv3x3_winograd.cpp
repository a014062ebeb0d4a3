// Winograd F(2 x 2, 3 x 3) (conv3x3_winograd.hpp), with the matrices
//   B^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1]
//   G   = [1 0 0; 1/2 1/2 1/2; 1/2 -1/2 1/2; 0 0 1]
//   A^T = [1 1 1 0; 0 1 -1 -1].
// Output tile (i, j) covers rows 2i, 2i + 1 and sectors 2j, 2j + 1, and reads rows
// 2i .. 2i + 3 and columns 2j .. 2j + 3 of the input padded by one on every side.
//
// SIMD lanes run over tiles. The input is first copied into a padded buffer whose rows
// are split into even and odd columns (E[q] = padded[2q], O[q] = padded[2q + 1]), so
// that the four columns of 16 neighbouring tiles are four contiguous loads (E and O at
// q and q + 1) rather than stride-2 gathers. Tiles are then taken in blocks, sized so
// that the transformed block V [16][cin][tiles] stays in L2 (each position's slice in
// L1): transform the block's input tiles, then for each block of 8 output channels run
// 16 small products M[xi] = U[xi] V[xi] (8 channels x whole vectors of tiles in
// registers, as the direct kernel does with sectors) and transform those 8 channels'
// outputs back. The tiles of a block are packed densely, whatever the image widths,
// so the 8 tiles of a 5 x 15 image's row do not waste half a vector. On wide images
// AVX-512 skips V and transforms the input inside the products (run_avx512).
//
// The transforms only add and subtract: they are written once with GCC's vector types
// and inlined into each level's entry, which compiles them for its target. The
// products need fused multiply-adds, which -ffp-contract=off leaves to intrinsics:
// one small kernel per level.
#include "disco/conv3x3_winograd.hpp"

#include <algorithm>
#include <cstring>
#include <stdexcept>

#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels

// GCC only: the vector code below uses its vector extensions (see winograd_level).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define DISCO_WINO_X86 1
#define DISCO_WINO_AVX512 __attribute__((target("avx512f")))
#define DISCO_WINO_AVX2 __attribute__((target("avx2,fma")))
#endif
#define DISCO_WINO_INLINE __attribute__((always_inline)) inline

namespace disco {

namespace {

constexpr int kBlock = 8;  // output channels per product block
constexpr int kPos = 16;   // positions of a 4 x 4 tile
// Bytes of transformed input per block of tiles: about a quarter of this core's L2.
constexpr std::int64_t kBlockBytes = 256 * 1024;

// GCC warns that these vectors would pass between functions differently without
// AVX: they never do, every function that takes one is inlined into its level's entry.
#pragma GCC diagnostic ignored "-Wpsabi"

template <int W>
struct Lanes {
    typedef float vf __attribute__((vector_size(4 * W)));
    typedef int vi __attribute__((vector_size(4 * W)));
    // Loads and stores through an unaligned vector type, not memcpy: memcpy may alias
    // anything, and GCC then reloads the Job's fields after every store.
    typedef float vu __attribute__((vector_size(4 * W), aligned(4)));
    static DISCO_WINO_INLINE vf load(const float* p) { return *reinterpret_cast<const vu*>(p); }
    static DISCO_WINO_INLINE void store(float* p, const vf& x) { *reinterpret_cast<vu*>(p) = x; }
};

// Lane l of the result: a[idx[l]], or b[idx[l] - W] from W on (W lanes a vector). GCC's
// builtin; clang has none that takes the indices as a vector, and gets the loop.
template <class V, class I>
DISCO_WINO_INLINE V shuffle(V a, V b, I idx) {
#if defined(__clang__)
    constexpr int W = sizeof(V) / sizeof(float);
    V r;
    for (int l = 0; l < W; ++l) r[l] = idx[l] < W ? a[idx[l]] : b[idx[l] - W];
    return r;
#else
    return __builtin_shuffle(a, b, idx);
#endif
}

// One run of up to W neighbouring tiles in a tile row, at column `pos` of the block.
struct Segment {
    std::int64_t b, i, j0, n, pos;
};

struct Job {
    float* padded;   // [cin][B][rows][2][half]: even then odd columns of each row
    const float* u;  // Conv3x3Winograd::u_
    const float* bias;
    std::int64_t cin, cout, batch, rings, sectors, tile_rows, tile_cols, rows, half;
    bool relu;
    float* out;
    float* v;  // [16][cin][stride]: a block's transformed input
    float* m;  // [16][8][stride]: its products for one block of 8 output channels
    std::int64_t stride;
};

// M[xi] [8][stride] = U[xi] [cin][8] (as 8 x cin) times V[xi] [cin][stride], for
// `vectors` vectors of tiles; each level's kernel below.
typedef void (*Gemm)(const float* v, const float* u, std::int64_t cin, std::int64_t stride,
                     std::int64_t vectors, float* m);

void gemm_plain(const float* v, const float* u, std::int64_t cin, std::int64_t stride,
                std::int64_t vectors, float* m) {
    constexpr int V = 8;
    for (std::int64_t t = 0; t < vectors * V; t += V) {
        float acc[kBlock][V] = {};
        for (std::int64_t c = 0; c < cin; ++c)
            for (int k = 0; k < kBlock; ++k)
                for (int l = 0; l < V; ++l) acc[k][l] += u[c * kBlock + k] * v[c * stride + t + l];
        for (int k = 0; k < kBlock; ++k)
            for (int l = 0; l < V; ++l) m[k * stride + t + l] = acc[k][l];
    }
}

#if DISCO_WINO_X86
// AVX-512: 8 channels x NV vectors of 16 tiles in registers.
template <int NV>
DISCO_WINO_AVX512 void gemm_block_avx512(const float* v, const float* u, std::int64_t cin,
                                         std::int64_t stride, float* m) {
    __m512 acc[kBlock][NV];
#pragma GCC unroll 8
    for (int k = 0; k < kBlock; ++k)
#pragma GCC unroll 3
        for (int l = 0; l < NV; ++l) acc[k][l] = _mm512_setzero_ps();
    for (std::int64_t c = 0; c < cin; ++c, v += stride, u += kBlock) {
        __m512 x[NV];
#pragma GCC unroll 3
        for (int l = 0; l < NV; ++l) x[l] = _mm512_loadu_ps(v + 16 * l);
#pragma GCC unroll 8
        for (int k = 0; k < kBlock; ++k) {
            const __m512 w = _mm512_set1_ps(u[k]);
#pragma GCC unroll 3
            for (int l = 0; l < NV; ++l) acc[k][l] = _mm512_fmadd_ps(w, x[l], acc[k][l]);
        }
    }
#pragma GCC unroll 8
    for (int k = 0; k < kBlock; ++k)
#pragma GCC unroll 3
        for (int l = 0; l < NV; ++l) _mm512_storeu_ps(m + k * stride + 16 * l, acc[k][l]);
}

DISCO_WINO_AVX512 void gemm_avx512(const float* v, const float* u, std::int64_t cin,
                                   std::int64_t stride, std::int64_t vectors, float* m) {
    std::int64_t t = 0;
    for (; t + 3 <= vectors; t += 3) gemm_block_avx512<3>(v + 16 * t, u, cin, stride, m + 16 * t);
    if (t + 2 <= vectors) gemm_block_avx512<2>(v + 16 * t, u, cin, stride, m + 16 * t), t += 2;
    if (t < vectors) gemm_block_avx512<1>(v + 16 * t, u, cin, stride, m + 16 * t);
}

// AVX2 + FMA: 4 channels x NV vectors of 8 tiles (12 of the 16 registers at NV 3).
template <int NV>
DISCO_WINO_AVX2 void gemm_block_avx2(const float* v, const float* u, std::int64_t cin,
                                     std::int64_t stride, float* m) {
    constexpr int KB = 4;
    __m256 acc[KB][NV];
#pragma GCC unroll 4
    for (int k = 0; k < KB; ++k)
#pragma GCC unroll 3
        for (int l = 0; l < NV; ++l) acc[k][l] = _mm256_setzero_ps();
    for (std::int64_t c = 0; c < cin; ++c, v += stride, u += kBlock) {
        __m256 x[NV];
#pragma GCC unroll 3
        for (int l = 0; l < NV; ++l) {
            x[l] = _mm256_loadu_ps(v + 8 * l);
            // Keeps the vector in a register: GCC would fold it into each multiply-add
            // as a memory operand (as in conv3x3.cpp).
            __asm__("" : "+x"(x[l]));
        }
#pragma GCC unroll 4
        for (int k = 0; k < KB; ++k) {
            const __m256 w = _mm256_broadcast_ss(u + k);
#pragma GCC unroll 3
            for (int l = 0; l < NV; ++l) acc[k][l] = _mm256_fmadd_ps(w, x[l], acc[k][l]);
        }
    }
#pragma GCC unroll 4
    for (int k = 0; k < KB; ++k)
#pragma GCC unroll 3
        for (int l = 0; l < NV; ++l) _mm256_storeu_ps(m + k * stride + 8 * l, acc[k][l]);
}

template <int NV>
DISCO_WINO_AVX2 void gemm_halves_avx2(const float* v, const float* u, std::int64_t cin,
                                      std::int64_t stride, float* m) {
    gemm_block_avx2<NV>(v, u, cin, stride, m);
    gemm_block_avx2<NV>(v, u + 4, cin, stride, m + 4 * stride);
}

DISCO_WINO_AVX2 void gemm_avx2(const float* v, const float* u, std::int64_t cin,
                               std::int64_t stride, std::int64_t vectors, float* m) {
    std::int64_t t = 0;
    for (; t + 3 <= vectors; t += 3) gemm_halves_avx2<3>(v + 8 * t, u, cin, stride, m + 8 * t);
    if (t + 2 <= vectors) gemm_halves_avx2<2>(v + 8 * t, u, cin, stride, m + 8 * t), t += 2;
    if (t < vectors) gemm_halves_avx2<1>(v + 8 * t, u, cin, stride, m + 8 * t);
}
#endif

// Copies the parts into Job::padded (see the top of the file): row r of an image is
// padded row r + 1; padded column p holds sector p - 1, the wrapped (or zero) sector
// at p = 0 and p = sectors + 1, zeros beyond. Rows past the image are zeros.
template <int W>
DISCO_WINO_INLINE void pad_split(const std::vector<ConvPart>& parts, const Job& j,
                                 bool circular, float* dst) {
    typedef Lanes<W> L;
    typedef typename L::vf vf;
    typedef typename L::vi vi;
    vi even, odd;  // lanes 0, 2, 4, ... and 1, 3, 5, ... of two vectors
    for (int l = 0; l < W; ++l) even[l] = 2 * l, odd[l] = 2 * l + 1;
    const std::int64_t s = j.sectors, h = j.half, row = 2 * h;
    for (const auto& part : parts) {
        const float* src = part.data;
        for (std::int64_t img = 0; img < part.channels * j.batch; ++img) {
            std::fill(dst, dst + row, 0.0f);
            dst += row;
            for (std::int64_t r = 0; r < j.rings; ++r, src += s, dst += row) {
                float *e = dst, *o = dst + h;
                // Sector 2q is padded column 2q + 1 (O[q]); sector 2q + 1 is E[q + 1].
                std::int64_t q = 0;
                for (; 2 * q + 2 * W <= s; q += W) {
                    const vf a = L::load(src + 2 * q), b = L::load(src + 2 * q + W);
                    L::store(o + q, shuffle(a, b, even));
                    L::store(e + q + 1, shuffle(a, b, odd));
                }
                for (std::int64_t t = q; 2 * t < s; ++t) o[t] = src[2 * t];
                for (std::int64_t t = std::max<std::int64_t>(q, 1); 2 * t - 1 < s; ++t)
                    e[t] = src[2 * t - 1];
                e[0] = circular ? src[s - 1] : 0.0f;
                // Column s + 1 (the right-hand pad), then zeros to the row's end.
                float* right = (s + 1) % 2 == 0 ? e + (s + 1) / 2 : o + s / 2;
                *right = circular ? src[0] : 0.0f;
                std::fill(e + (s + 2) / 2 + ((s + 1) % 2 == 0), e + h, 0.0f);
                std::fill(o + (s + 1) / 2 + (s % 2 == 0), o + h, 0.0f);
            }
            const std::int64_t tail = j.rows - 1 - j.rings;
            std::fill(dst, dst + tail * row, 0.0f);
            dst += tail * row;
        }
    }
}

// V[xi][c][seg.pos ..] = B^T d B of the segment's tiles for every input channel. Whole
// vectors are stored: lanes past seg.n land where the next segment (or the spare
// vector at the end of each row of V) is written after.
template <int W>
DISCO_WINO_INLINE void transform_input(const Job& j, const Segment& seg) {
    typedef Lanes<W> L;
    typedef typename L::vf vf;
    const std::int64_t half = j.half, row = 2 * half, image = j.rows * row;
    const std::int64_t cplane = j.batch * image, vplane = j.cin * j.stride;
    const std::int64_t cin = j.cin, vstride = j.stride;
    const float* base = j.padded + seg.b * image + 2 * seg.i * row + seg.j0;
    float* v = j.v + seg.pos;
    for (std::int64_t c = 0; c < cin; ++c, base += cplane, v += vstride) {
        vf d[4][4], e[4][4];  // the tile's columns 0 .. 3 by row; B^T d
#pragma GCC unroll 4
        for (int r = 0; r < 4; ++r) {
            const float* p = base + r * row;
            d[r][0] = L::load(p), d[r][1] = L::load(p + half);
            d[r][2] = L::load(p + 1), d[r][3] = L::load(p + half + 1);
        }
#pragma GCC unroll 4
        for (int q = 0; q < 4; ++q) {
            e[0][q] = d[0][q] - d[2][q];
            e[1][q] = d[1][q] + d[2][q];
            e[2][q] = d[2][q] - d[1][q];
            e[3][q] = d[1][q] - d[3][q];
        }
        float* o = v;
#pragma GCC unroll 4
        for (int r = 0; r < 4; ++r) {  // (B^T d) B: the same on columns
            L::store(o, e[r][0] - e[r][2]), o += vplane;
            L::store(o, e[r][1] + e[r][2]), o += vplane;
            L::store(o, e[r][2] - e[r][1]), o += vplane;
            L::store(o, e[r][1] - e[r][3]), o += vplane;
        }
    }
}

// out = A^T M A + bias (then ReLU) for output channels k0 .. k0 + kc of a segment,
// from Job::m; each 2 x 2 tile's two sectors interleaved into place.
template <int W>
DISCO_WINO_INLINE void transform_output(const Job& j, const Segment& seg, std::int64_t k0,
                                        std::int64_t kc) {
    typedef Lanes<W> L;
    typedef typename L::vf vf;
    typedef typename L::vi vi;
    vi lo, hi;  // lane l of y0 to 2l, of y1 to 2l + 1
    for (int l = 0; l < W; ++l) {
        lo[l] = l % 2 ? W + l / 2 : l / 2;
        hi[l] = l % 2 ? W + W / 2 + l / 2 : W / 2 + l / 2;
    }
    const std::int64_t stride = j.stride, plane = kBlock * stride;
    const std::int64_t sectors = j.sectors;
    const std::int64_t cols = std::min<std::int64_t>(2 * W, sectors - 2 * seg.j0);
    const std::int64_t rows = std::min<std::int64_t>(2, j.rings - 2 * seg.i);
    const std::int64_t ostride = j.batch * j.rings * sectors;  // between output channels
    const float* bias = j.bias + k0;
    const bool relu = j.relu;
    float* out = j.out + ((k0 * j.batch + seg.b) * j.rings + 2 * seg.i) * sectors + 2 * seg.j0;
    for (std::int64_t k = 0; k < kc; ++k, out += ostride) {
        const float* m = j.m + k * stride + seg.pos;
        vf t[2][4];  // A^T M
#pragma GCC unroll 4
        for (int q = 0; q < 4; ++q) {
            const vf r0 = L::load(m + q * plane), r1 = L::load(m + (4 + q) * plane);
            const vf r2 = L::load(m + (8 + q) * plane), r3 = L::load(m + (12 + q) * plane);
            t[0][q] = r0 + r1 + r2;
            t[1][q] = r1 - r2 - r3;
        }
#pragma GCC unroll 2
        for (int a = 0; a < 2; ++a) {
            if (a >= rows) break;  // the pad row of an odd ring count
            vf y0 = t[a][0] + t[a][1] + t[a][2] + bias[k];
            vf y1 = t[a][1] - t[a][2] - t[a][3] + bias[k];
            if (relu) y0 = y0 > 0 ? y0 : 0, y1 = y1 > 0 ? y1 : 0;
            const vf pair[2] = {shuffle(y0, y1, lo), shuffle(y0, y1, hi)};
            float* dst = out + a * sectors;
            if (cols == 2 * W) {
                L::store(dst, pair[0]), L::store(dst + W, pair[1]);
            } else {
                std::memcpy(dst, pair, static_cast<std::size_t>(cols) * sizeof(float));
            }
        }
    }
}

// One block of tiles: its input transformed, then per block of 8 output channels the
// 16 products and the output transform.
template <int W>
DISCO_WINO_INLINE void run_block(const Job& job, const std::vector<Segment>& segs,
                                 std::int64_t filled, Gemm gemm) {
    for (const auto& s : segs) transform_input<W>(job, s);
    const std::int64_t vectors = (filled + W - 1) / W;
    const std::int64_t ublock = (job.cout + kBlock - 1) / kBlock * kBlock * job.cin;
    for (std::int64_t k0 = 0; k0 < job.cout; k0 += kBlock) {
        const float* u = job.u + k0 * job.cin;  // block k0 / 8 of position 0
        for (int xi = 0; xi < kPos; ++xi)
            gemm(job.v + xi * job.cin * job.stride, u + xi * ublock, job.cin, job.stride,
                 vectors, job.m + xi * kBlock * job.stride);
        const std::int64_t kc = std::min<std::int64_t>(kBlock, job.cout - k0);
        for (const auto& s : segs) transform_output<W>(job, s, k0, kc);
    }
}

// The whole convolution at one level: W lanes, `gemm` its products. Inlined into each
// level's entry below, so that the transforms compile for that level's target.
template <int W>
DISCO_WINO_INLINE void run_level(const std::vector<ConvPart>& parts, bool circular,
                                 const Job& job, Gemm gemm) {
    pad_split<W>(parts, job, circular, job.padded);
    const std::int64_t capacity = job.stride - W;
    std::vector<Segment> segs;
    std::int64_t filled = 0;
    for (std::int64_t b = 0; b < job.batch; ++b)
        for (std::int64_t i = 0; i < job.tile_rows; ++i)
            for (std::int64_t j0 = 0; j0 < job.tile_cols; j0 += W) {
                const std::int64_t n = std::min<std::int64_t>(W, job.tile_cols - j0);
                if (filled + n > capacity) {
                    run_block<W>(job, segs, filled, gemm);
                    segs.clear();
                    filled = 0;
                }
                segs.push_back({b, i, j0, n, filled});
                filled += n;
            }
    if (filled > 0) run_block<W>(job, segs, filled, gemm);
}

#if DISCO_WINO_X86
// AVX-512 transforms each input tile inside the products instead: position xi = (r, q)
// of B^T d B is (d[a] -+ d[b]) -+ (d[c] -+ d[d]) over four padded columns, 4 loads and
// 3 additions per vector of tiles, which run on the adders beside the multiply-adds.
// That saves writing and reading V (16 stores a tile and channel, which cost as much
// as 16 multiply-adds at 8 output channels). Row offsets ra, rb and column offsets
// ca, cb (into the split rows) pick the four; RowPlus / ColPlus the signs.
template <int NV, bool RowPlus, bool ColPlus>
DISCO_WINO_AVX512 void fused_avx512(const float* x, std::int64_t cplane, std::int64_t ra,
                                    std::int64_t rb, std::int64_t ca, std::int64_t cb,
                                    const float* u, std::int64_t cin, float* m) {
    __m512 acc[kBlock][NV];
#pragma GCC unroll 8
    for (int k = 0; k < kBlock; ++k)
#pragma GCC unroll 2
        for (int l = 0; l < NV; ++l) acc[k][l] = _mm512_setzero_ps();
    const float *pa = x + ra, *pb = x + rb;
    for (std::int64_t c = 0; c < cin; ++c, pa += cplane, pb += cplane, u += kBlock) {
        __m512 v[NV];
#pragma GCC unroll 2
        for (int l = 0; l < NV; ++l) {
            const __m512 a0 = _mm512_loadu_ps(pa + ca + 16 * l);
            const __m512 a1 = _mm512_loadu_ps(pa + cb + 16 * l);
            const __m512 b0 = _mm512_loadu_ps(pb + ca + 16 * l);
            const __m512 b1 = _mm512_loadu_ps(pb + cb + 16 * l);
            const __m512 a = ColPlus ? _mm512_add_ps(a0, a1) : _mm512_sub_ps(a0, a1);
            const __m512 b = ColPlus ? _mm512_add_ps(b0, b1) : _mm512_sub_ps(b0, b1);
            v[l] = RowPlus ? _mm512_add_ps(a, b) : _mm512_sub_ps(a, b);
        }
#pragma GCC unroll 8
        for (int k = 0; k < kBlock; ++k) {
            const __m512 w = _mm512_set1_ps(u[k]);
#pragma GCC unroll 2
            for (int l = 0; l < NV; ++l) acc[k][l] = _mm512_fmadd_ps(w, v[l], acc[k][l]);
        }
    }
#pragma GCC unroll 8
    for (int k = 0; k < kBlock; ++k)
#pragma GCC unroll 2
        for (int l = 0; l < NV; ++l) _mm512_storeu_ps(m + k * 32 + 16 * l, acc[k][l]);
}

template <int NV>
DISCO_WINO_AVX512 void position_avx512(int xi, const float* x, std::int64_t cplane,
                                       std::int64_t row, std::int64_t half, const float* u,
                                       std::int64_t cin, float* m) {
    // Rows of B^T: (a, b, sign) = (0, 2, -), (1, 2, +), (2, 1, -), (1, 3, -); columns
    // the same over E[j], O[j], E[j + 1], O[j + 1] at offsets 0, half, 1, half + 1.
    static const int ra[4] = {0, 1, 2, 1}, rb[4] = {2, 2, 1, 3};
    const std::int64_t ca[4] = {0, half, 1, half}, cb[4] = {1, 1, half, half + 1};
    const int r = xi / 4, q = xi % 4;
    const std::int64_t a = ra[r] * row, b = rb[r] * row;
    const std::int64_t c0 = ca[q], c1 = cb[q];
    if (r == 1 && q == 1) return fused_avx512<NV, true, true>(x, cplane, a, b, c0, c1, u, cin, m);
    if (r == 1) return fused_avx512<NV, true, false>(x, cplane, a, b, c0, c1, u, cin, m);
    if (q == 1) return fused_avx512<NV, false, true>(x, cplane, a, b, c0, c1, u, cin, m);
    fused_avx512<NV, false, false>(x, cplane, a, b, c0, c1, u, cin, m);
}

// Fused where the tile rows fill whole vectors (measured on this project's U-Net, Zen 4:
// 1.3 - 1.5x the direct kernel at 40 x 120 and 20 x 60); at 30 sectors and below a
// row's 15 tiles or fewer would leave lanes idle, and the blocked path packs them.
constexpr std::int64_t kFusedTileCols = 24;

DISCO_WINO_AVX512 void run_avx512(const std::vector<ConvPart>& parts, bool circular,
                                  const Job& job) {
    if (job.tile_cols < kFusedTileCols) return run_level<16>(parts, circular, job, gemm_avx512);
    pad_split<16>(parts, job, circular, job.padded);
    Job out = job;
    out.stride = 32;  // Job::m as [16][8][32]: two vectors of tiles
    const std::int64_t row = 2 * job.half, image = job.rows * row, cplane = job.batch * image;
    const std::int64_t ublock = (job.cout + kBlock - 1) / kBlock * kBlock * job.cin;
    for (std::int64_t b = 0; b < job.batch; ++b)
        for (std::int64_t i = 0; i < job.tile_rows; ++i)
            for (std::int64_t j0 = 0; j0 < job.tile_cols; j0 += 32) {
                const std::int64_t n0 = std::min<std::int64_t>(16, job.tile_cols - j0);
                const std::int64_t n1 = std::min<std::int64_t>(16, job.tile_cols - j0 - n0);
                const Segment segs[2] = {{b, i, j0, n0, 0}, {b, i, j0 + 16, n1, 16}};
                const float* x = job.padded + b * image + 2 * i * row + j0;
                for (std::int64_t k0 = 0; k0 < job.cout; k0 += kBlock) {
                    const float* u = job.u + k0 * job.cin;
                    for (int xi = 0; xi < kPos; ++xi) {
                        float* m = job.m + xi * kBlock * 32;
                        if (n1 > 0)
                            position_avx512<2>(xi, x, cplane, row, job.half, u + xi * ublock,
                                               job.cin, m);
                        else
                            position_avx512<1>(xi, x, cplane, row, job.half, u + xi * ublock,
                                               job.cin, m);
                    }
                    const std::int64_t kc = std::min<std::int64_t>(kBlock, job.cout - k0);
                    transform_output<16>(out, segs[0], k0, kc);
                    if (n1 > 0) transform_output<16>(out, segs[1], k0, kc);
                }
            }
}

DISCO_WINO_AVX2 void run_avx2(const std::vector<ConvPart>& parts, bool circular,
                              const Job& job) {
    run_level<8>(parts, circular, job, gemm_avx2);
}
#endif

void run_plain(const std::vector<ConvPart>& parts, bool circular, const Job& job) {
    run_level<8>(parts, circular, job, gemm_plain);
}

}  // namespace

Conv3x3Winograd::Conv3x3Winograd(const float* weight, const float* bias, std::int64_t cout,
                                 std::int64_t cin)
    : cout_(cout), cin_(cin) {
    if (cout < 1 || cin < 1)
        throw std::invalid_argument("conv3x3 winograd needs cout >= 1 and cin >= 1");
    const std::int64_t blocks = (cout + kBlock - 1) / kBlock;
    u_.assign(static_cast<std::size_t>(kPos * blocks * kBlock * cin), 0.0f);
    bias_.assign(static_cast<std::size_t>(blocks * kBlock), 0.0f);
    static const double G[4][3] = {{1, 0, 0}, {0.5, 0.5, 0.5}, {0.5, -0.5, 0.5}, {0, 0, 1}};
    for (std::int64_t o = 0; o < cout; ++o) {
        bias_[static_cast<std::size_t>(o)] = bias[o];
        for (std::int64_t c = 0; c < cin; ++c) {
            const float* g = weight + (o * cin + c) * 9;
            double gg[4][3];  // G g
            for (int p = 0; p < 4; ++p)
                for (int x = 0; x < 3; ++x)
                    gg[p][x] = G[p][0] * g[x] + G[p][1] * g[3 + x] + G[p][2] * g[6 + x];
            for (int p = 0; p < 4; ++p)
                for (int q = 0; q < 4; ++q) {
                    const double val = gg[p][0] * G[q][0] + gg[p][1] * G[q][1] + gg[p][2] * G[q][2];
                    const std::int64_t at = ((4 * p + q) * blocks + o / kBlock) * cin * kBlock +
                                            c * kBlock + o % kBlock;
                    u_[static_cast<std::size_t>(at)] = static_cast<float>(val);
                }
        }
    }
}

void Conv3x3Winograd::run(const std::vector<ConvPart>& parts, std::int64_t batch,
                          std::int64_t rings, std::int64_t sectors, bool circular, bool relu,
                          float* out) const {
    const int level = winograd_level(bev_kernel_level());
    const std::int64_t w = level == 3 ? 16 : 8;
    Job job{};
    job.u = u_.data(), job.bias = bias_.data(), job.cin = cin_, job.cout = cout_;
    job.batch = batch, job.rings = rings, job.sectors = sectors, job.relu = relu, job.out = out;
    job.tile_rows = (rings + 1) / 2, job.tile_cols = (sectors + 1) / 2;
    job.rows = 2 * job.tile_rows + 2;
    // Vector loads reach column q + 1 for the last whole vector of tiles starting at q.
    job.half = (job.tile_cols + w - 1) / w * w + 1;
    // Whole vectors of tiles per block, at least one; a spare vector past the last.
    const std::int64_t fit = kBlockBytes / (kPos * cin_ * 4) / w * w;
    const std::int64_t all = batch * job.tile_rows * ((job.tile_cols + w - 1) / w * w);
    job.stride = std::max(w, std::min(fit, all)) + w;
    // One set of buffers per thread, kept: fresh ones each call would fault pages in.
    thread_local std::vector<float> padded, v, m;
    const auto grow = [](std::vector<float>& buf, std::int64_t n) {
        if (buf.size() < static_cast<std::size_t>(n)) buf.resize(static_cast<std::size_t>(n));
        return buf.data();
    };
    job.padded = grow(padded, cin_ * batch * job.rows * 2 * job.half);
    job.v = grow(v, kPos * cin_ * job.stride);
    job.m = grow(m, kPos * kBlock * job.stride);
#if DISCO_WINO_X86
    if (level == 3) return run_avx512(parts, circular, job);
    if (level == 2) return run_avx2(parts, circular, job);
#endif
    run_plain(parts, circular, job);
}

int winograd_level(int level) {
#if DISCO_WINO_X86
    return level >= 3 ? 3 : level == 2 ? 2 : 0;
#else
    (void)level;
    return 0;
#endif
}

}  // namespace disco
