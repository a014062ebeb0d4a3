#pragma once
// The real DFT along the sectors of polar images, for batches of rows (rings): the
// transforms of numpy.fft.rfft and numpy.fft.irfft(n=n) along the last axis, in float32.
//
// A mixed-radix Stockham FFT, vectorized across rows: 16 (AVX-512), 8 (AVX2), 4 (SSE2)
// or 1 (plain) rows run side by side in the lanes of one register, each lane doing the
// same operations in the same order, so every SIMD level gives the same values to the
// bit (the core is built without FMA contraction). Radix 4 and 2 take the powers of
// two, radix 3 and 5 have butterflies of their own, and any other prime factor p a
// direct p-point DFT (a prime length is thus one direct DFT). The SIMD level follows
// the cap shared by the kernels (set_bev_kernel_level).
#include <cstdint>
#include <vector>

namespace disco {

// Twiddles and factors of one length, built once per length and kept.
struct SectorPlan {
    int n = 0;
    struct Stage {
        int radix = 0;
        int len = 0;              // the length this stage splits: radix * (len / radix)
        std::vector<float> wr;    // exp(-2 pi i j u / len): [len / radix][radix - 1]
        std::vector<float> wi;
        std::vector<float> pc;    // cos and sin of 2 pi r / radix, r < radix (butterflies)
        std::vector<float> ps;
    };
    std::vector<Stage> stages;  // the complex DFT of length n
    // Even n: a real row of n is transformed as a complex row of n / 2 (even samples
    // real, odd ones imaginary) by `half`'s stages, and split into the spectrum with
    // exp(-2 pi i k / n), k <= n / 2 (hr, hi).
    std::vector<Stage> half;
    std::vector<float> hr, hi;
};

// The plan of length n >= 1 (thread-safe; plans are kept for the process's life).
const SectorPlan& sector_plan(int n);

// out[row, k] = sum_s in[row, s] exp(-2 pi i k s / n), k <= n / 2: in [rows][n] float32,
// out [rows][n / 2 + 1] complex64 (re, im interleaved).
void rfft_rows(const float* in, std::int64_t rows, std::int64_t n, float* out);

// out[row, s] = (1 / n) sum_k X[k] exp(+2 pi i k s / n) over all k < n, X the Hermitian
// extension of in[row] (X[n - k] = conj(X[k])): numpy.fft.irfft(in, n). The imaginary
// parts of X[0] and, for even n, of X[n / 2] are ignored. in [rows][n / 2 + 1]
// complex64, out [rows][n] float32.
void irfft_rows(const float* in, std::int64_t rows, std::int64_t n, float* out);

// The SIMD level the transforms run at now (0 plain .. 3 AVX-512) and its lane count.
int sector_fft_level();
int sector_fft_lanes(int level);

}  // namespace disco
