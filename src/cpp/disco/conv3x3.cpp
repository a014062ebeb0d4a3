// The direct 3 x 3 convolution (conv3x3.hpp), and the choice between it and Winograd's
// (conv3x3_winograd.cpp; prefers_winograd below). The input parts are first copied into
// one padded buffer [cin][B][R + 2][W]: a ring of zeros (or the wrapped sectors) round
// each image, and each row widened to W = the sectors rounded up to whole vectors, plus
// 2, so that a vector of outputs at sector s reads its taps at s, s + 1, s + 2 of three
// rows without a bounds check; the outputs past the last sector are computed on the
// zeros there and not written. The copy costs a few percent of the arithmetic.
//
// Each kernel then keeps 8 output channels x NV vectors of sectors in registers and
// streams the input channels and taps through them: per tap, NV vector loads and 8
// weight broadcasts feed 8 * NV multiply-adds.
#include "disco/conv3x3.hpp"

#include <algorithm>
#include <cstring>
#include <stdexcept>

#include "disco/conv3x3_winograd.hpp"
#include "disco/polar_bev.hpp"  // the SIMD level cap shared by the kernels

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define DISCO_CONV_X86 1
#define DISCO_CONV_AVX512 __attribute__((target("avx512f")))
#define DISCO_CONV_AVX2 __attribute__((target("avx2,fma")))
#endif

namespace disco {

namespace {

constexpr int kBlock = 8;  // output channels per register block
constexpr int kTaps = 9;

struct Job {
    const float* padded;  // [cin][B][R + 2][W]
    const float* packed;  // Conv3x3::packed_
    const float* bias;    // padded to whole blocks
    std::int64_t cin, cout, batch, rings, sectors, width;
    bool relu;
    float* out;  // [cout][B][R][S]
};

// Copies the parts into `padded` (see the top of the file).
void pad_input(const std::vector<ConvPart>& parts, std::int64_t batch, std::int64_t rings,
               std::int64_t sectors, std::int64_t width, bool circular, float* padded) {
    const std::int64_t plane = (rings + 2) * width;
    const auto row_bytes = static_cast<std::size_t>(sectors) * sizeof(float);
    const auto tail = static_cast<std::size_t>(width - sectors - 2);
    float* dst = padded;
    for (const auto& part : parts) {
        const float* src = part.data;
        for (std::int64_t img = 0; img < part.channels * batch; ++img, dst += plane) {
            std::fill(dst, dst + width, 0.0f);
            for (std::int64_t r = 0; r < rings; ++r, src += sectors) {
                float* d = dst + (r + 1) * width;
                d[0] = circular ? src[sectors - 1] : 0.0f;
                std::memcpy(d + 1, src, row_bytes);
                d[sectors + 1] = circular ? src[0] : 0.0f;
                std::fill(d + sectors + 2, d + sectors + 2 + tail, 0.0f);
            }
            std::fill(dst + (rings + 1) * width, dst + plane, 0.0f);
        }
    }
}

// --- plain C++: blocks of 8 sectors, the compiler vectorizes what it can ---
void run_plain(const Job& j) {
    constexpr int V = 8;
    const std::int64_t plane = (j.rings + 2) * j.width, cstride = j.batch * plane;
    const std::int64_t kstride = j.batch * j.rings * j.sectors;
    for (std::int64_t blk = 0; blk * kBlock < j.cout; ++blk) {
        const float* wb = j.packed + blk * j.cin * kTaps * kBlock;
        const float* bias = j.bias + blk * kBlock;
        const std::int64_t kc = std::min<std::int64_t>(kBlock, j.cout - blk * kBlock);
        for (std::int64_t b = 0; b < j.batch; ++b) {
            for (std::int64_t r = 0; r < j.rings; ++r) {
                const float* row = j.padded + b * plane + r * j.width;
                float* orow = j.out + (blk * kBlock * j.batch + b) * j.rings * j.sectors +
                              r * j.sectors;
                for (std::int64_t s0 = 0; s0 < j.sectors; s0 += V) {
                    float acc[kBlock][V];
                    for (int k = 0; k < kBlock; ++k)
                        for (int v = 0; v < V; ++v) acc[k][v] = bias[k];
                    const float* x = row + s0;
                    const float* w = wb;
                    for (std::int64_t c = 0; c < j.cin; ++c, x += cstride, w += kTaps * kBlock) {
                        for (int t = 0; t < kTaps; ++t) {
                            const float* xt = x + (t / 3) * j.width + t % 3;
                            const float* wt = w + t * kBlock;
                            for (int k = 0; k < kBlock; ++k)
                                for (int v = 0; v < V; ++v) acc[k][v] += wt[k] * xt[v];
                        }
                    }
                    const std::int64_t n = std::min<std::int64_t>(V, j.sectors - s0);
                    for (std::int64_t k = 0; k < kc; ++k)
                        for (std::int64_t v = 0; v < n; ++v)
                            orow[k * kstride + s0 + v] = j.relu ? std::max(acc[k][v], 0.0f)
                                                                : acc[k][v];
                }
            }
        }
    }
}

#if DISCO_CONV_X86
// --- AVX-512: 8 channels x NV vectors of 16 sectors (16 of the 32 registers at NV 2) ---
template <int NV>
DISCO_CONV_AVX512 void block_avx512(const Job& j, const float* row, const float* wb,
                                    const float* bias, std::int64_t kc, std::int64_t s0,
                                    float* orow) {
    constexpr int V = 16;
    const std::int64_t cstride = j.batch * (j.rings + 2) * j.width;
    const std::int64_t kstride = j.batch * j.rings * j.sectors;
    __m512 acc[kBlock][NV];
#pragma GCC unroll 8
    for (int k = 0; k < kBlock; ++k)
#pragma GCC unroll 2
        for (int v = 0; v < NV; ++v) acc[k][v] = _mm512_set1_ps(bias[k]);
    const float* x = row + s0;
    const float* w = wb;
    for (std::int64_t c = 0; c < j.cin; ++c, x += cstride, w += kTaps * kBlock) {
#pragma GCC unroll 9
        for (int t = 0; t < kTaps; ++t) {
            const float* xt = x + (t / 3) * j.width + t % 3;
            __m512 xv[NV];
#pragma GCC unroll 2
            for (int v = 0; v < NV; ++v) xv[v] = _mm512_loadu_ps(xt + V * v);
#pragma GCC unroll 8
            for (int k = 0; k < kBlock; ++k) {
                const __m512 wk = _mm512_set1_ps(w[t * kBlock + k]);
#pragma GCC unroll 2
                for (int v = 0; v < NV; ++v) acc[k][v] = _mm512_fmadd_ps(wk, xv[v], acc[k][v]);
            }
        }
    }
    const __m512 zero = _mm512_setzero_ps();
#pragma GCC unroll 2
    for (int v = 0; v < NV; ++v) {
        const std::int64_t n = j.sectors - s0 - V * v;
        if (n <= 0) break;
        const __mmask16 m = n >= V ? __mmask16(0xFFFF) : __mmask16((1u << n) - 1u);
#pragma GCC unroll 8
        for (int k = 0; k < kBlock; ++k) {
            if (k >= kc) break;
            // maskz_max, not max: GCC 12 warns of max's undefined pass-through operand.
            const __m512 y =
                j.relu ? _mm512_maskz_max_ps(__mmask16(0xFFFF), acc[k][v], zero) : acc[k][v];
            _mm512_mask_storeu_ps(orow + k * kstride + s0 + V * v, m, y);
        }
    }
}

DISCO_CONV_AVX512 void run_avx512(const Job& j) {
    constexpr int V = 16;
    const std::int64_t plane = (j.rings + 2) * j.width;
    for (std::int64_t blk = 0; blk * kBlock < j.cout; ++blk) {
        const float* wb = j.packed + blk * j.cin * kTaps * kBlock;
        const float* bias = j.bias + blk * kBlock;
        const std::int64_t kc = std::min<std::int64_t>(kBlock, j.cout - blk * kBlock);
        for (std::int64_t b = 0; b < j.batch; ++b) {
            for (std::int64_t r = 0; r < j.rings; ++r) {
                const float* row = j.padded + b * plane + r * j.width;
                float* orow = j.out + (blk * kBlock * j.batch + b) * j.rings * j.sectors +
                              r * j.sectors;
                std::int64_t s0 = 0;
                for (; s0 + V < j.sectors; s0 += 2 * V)
                    block_avx512<2>(j, row, wb, bias, kc, s0, orow);
                if (s0 < j.sectors) block_avx512<1>(j, row, wb, bias, kc, s0, orow);
            }
        }
    }
}

// --- AVX2 + FMA: KB channels x NV vectors of 8 sectors (at most 12 of the 16
// registers hold sums) ---
template <int KB, int NV>
DISCO_CONV_AVX2 void block_avx2(const Job& j, const float* row, const float* wb,
                                const float* bias, std::int64_t kc, std::int64_t s0,
                                float* orow) {
    constexpr int V = 8;
    const std::int64_t cstride = j.batch * (j.rings + 2) * j.width;
    const std::int64_t kstride = j.batch * j.rings * j.sectors;
    __m256 acc[KB][NV];
#pragma GCC unroll 8
    for (int k = 0; k < KB; ++k)
#pragma GCC unroll 3
        for (int v = 0; v < NV; ++v) acc[k][v] = _mm256_set1_ps(bias[k]);
    const float* x = row + s0;
    const float* w = wb;
    for (std::int64_t c = 0; c < j.cin; ++c, x += cstride, w += kTaps * kBlock) {
#pragma GCC unroll 9
        for (int t = 0; t < kTaps; ++t) {
            const float* xt = x + (t / 3) * j.width + t % 3;
            __m256 xv[NV];
#pragma GCC unroll 3
            for (int v = 0; v < NV; ++v) {
                xv[v] = _mm256_loadu_ps(xt + V * v);
                // Keeps the vector in a register: GCC would fold it into each
                // multiply-add as a memory operand, a load per multiply-add.
                __asm__("" : "+x"(xv[v]));
            }
#pragma GCC unroll 8
            for (int k = 0; k < KB; ++k) {
                const __m256 wk = _mm256_broadcast_ss(w + t * kBlock + k);
#pragma GCC unroll 3
                for (int v = 0; v < NV; ++v) acc[k][v] = _mm256_fmadd_ps(wk, xv[v], acc[k][v]);
            }
        }
    }
    const __m256i lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256 zero = _mm256_setzero_ps();
#pragma GCC unroll 3
    for (int v = 0; v < NV; ++v) {
        const std::int64_t n = j.sectors - s0 - V * v;
        if (n <= 0) break;
        const __m256i m = _mm256_cmpgt_epi32(
            _mm256_set1_epi32(static_cast<int>(std::min<std::int64_t>(n, V))), lanes);
#pragma GCC unroll 8
        for (int k = 0; k < KB; ++k) {
            if (k >= kc) break;
            const __m256 y = j.relu ? _mm256_max_ps(acc[k][v], zero) : acc[k][v];
            _mm256_maskstore_ps(orow + k * kstride + s0 + V * v, m, y);
        }
    }
}

// One block of 8 channels as two halves of 4 x 3 vectors: fewer loads per
// multiply-add than 8 x 1, which Zen 2's two load ports need.
template <int NV>
DISCO_CONV_AVX2 void halves_avx2(const Job& j, const float* row, const float* wb,
                                 const float* bias, std::int64_t kc, std::int64_t s0,
                                 float* orow) {
    const std::int64_t kstride = j.batch * j.rings * j.sectors;
    block_avx2<4, NV>(j, row, wb, bias, kc, s0, orow);
    if (kc > 4) block_avx2<4, NV>(j, row, wb + 4, bias + 4, kc - 4, s0, orow + 4 * kstride);
}

DISCO_CONV_AVX2 void run_avx2(const Job& j) {
    constexpr int V = 8;
    const std::int64_t plane = (j.rings + 2) * j.width;
    for (std::int64_t blk = 0; blk * kBlock < j.cout; ++blk) {
        const float* wb = j.packed + blk * j.cin * kTaps * kBlock;
        const float* bias = j.bias + blk * kBlock;
        const std::int64_t kc = std::min<std::int64_t>(kBlock, j.cout - blk * kBlock);
        for (std::int64_t b = 0; b < j.batch; ++b) {
            for (std::int64_t r = 0; r < j.rings; ++r) {
                const float* row = j.padded + b * plane + r * j.width;
                float* orow = j.out + (blk * kBlock * j.batch + b) * j.rings * j.sectors +
                              r * j.sectors;
                std::int64_t s0 = 0;
                for (; s0 + 2 * V < j.sectors; s0 += 3 * V)
                    halves_avx2<3>(j, row, wb, bias, kc, s0, orow);
                if (s0 + V < j.sectors)
                    halves_avx2<2>(j, row, wb, bias, kc, s0, orow);
                else if (s0 < j.sectors)  // 4 x 1 would wait on its 4 sums' latency
                    block_avx2<8, 1>(j, row, wb, bias, kc, s0, orow);
            }
        }
    }
}
#endif

// 3 AVX-512, 2 AVX2, 0 plain: from the cap shared with the voxelizer.
int conv_level(int level) {
#if DISCO_CONV_X86
    return level >= 3 ? 3 : level == 2 ? 2 : 0;
#else
    (void)level;
    return 0;
#endif
}

// Winograd where it measured faster on this project's U-Net (Zen 4; direct / Winograd
// per layer, benchmarks/bench_query.py): at AVX-512 from 10 x 30 images up (1.1 - 1.5x;
// at 5 x 15 its 3 x 8 tiles fill vectors badly: 0.9x), at AVX2 from 5 x 15 up (1.1 -
// 1.6x); never in plain C++, whose Winograd products the compiler vectorizes worse
// than the direct loops (0.5 - 0.9x). Tiny images pay more for the transforms.
bool prefers_winograd(int level, std::int64_t rings, std::int64_t sectors) {
    const std::int64_t cells = rings * sectors;
    if (winograd_level(level) != level) return false;  // only its plain kernel here
    if (level == 3) return cells >= 256;
    if (level == 2) return cells >= 64;
    return false;
}

// Sectors per vector at a level: rows are widened to whole vectors of it.
std::int64_t vector_width(int level) { return level == 3 ? 16 : 8; }

}  // namespace

Conv3x3::Conv3x3(const float* weight, const float* bias, std::int64_t cout, std::int64_t cin)
    : cout_(cout), cin_(cin) {
    if (cout < 1 || cin < 1) throw std::invalid_argument("conv3x3 needs cout >= 1 and cin >= 1");
    const std::int64_t blocks = (cout + kBlock - 1) / kBlock;
    packed_.assign(static_cast<std::size_t>(blocks * cin * kTaps * kBlock), 0.0f);
    bias_.assign(static_cast<std::size_t>(blocks * kBlock), 0.0f);
    for (std::int64_t o = 0; o < cout; ++o) {
        bias_[static_cast<std::size_t>(o)] = bias[o];
        const std::int64_t blk = o / kBlock, k = o % kBlock;
        for (std::int64_t c = 0; c < cin; ++c)
            for (int t = 0; t < kTaps; ++t)
                packed_[static_cast<std::size_t>(((blk * cin + c) * kTaps + t) * kBlock + k)] =
                    weight[(o * cin + c) * kTaps + t];
    }
    winograd_ = std::make_shared<const Conv3x3Winograd>(weight, bias, cout, cin);
}

ConvAlgorithm Conv3x3::choose(std::int64_t rings, std::int64_t sectors) const {
    return prefers_winograd(conv_level(bev_kernel_level()), rings, sectors)
               ? ConvAlgorithm::winograd
               : ConvAlgorithm::direct;
}

void Conv3x3::run(const std::vector<ConvPart>& parts, std::int64_t batch, std::int64_t rings,
                  std::int64_t sectors, bool circular, bool relu, float* out,
                  ConvAlgorithm algorithm) const {
    std::int64_t channels = 0;
    for (const auto& p : parts) {
        if (p.channels < 0) throw std::invalid_argument("conv3x3: negative channel count");
        channels += p.channels;
    }
    if (channels != cin_) throw std::invalid_argument("conv3x3: input channels != cin");
    if (batch < 0 || rings < 0 || sectors < 0)
        throw std::invalid_argument("conv3x3: negative size");
    if (batch == 0 || rings == 0 || sectors == 0) return;
    if (algorithm == ConvAlgorithm::automatic) algorithm = choose(rings, sectors);
    if (algorithm == ConvAlgorithm::winograd)
        return winograd_->run(parts, batch, rings, sectors, circular, relu, out);
    const int level = conv_level(bev_kernel_level());
    const std::int64_t vw = vector_width(level);
    const std::int64_t width = (sectors + vw - 1) / vw * vw + 2;
    // One buffer per thread, kept: a fresh one each call would fault its pages in.
    thread_local std::vector<float> scratch;
    const auto need = static_cast<std::size_t>(cin_ * batch * (rings + 2) * width);
    if (scratch.size() < need) scratch.resize(need);
    pad_input(parts, batch, rings, sectors, width, circular, scratch.data());
    const Job job{scratch.data(), packed_.data(), bias_.data(), cin_,  cout_,
                  batch,          rings,          sectors,      width, relu, out};
#if DISCO_CONV_X86
    if (level == 3) return run_avx512(job);
    if (level == 2) return run_avx2(job);
#endif
    run_plain(job);
}

void max_pool2(const float* x, std::int64_t images, std::int64_t rows, std::int64_t cols,
               float* out) {
    const std::int64_t r2 = rows / 2, c2 = cols / 2;
    for (std::int64_t n = 0; n < images; ++n) {
        const float* img = x + n * rows * cols;
        for (std::int64_t i = 0; i < r2; ++i, out += c2) {
            const float* a = img + 2 * i * cols;
            const float* b = a + cols;
            for (std::int64_t j = 0; j < c2; ++j)
                out[j] = std::max(std::max(a[2 * j], a[2 * j + 1]),
                                  std::max(b[2 * j], b[2 * j + 1]));
        }
    }
}

namespace {
// The non-zero weights of each output of a [outs][ins] matrix, read with strides:
// begin[o] .. begin[o + 1] index into (src, w).
struct Taps {
    std::vector<std::int64_t> begin, src;
    std::vector<float> w;
};

Taps taps_of(const float* m, std::int64_t outs, std::int64_t ins, std::int64_t out_stride,
             std::int64_t in_stride) {
    Taps t;
    t.begin.reserve(static_cast<std::size_t>(outs + 1));
    for (std::int64_t o = 0; o < outs; ++o) {
        t.begin.push_back(static_cast<std::int64_t>(t.src.size()));
        for (std::int64_t i = 0; i < ins; ++i) {
            const float v = m[o * out_stride + i * in_stride];
            if (v != 0.0f) t.src.push_back(i), t.w.push_back(v);
        }
    }
    t.begin.push_back(static_cast<std::int64_t>(t.src.size()));
    return t;
}
}  // namespace

void resize_separable(const float* x, std::int64_t images, std::int64_t rows,
                      std::int64_t cols, const float* row_w, std::int64_t out_rows,
                      const float* col_w, std::int64_t out_cols, float* out) {
    const Taps rt = taps_of(row_w, out_rows, rows, rows, 1);
    const Taps ct = taps_of(col_w, out_cols, cols, 1, out_cols);
    // Bilinear weights give each output column at most two taps: then as two flat
    // tables (a missing tap reads column 0 with weight 0), a loop without branches.
    bool two = true;
    for (std::int64_t j = 0; j < out_cols; ++j) two = two && ct.begin[j + 1] - ct.begin[j] <= 2;
    std::vector<std::int32_t> i0(static_cast<std::size_t>(out_cols), 0), i1 = i0;
    std::vector<float> w0(static_cast<std::size_t>(out_cols), 0.0f), w1 = w0;
    for (std::int64_t j = 0; two && j < out_cols; ++j) {
        const auto b = ct.begin[j], n = ct.begin[j + 1] - b;
        if (n > 0) i0[j] = static_cast<std::int32_t>(ct.src[b]), w0[j] = ct.w[b];
        if (n > 1) i1[j] = static_cast<std::int32_t>(ct.src[b + 1]), w1[j] = ct.w[b + 1];
    }
    std::vector<float> tmp(static_cast<std::size_t>(rows * out_cols));
    for (std::int64_t n = 0; n < images; ++n, x += rows * cols) {
        // Along columns (a gather per output), then whole rows combined.
        for (std::int64_t a = 0; a < rows; ++a) {
            const float* xr = x + a * cols;
            float* tr = tmp.data() + a * out_cols;
            if (two) {
                for (std::int64_t j = 0; j < out_cols; ++j)
                    tr[j] = w0[j] * xr[i0[j]] + w1[j] * xr[i1[j]];
                continue;
            }
            for (std::int64_t j = 0; j < out_cols; ++j) {
                float sum = 0.0f;
                for (auto k = ct.begin[j]; k < ct.begin[j + 1]; ++k) sum += ct.w[k] * xr[ct.src[k]];
                tr[j] = sum;
            }
        }
        for (std::int64_t i = 0; i < out_rows; ++i, out += out_cols) {
            const auto b = rt.begin[i], e = rt.begin[i + 1];
            if (e - b == 2) {  // bilinear: one pass
                const float u = rt.w[b], v = rt.w[b + 1];
                const float* p = tmp.data() + rt.src[b] * out_cols;
                const float* q = tmp.data() + rt.src[b + 1] * out_cols;
                for (std::int64_t j = 0; j < out_cols; ++j) out[j] = u * p[j] + v * q[j];
                continue;
            }
            std::fill(out, out + out_cols, 0.0f);
            for (auto k = b; k < e; ++k) {
                const float w = rt.w[k];
                const float* tr = tmp.data() + rt.src[k] * out_cols;
                for (std::int64_t j = 0; j < out_cols; ++j) out[j] += w * tr[j];
            }
        }
    }
}

const char* conv3x3_kernel_name(int level) {
    if (level < 0) level = bev_kernel_level();
    if (bev_kernel_name(level)[0] == '\0') return "";
    return wide_kernel_name(conv_level(level));
}

}  // namespace disco
