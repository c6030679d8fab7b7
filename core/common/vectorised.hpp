#pragma once

/// Marks a function whose loops are written to vectorise: with GCC on x86-64 it is compiled twice,
/// for AVX2 and for the x86-64 baseline (SSE2), and the dynamic loader picks the one this CPU runs
/// (target_clones, an ifunc); elsewhere it is compiled once. The file holding it is compiled with
/// the vectoriser's dynamic cost model, without errno for math functions and without trapping FP
/// (VSM_VECTORISED_FLAGS in the top CMakeLists.txt), else GCC leaves such loops scalar.
///
/// No FMA: AVX2 alone keeps every operation rounded as in the scalar code, so both clones compute
/// the same bits.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define VSM_VECTORISED __attribute__((target_clones("avx2", "default")))
#else
#define VSM_VECTORISED
#endif

#include <array>
#include <cstddef>

namespace vsm::core {

/// Widens lo and hi (x, y, z) by the points i < n that keep(p) accepts, p = point(i) a
/// std::array<T, 3>. Eight lanes of extremes, combined at the end, so that the loop vectorises in
/// a VSM_VECTORISED caller: GCC does not vectorise a min or max reduction that may see NaN. A
/// point's coordinates count as they would in a scalar loop of `x < lo ? x : lo`. Always inlined:
/// compiled apart it would be neither vectorised nor cloned.
template <class T, class Point, class Keep>
[[gnu::always_inline]] inline void widenBoxInLanes(std::size_t n, Point point, Keep keep, T* lo,
                                                   T* hi) {
  constexpr std::size_t kLanes = 8;
  T loX[kLanes], loY[kLanes], loZ[kLanes], hiX[kLanes], hiY[kLanes], hiZ[kLanes];
  for (std::size_t l = 0; l < kLanes; ++l) {
    loX[l] = lo[0], loY[l] = lo[1], loZ[l] = lo[2];
    hiX[l] = hi[0], hiY[l] = hi[1], hiZ[l] = hi[2];
  }
  const auto widen = [&](std::size_t i, std::size_t l) {
    const std::array<T, 3> p = point(i);
    const bool kept = keep(p);
    loX[l] = (kept & (p[0] < loX[l])) ? p[0] : loX[l];
    loY[l] = (kept & (p[1] < loY[l])) ? p[1] : loY[l];
    loZ[l] = (kept & (p[2] < loZ[l])) ? p[2] : loZ[l];
    hiX[l] = (kept & (hiX[l] < p[0])) ? p[0] : hiX[l];
    hiY[l] = (kept & (hiY[l] < p[1])) ? p[1] : hiY[l];
    hiZ[l] = (kept & (hiZ[l] < p[2])) ? p[2] : hiZ[l];
  };
  std::size_t i = 0;
  for (; i + kLanes <= n; i += kLanes) {
    for (std::size_t l = 0; l < kLanes; ++l) {
      widen(i + l, l);
    }
  }
  for (; i < n; ++i) {
    widen(i, 0);
  }
  for (std::size_t l = 0; l < kLanes; ++l) {
    lo[0] = loX[l] < lo[0] ? loX[l] : lo[0];
    lo[1] = loY[l] < lo[1] ? loY[l] : lo[1];
    lo[2] = loZ[l] < lo[2] ? loZ[l] : lo[2];
    hi[0] = hi[0] < hiX[l] ? hiX[l] : hi[0];
    hi[1] = hi[1] < hiY[l] ? hiY[l] : hi[1];
    hi[2] = hi[2] < hiZ[l] ? hiZ[l] : hi[2];
  }
}

}  // namespace vsm::core
