// The U-Net's 3 x 3 convolution by Winograd's F(2 x 2, 3 x 3): each 2 x 2 block of
// outputs from a 4 x 4 tile of the padded input (tiles overlap by 2), as
//   Y = A^T [ (G g G^T) . (B^T d B) ] A
// with g a 3 x 3 kernel, d the tile and . the element-wise product, summed over input
// channels before A^T . A. That costs 16 multiply-adds per 4 outputs and channel pair
// where the direct kernel (conv3x3.cpp) spends 36, plus the transforms of each input
// tile (per input channel) and output tile (per output channel): a gain where the
// channels are many enough for the products to outweigh the transforms.
//
// Same contract as Conv3x3::run (conv3x3.hpp): activations [C, B, R, S], input parts
// joined along channels, sectors padded circularly or with zeros, rings with zeros,
// bias and an optional ReLU; odd R or S (partial tiles) allowed. Sums run in float32 in
// another order than the direct kernel's and pass through the transforms, so the two
// agree within rounding, not to the bit. C++17 with the vector extensions GCC and clang
// share (its SIMD kernels: GCC only, winograd_level).
#pragma once

#include <cstdint>
#include <vector>

#include "disco/conv3x3.hpp"  // ConvPart

namespace disco {

class Conv3x3Winograd {
  public:
    // weight [cout][cin][3][3], bias [cout]; G g G^T is computed here once, in double.
    // std::invalid_argument when cout or cin < 1.
    Conv3x3Winograd(const float* weight, const float* bias, std::int64_t cout,
                    std::int64_t cin);

    std::int64_t cout() const { return cout_; }
    std::int64_t cin() const { return cin_; }

    // As Conv3x3::run; the caller has checked the parts (their channels add up to cin)
    // and the sizes (all >= 1). Safe to call from several threads at once.
    void run(const std::vector<ConvPart>& parts, std::int64_t batch, std::int64_t rings,
             std::int64_t sectors, bool circular, bool relu, float* out) const;

  private:
    std::int64_t cout_, cin_;
    // The transformed weights by position xi of the 4 x 4 tile and block of 8 output
    // channels: [16][cout / 8 rounded up][cin][8], zero past cout.
    std::vector<float> u_;
    std::vector<float> bias_;  // padded to whole blocks of 8
};

// The SIMD level Conv3x3Winograd::run works at under the kernel level `level`: 3
// (AVX-512), 2 (AVX2 + FMA) or 0 (plain C++). Its vector code is written with GCC's
// vector extensions (__builtin_shuffle among them), so other compilers, clang
// included, get the plain kernel at every level.
int winograd_level(int level);

}  // namespace disco
