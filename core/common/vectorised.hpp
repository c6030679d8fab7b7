#pragma once

/// Marks a function whose loops are written to vectorise: with GCC on x86-64 it is compiled twice,
/// for AVX2 and for the x86-64 baseline (SSE2), and the dynamic loader picks the one this CPU runs
/// (target_clones, an ifunc); elsewhere it is compiled once. The file holding it is compiled with
/// the vectoriser's dynamic cost model and without errno for math functions (VSM_VECTORISED_FLAGS
/// in the top CMakeLists.txt), else GCC leaves such loops scalar.
///
/// No FMA: AVX2 alone keeps every operation rounded as in the scalar code, so both clones compute
/// the same bits.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define VSM_VECTORISED __attribute__((target_clones("avx2", "default")))
#else
#define VSM_VECTORISED
#endif
