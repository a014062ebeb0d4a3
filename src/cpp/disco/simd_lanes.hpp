#pragma once

// The SIMD levels of the kernels written once over a vector type and compiled per level
// (sector_fft, sector_correlation, recentre_curves): SSE2, AVX2 and AVX-512 namespaces
// only on x86-64 GCC, whose vector extensions and target pragmas they use (clang builds
// the plain level alone). simd_lanes.inc defines one level's lanes; simd_levels.inc
// compiles a body at every level.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define DISCO_SIMD_X86 1
#endif
