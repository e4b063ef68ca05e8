#pragma once
// The run-time dispatched SIMD lanes (core/simd_dispatch.hpp: AVX2, AVX-512) a kernel test compares with its scalar
// path. Each level gets its own test case, named "... (avx2)" / "... (avx512)" (FLEXSPLAT_DISPATCH_TEST_CASES), which
// skips (FLEXSPLAT_SKIP, tests/skip.hpp) where the build has no dispatch or the CPU lacks the level: a lane that did
// not run shows in ctest's output by name, never as a pass, and .ci/run allows the skip only where /proc/cpuinfo lacks
// the level's flags (docs/testing.md).
#include "flexsplat/core/simd_dispatch.hpp"
#include "skip.hpp"

namespace flexsplat_test {

// Whether this CPU runs `level`'s dispatch vectors: the features dispatch_level() asks for (.ci/run's missing_levels
// reads the same flags from /proc/cpuinfo).
inline bool cpu_runs(flexsplat::simd::DispatchLevel level) {
  const auto& f = flexsplat::simd::cpu_features();
  return level == flexsplat::simd::DispatchLevel::avx512 ? f.avx512f && f.avx512dq && f.avx512bw && f.avx512vl && f.fma
                                                         : f.avx2 && f.fma;
}

// The lanes with_lanes runs for a dispatch level.
inline flexsplat::simd::Lanes dispatch_lanes(flexsplat::simd::DispatchLevel level) {
  return level == flexsplat::simd::DispatchLevel::avx512 ? flexsplat::simd::Lanes::avx512 : flexsplat::simd::Lanes::avx2;
}

}  // namespace flexsplat_test

// First in a test case of one dispatch level: skips it where this build or this CPU cannot run the level's lanes.
#define FLEXSPLAT_REQUIRE_DISPATCH(level)                                                                          \
  do {                                                                                                             \
    if (!FLEXSPLAT_SIMD_DISPATCH) FLEXSPLAT_SKIP("this build has no run-time SIMD dispatch (GCC or Clang on x86)"); \
    if (!flexsplat_test::cpu_runs(level))                                                                          \
      FLEXSPLAT_SKIP("CPU lacks " << flexsplat::simd::dispatch_name(level) << ": its dispatched lanes cannot run here"); \
  } while (false)

// Two test cases, "name (avx2)" and "name (avx512)": each calls check(lanes) with its level's lanes, or skips.
#define FLEXSPLAT_DISPATCH_TEST_CASES(name, tags, check)                                              \
  TEST_CASE(name " (avx2)", tags) {                                                                 \
    FLEXSPLAT_REQUIRE_DISPATCH(flexsplat::simd::DispatchLevel::avx2);                               \
    check(flexsplat_test::dispatch_lanes(flexsplat::simd::DispatchLevel::avx2));                    \
  }                                                                                                 \
  TEST_CASE(name " (avx512)", tags) {                                                               \
    FLEXSPLAT_REQUIRE_DISPATCH(flexsplat::simd::DispatchLevel::avx512);                             \
    check(flexsplat_test::dispatch_lanes(flexsplat::simd::DispatchLevel::avx512));                  \
  }
