// The U-Net's 3 x 3 convolution for inference (disco_cli/model/unet_numpy.py), direct
// and register-blocked: a block of 8 output channels times one or two SIMD vectors of
// sectors stays in registers across every input channel and the 9 taps.
//
// Activations are [C, B, R, S] (channels, batch, rings, sectors), float32, row-major.
// The input is one or more such arrays joined along channels (the U-Net's skip
// connections), read as if concatenated. Along sectors the padding wraps around
// (`circular`) or is zero; along rings it is zero. With w the weights [cout, cin, 3, 3]
// (BatchNorm already folded in) and x the input padded by one on every side:
//   out[o, b, r, s] = bias[o] + sum_{c, dy, dx} w[o, c, dy, dx] * x[c, b, r + dy, s + dx]
// then max(0, .) with `relu`. Sums run in float32 in an order that differs between
// kernels (and from BLAS); the SIMD kernels fuse multiply-adds. Plain C++17.
//
// Where it is faster, the convolution runs as Winograd's F(2 x 2, 3 x 3) instead
// (conv3x3_winograd.hpp: 16 multiply-adds per 2 x 2 outputs instead of 36); `choose`
// says where, and `run` can be told which.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

namespace disco {

class Conv3x3Winograd;

enum class ConvAlgorithm { automatic, direct, winograd };

// One input part: `channels` channels of [B, R, S], contiguous.
struct ConvPart {
    const float* data;
    std::int64_t channels;
};

class Conv3x3 {
  public:
    // weight [cout][cin][3][3], bias [cout]; throws std::invalid_argument when
    // cout or cin < 1.
    Conv3x3(const float* weight, const float* bias, std::int64_t cout, std::int64_t cin);

    std::int64_t cout() const { return cout_; }
    std::int64_t cin() const { return cin_; }

    // out [cout][batch][rings][sectors] of the parts joined along channels (their
    // channels must add up to cin: std::invalid_argument otherwise), by `algorithm`
    // (automatic: the one `choose` names). Safe to call from several threads at once.
    void run(const std::vector<ConvPart>& parts, std::int64_t batch, std::int64_t rings,
             std::int64_t sectors, bool circular, bool relu, float* out,
             ConvAlgorithm algorithm = ConvAlgorithm::automatic) const;

    // The algorithm `automatic` runs on rings x sectors images at the kernel level in
    // use: direct or winograd (see conv3x3.cpp for the rule).
    ConvAlgorithm choose(std::int64_t rings, std::int64_t sectors) const;

  private:
    std::int64_t cout_, cin_;
    // Weights by block of 8 output channels: [cout / 8 rounded up][cin][9 taps][8],
    // zero past cout; bias padded the same way.
    std::vector<float> packed_;
    std::vector<float> bias_;
    std::shared_ptr<const Conv3x3Winograd> winograd_;  // its transformed weights
};

// The U-Net's other steps, on images [N][rows][cols] (N = C * B):
// 2 x 2 max-pooling, out [N][rows / 2][cols / 2] (an odd last row or column dropped,
// as torch's MaxPool2d(2) does).
void max_pool2(const float* x, std::int64_t images, std::int64_t rows, std::int64_t cols,
               float* out);
// A separable linear resize, out[n] = row_w @ x[n] @ col_w with row_w [out_rows][rows]
// and col_w [cols][out_cols] (the U-Net's bilinear 2x upsampling): each output sums
// only its non-zero weights, so a bilinear one costs two multiply-adds per pass.
void resize_separable(const float* x, std::int64_t images, std::int64_t rows,
                      std::int64_t cols, const float* row_w, std::int64_t out_rows,
                      const float* col_w, std::int64_t out_cols, float* out);

// The kernel that runs at `level` of the SIMD cap shared with the BEV voxelizer
// (set_bev_kernel_level, polar_bev.hpp; -1: the level in use): "avx512" (3), "avx2"
// (2, AVX2 + FMA) or "plain" (1 and 0, portable C++); "" for a level this CPU lacks.
const char* conv3x3_kernel_name(int level = -1);

}  // namespace disco
