#pragma once
// The one SIMD layer: xsimd batches for the instruction set this translation unit is compiled for, run-time CPU
// feature detection (cpuid + OS support), and a switch that forces the scalar path (FLEXSPLAT_SIMD=scalar) so tests
// can compare both.
#if defined(__x86_64__) || defined(__i386__)
#include <cpuid.h>
#endif
#if defined(__linux__) && defined(__x86_64__)
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <type_traits>

#include <xsimd/xsimd.hpp>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {
namespace simd {

using arch = xsimd::default_arch;
template <class T>
using batch = xsimd::batch<T, arch>;
template <class T>
inline constexpr std::size_t width = batch<T>::size;

// Horizontal reductions in lane order (xsimd 8.1 has no max reduction; its AVX-512 hadd trips GCC 12 warnings).
template <class T>
T reduce_add(const batch<T>& x) noexcept {
  alignas(64) T lanes[batch<T>::size];
  x.store_aligned(lanes);
  T s = lanes[0];
  for (std::size_t i = 1; i < batch<T>::size; ++i) s += lanes[i];
  return s;
}

template <class T>
T reduce_max(const batch<T>& x) noexcept {
  alignas(64) T lanes[batch<T>::size];
  x.store_aligned(lanes);
  T m = lanes[0];
  for (std::size_t i = 1; i < batch<T>::size; ++i) m = lanes[i] > m ? lanes[i] : m;
  return m;
}

struct CpuFeatures {
  bool sse2 = false, sse41 = false, avx = false, avx2 = false, fma = false;
  bool avx512f = false, avx512bw = false, avx512vl = false, avx512dq = false, avx512bf16 = false;
  bool amx_tile = false, amx_bf16 = false, amx_int8 = false;
  bool os_avx = false, os_avx512 = false, os_amx = false;  // the OS saves the register state
  bool amx_permitted = false;  // Linux granted this process the AMX tile data state (arch_prctl)
};

// Linux enables AMX tile data per process on request (ARCH_REQ_XCOMP_PERM for XFEATURE_XTILEDATA); true if granted.
inline bool request_amx_permission() {
#if defined(__linux__) && defined(__x86_64__)
  constexpr long arch_req_xcomp_perm = 0x1023;
  constexpr long xfeature_xtiledata = 18;
  return ::syscall(SYS_arch_prctl, arch_req_xcomp_perm, xfeature_xtiledata) == 0;
#else
  return false;
#endif
}

inline CpuFeatures detect_cpu_features() {
  CpuFeatures f;
#if defined(__x86_64__) || defined(__i386__)
  unsigned a = 0, b = 0, c = 0, d = 0;
  if (!__get_cpuid(1, &a, &b, &c, &d)) return f;
  f.sse2 = d >> 26 & 1;
  f.sse41 = c >> 19 & 1;
  const bool osxsave = c >> 27 & 1;
  f.fma = c >> 12 & 1;
  f.avx = c >> 28 & 1;
  std::uint64_t xcr0 = 0;
  if (osxsave) {
    unsigned lo = 0, hi = 0;
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    xcr0 = (std::uint64_t(hi) << 32) | lo;
  }
  f.os_avx = (xcr0 & 0x6) == 0x6;
  f.os_avx512 = (xcr0 & 0xe6) == 0xe6;
  f.os_amx = (xcr0 & 0x60000) == 0x60000;
  unsigned max_leaf7_subleaf = 0;
  if (__get_cpuid_count(7, 0, &a, &b, &c, &d)) {
    max_leaf7_subleaf = a;
    f.avx2 = b >> 5 & 1;
    f.avx512f = b >> 16 & 1;
    f.avx512dq = b >> 17 & 1;
    f.avx512bw = b >> 30 & 1;
    f.avx512vl = b >> 31 & 1;
    f.amx_bf16 = d >> 22 & 1;
    f.amx_tile = d >> 24 & 1;
    f.amx_int8 = d >> 25 & 1;
  }
  if (max_leaf7_subleaf >= 1 && __get_cpuid_count(7, 1, &a, &b, &c, &d)) f.avx512bf16 = a >> 5 & 1;
  f.avx = f.avx && f.os_avx;
  f.avx2 = f.avx2 && f.os_avx;
  f.fma = f.fma && f.os_avx;
  f.avx512f = f.avx512f && f.os_avx512;
  f.avx512bw = f.avx512bw && f.os_avx512;
  f.avx512vl = f.avx512vl && f.os_avx512;
  f.avx512dq = f.avx512dq && f.os_avx512;
  f.avx512bf16 = f.avx512bf16 && f.os_avx512;
  f.amx_permitted = f.amx_tile && f.os_amx && request_amx_permission();
#endif
  return f;
}

inline const CpuFeatures& cpu_features() {
  static const CpuFeatures features = detect_cpu_features();
  return features;
}

inline std::string describe(const CpuFeatures& f) {
  std::string s;
  auto add = [&](bool on, const char* name) {
    if (!on) return;
    if (!s.empty()) s += ' ';
    s += name;
  };
  add(f.sse2, "sse2");
  add(f.sse41, "sse4.1");
  add(f.avx, "avx");
  add(f.avx2, "avx2");
  add(f.fma, "fma");
  add(f.avx512f, "avx512f");
  add(f.avx512bw, "avx512bw");
  add(f.avx512vl, "avx512vl");
  add(f.avx512bf16, "avx512bf16");
  add(f.amx_tile && f.os_amx, "amx-tile");
  add(f.amx_bf16 && f.os_amx, "amx-bf16");
  add(f.amx_int8 && f.os_amx, "amx-int8");
  if (f.amx_tile && f.os_amx) s += f.amx_permitted ? " (amx permitted)" : " (amx not permitted by the OS)";
  return s.empty() ? "none detected" : s;
}

// Name of the instruction set this translation unit's batches use.
inline const char* compiled_arch_name() { return arch::name(); }

// A binary built with -march flags the CPU lacks gets a clear error instead of SIGILL in a kernel.
inline void require_cpu_supports_build() {
  const CpuFeatures& f = cpu_features();
  bool ok = true;
#if defined(__AVX512F__)
  ok = ok && f.avx512f;
#endif
#if defined(__AVX2__)
  ok = ok && f.avx2;
#endif
#if defined(__FMA__)
  ok = ok && f.fma;
#endif
  require(ok, "this binary was compiled for ", compiled_arch_name(), " but the CPU offers only: ", describe(f),
          "; rebuild without FLEXSPLAT_NATIVE");
}

// FLEXSPLAT_SIMD=scalar selects the scalar reference path at run time.
inline bool enabled() {
  static const bool on = [] {
    const char* env = std::getenv("FLEXSPLAT_SIMD");
    return !(env && std::strcmp(env, "scalar") == 0);
  }();
  return on;
}

// Lane helpers: one kernel body serves the scalar path (plain T, one lane) and the SIMD path (batch<T>).
template <class V>
struct lane_count {
  static constexpr std::size_t value = 1;
};
template <class T, class A>
struct lane_count<xsimd::batch<T, A>> {
  static constexpr std::size_t value = xsimd::batch<T, A>::size;
};
template <class T>
inline T lane_select(bool c, T a, T b) { return c ? a : b; }
template <class T, class A>
inline xsimd::batch<T, A> lane_select(const xsimd::batch_bool<T, A>& c, const xsimd::batch<T, A>& a,
                                      const xsimd::batch<T, A>& b) {
  return xsimd::select(c, a, b);
}
inline bool lane_any(bool c) { return c; }
inline bool lane_all(bool c) { return c; }
inline bool lane_not(bool c) { return !c; }
template <class T, class A>
inline bool lane_any(const xsimd::batch_bool<T, A>& c) { return xsimd::any(c); }
template <class T, class A>
inline bool lane_all(const xsimd::batch_bool<T, A>& c) { return xsimd::all(c); }
template <class T, class A>
inline xsimd::batch_bool<T, A> lane_not(const xsimd::batch_bool<T, A>& c) { return !c; }
template <class T>
inline T lane_sum(T v) { return v; }
template <class T, class A>
inline T lane_sum(const xsimd::batch<T, A>& v) { return xsimd::hadd(v); }
template <class T>
inline T lane_exp(T v) { return std::exp(v); }
template <class T, class A>
inline xsimd::batch<T, A> lane_exp(const xsimd::batch<T, A>& v) { return xsimd::exp(v); }
template <class T>
inline T lane_min(T a, T b) { return a < b ? a : b; }
template <class T, class A>
inline xsimd::batch<T, A> lane_min(const xsimd::batch<T, A>& a, const xsimd::batch<T, A>& b) { return xsimd::min(a, b); }
template <class T>
inline T lane_max(T a, T b) { return a < b ? b : a; }
template <class T, class A>
inline xsimd::batch<T, A> lane_max(const xsimd::batch<T, A>& a, const xsimd::batch<T, A>& b) { return xsimd::max(a, b); }
// a * b + c: one rounding on the batch path where the target has FMA; the scalar path rounds as the compiler contracts.
template <class T>
inline T lane_fma(T a, T b, T c) { return a * b + c; }
template <class T, class A>
inline xsimd::batch<T, A> lane_fma(const xsimd::batch<T, A>& a, const xsimd::batch<T, A>& b, const xsimd::batch<T, A>& c) {
  return xsimd::fma(a, b, c);
}
template <class V, class T>
inline V lane_load(const T* p) {
  if constexpr (std::is_same_v<V, T>) return *p;
  else return V::load_unaligned(p);
}
template <class T>
inline void lane_store(T* p, T v) { *p = v; }
template <class T, class A>
inline void lane_store(T* p, const xsimd::batch<T, A>& v) { v.store_unaligned(p); }

}  // namespace simd
}  // namespace v0
}  // namespace flexsplat
