#pragma once
// Circular cross-correlations along the sectors of polar images, many pairs in one
// call: the aligned correlations that re-rank candidates (disco_cli/model/verify.py,
// aligned_correlations) and the whitened phase-correlation curves of the plain yaw
// (disco_cli/model/yaw.py, correlation_curves). The spectra along sectors come from
// sector_fft.hpp's transforms with the candidates side by side in the lanes of a
// vector, so each candidate's values are worked out with the same operations in the
// same order at every SIMD level: the levels agree to the bit. The SIMD level follows
// the cap shared by the kernels (set_bev_kernel_level).
#include <cstdint>

namespace disco {

// scores[v, k] (float32 [views][count]): the peak over circular shifts along sectors of
// the cross-correlation of query image v and candidate k, summed over rings, each image
// centred first (its mean over all cells subtracted, in float32), divided by the
// product of the centred images' norms and clipped to [-1, 1]; 0 where either image is
// all one value (a zero norm). queries float32 [views][rings][sectors], candidates
// float32 [count][rings][sectors] with candidate k at candidates + k * stride (stride >=
// 0 floats: a channel of larger features needs no copy); views or count may be 0.
void aligned_correlations(const float* queries, std::int64_t views, const float* candidates,
                          std::int64_t count, std::int64_t stride, std::int64_t rings,
                          std::int64_t sectors, float* scores);

// aligned_correlations with candidate k at candidates[k] (each [rings][sectors],
// contiguous): rows held apart, as a cache holds them, read where they lie.
void aligned_correlations_at(const float* queries, std::int64_t views,
                             const float* const* candidates, std::int64_t count,
                             std::int64_t rings, std::int64_t sectors, float* scores);

// curves[k, s] (float32 [count][sectors]): the phase-correlation curve of query
// [rings][sectors] against match k of matches [count][rings][sectors] (float32):
//   C[r, f] = Q[r, f] conj(M_k[r, f]), Q and M_k the spectra along sectors,
//   floor = 1e-3 max over r, f of |C| + 1e-12,
//   Y[f] = sum over r = 0 .. rings - 1 in order of C weight[r] / (|C| + floor),
//   curve = irfft(Y, sectors).
// weights float32 [rings]; match k at matches + k * stride (floats); count may be 0.
void yaw_curves(const float* query, const float* matches, std::int64_t count,
                std::int64_t stride, std::int64_t rings, std::int64_t sectors,
                const float* weights, float* curves);

// yaw_curves' curves turned into yaw.estimate_yaw_conf's yaws [count] (degrees in
// (-180, 180]: the first highest bin plus a parabola's offset, clipped to half a bin)
// and confidences [count] (1 - max(0, the highest bin more than `sep` bins from the
// best) / the best, clipped to [0, 1]; 0 where the best is not positive).
void yaw_conf(const float* query, const float* matches, std::int64_t count,
              std::int64_t stride, std::int64_t rings, std::int64_t sectors,
              const float* weights, std::int64_t sep, float* yaws, float* confs);

}  // namespace disco
