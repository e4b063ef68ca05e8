#pragma once
// The one SIMD layer: xsimd batches for the instruction set this translation unit is compiled for, run-time CPU
// feature detection (cpuid + OS support), and a switch that forces the scalar path (FLEXSPLAT_SIMD=scalar) so tests
// can compare both.
#if defined(__x86_64__) || defined(__i386__)
#include <cpuid.h>
#include <immintrin.h>
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
#include "flexsplat/core/inline.hpp"

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
// Scalar type of one lane.
template <class V>
struct lane_scalar {
  using type = V;
};
template <class T, class A>
struct lane_scalar<xsimd::batch<T, A>> {
  using type = T;
};
// Double lanes of a kernel whose float lanes are V: double for the scalar path, the batch of the same instruction set
// for xsimd batches (the dispatch vectors add theirs).
template <class V>
struct double_lanes {
  using type = double;
};
template <class T, class A>
struct double_lanes<xsimd::batch<T, A>> {
  using type = xsimd::batch<double, A>;
};
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_select(bool c, T a, T b) { return c ? a : b; }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_select(const xsimd::batch_bool<T, A>& c, const xsimd::batch<T, A>& a,
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
inline xsimd::batch<T, A> lane_exp(const xsimd::batch<T, A>& v) {
  if constexpr (std::is_same_v<T, double>) {
    // Without a packed double -> int64 conversion (SSE2, AVX2) xsimd casts the exponent in C++, undefined for
    // +-inf and NaN: clamp to +-1000 (exp gives 0 and inf there as well) and pass NaN around the call.
    using V = xsimd::batch<T, A>;
    const V lo(-1000.0), hi(1000.0), zero(0.0);
    const auto nan = v != v;
    const V arg = xsimd::select(nan, zero, xsimd::select(v < lo, lo, xsimd::select(v > hi, hi, v)));
    return xsimd::select(nan, v, xsimd::exp(arg));
  } else {
    return xsimd::exp(v);
  }
}
// erf: std::erf on the scalar path (the reference), xsimd's on the batches; the dispatch vectors add theirs.
template <class T>
inline T lane_erf(T v) { return std::erf(v); }
template <class T, class A>
inline xsimd::batch<T, A> lane_erf(const xsimd::batch<T, A>& v) { return xsimd::erf(v); }
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
// a * b + c rounded the same way on both paths: fused where the target has FMA, a product then a sum otherwise
// (xsimd::fma does the same), so lane bodies written with it match the scalar path bit for bit whatever the compiler
// contracts elsewhere. (lane_fma leaves the scalar rounding to the compiler.)
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_mul_add(T a, T b, T c) {
#if defined(__FMA__)
  return std::fma(a, b, c);
#else
  return a * b + c;
#endif
}
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_mul_add(const xsimd::batch<T, A>& a, const xsimd::batch<T, A>& b,
                                       const xsimd::batch<T, A>& c) {
#if defined(__AVX512F__)
  // xsimd 8.1 has no AVX-512 fma kernel: its generic a * b + c is fused or not as the compiler contracts
  if constexpr (sizeof(xsimd::batch<T, A>) == 64 && std::is_same_v<T, float>) return _mm512_fmadd_ps(a, b, c);
  else if constexpr (sizeof(xsimd::batch<T, A>) == 64 && std::is_same_v<T, double>) return _mm512_fmadd_pd(a, b, c);
  else
#endif
    return xsimd::fma(a, b, c);
}
// Correctly rounded on both paths (IEEE sqrt), so lanes match the scalar path bit for bit.
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_sqrt(T v) { return std::sqrt(v); }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_sqrt(const xsimd::batch<T, A>& v) { return xsimd::sqrt(v); }
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_abs(T v) { return std::abs(v); }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_abs(const xsimd::batch<T, A>& v) { return xsimd::abs(v); }
// Not correctly rounded: the batch log may differ from std::log in the last bit (use it for margins, not results).
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_log(T v) { return std::log(v); }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_log(const xsimd::batch<T, A>& v) { return xsimd::log(v); }
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_floor(T v) { return std::floor(v); }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_floor(const xsimd::batch<T, A>& v) {
#if defined(__SSE2__) && !defined(__SSE4_1__)
  if constexpr (std::is_same_v<T, double>) {
    // Without roundpd xsimd truncates through an emulated 64-bit integer conversion; adding and subtracting 2^52
    // rounds |v| < 2^52 to an integer exactly (larger values, infinities and NaN are their own floor).
    using B = xsimd::batch<double, A>;
    const B big = B(0x1p52), a = xsimd::abs(v);
    B r = xsimd::copysign((a + big) - big, v);
    r = xsimd::select(r > v, r - B(1.0), r);
    return xsimd::select(a < big, r, v);
  } else
#endif
    return xsimd::floor(v);
}
template <class T>
FLEXSPLAT_ALWAYS_INLINE T lane_ceil(T v) { return std::ceil(v); }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch<T, A> lane_ceil(const xsimd::batch<T, A>& v) {
#if defined(__SSE2__) && !defined(__SSE4_1__)
  if constexpr (std::is_same_v<T, double>) return -lane_floor(-v);
  else
#endif
    return xsimd::ceil(v);
}
FLEXSPLAT_ALWAYS_INLINE bool lane_isfinite(float v) { return std::isfinite(v); }
FLEXSPLAT_ALWAYS_INLINE bool lane_isfinite(double v) { return std::isfinite(v); }
template <class T, class A>
FLEXSPLAT_ALWAYS_INLINE xsimd::batch_bool<T, A> lane_isfinite(const xsimd::batch<T, A>& v) { return xsimd::isfinite(v); }
// Mask type of V (bool on the scalar path).
template <class V>
using lane_mask = decltype(V() < V());
template <class V, class T>
inline V lane_load(const T* p) {
  if constexpr (std::is_same_v<V, T>) return *p;
  else return V::load_unaligned(p);
}
template <class T>
inline void lane_store(T* p, T v) { *p = v; }
template <class T, class A>
inline void lane_store(T* p, const xsimd::batch<T, A>& v) { v.store_unaligned(p); }

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
// col[k] lane l = rows[l][j0 + k] for j0 + k < count (other columns unspecified): 16 (masked) row loads, which never
// read past rows[l][count - 1], and a 16 x 16 in-register transpose. For the AVX-512 batches of a native build and
// the dispatched 16-float lanes.
__attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma"))) inline void transpose_rows_avx512(
    const float* const* rows, int j0, int count, __m512 col[16]) {
  const __mmask16 live = count - j0 >= 16 ? __mmask16(0xffff) : __mmask16((1u << (count - j0)) - 1);
  constexpr __mmask16 all = 0xffff;  // masked forms: the plain ones draw false GCC 12 warnings from its own headers
  __m512 r[16], t[16];
  for (int l = 0; l < 16; ++l) r[l] = _mm512_maskz_loadu_ps(live, rows[l] + j0);
  for (int i = 0; i < 8; ++i) {  // pairs of rows interleaved
    t[2 * i] = _mm512_mask_unpacklo_ps(r[2 * i], all, r[2 * i], r[2 * i + 1]);
    t[2 * i + 1] = _mm512_mask_unpackhi_ps(r[2 * i], all, r[2 * i], r[2 * i + 1]);
  }
  for (int g = 0; g < 4; ++g) {  // r[4g + c]: rows 4g..4g+3 of column 4k + c in 128-bit lane k
    r[4 * g] = _mm512_shuffle_ps(t[4 * g], t[4 * g + 2], 0x44);
    r[4 * g + 1] = _mm512_shuffle_ps(t[4 * g], t[4 * g + 2], 0xee);
    r[4 * g + 2] = _mm512_shuffle_ps(t[4 * g + 1], t[4 * g + 3], 0x44);
    r[4 * g + 3] = _mm512_shuffle_ps(t[4 * g + 1], t[4 * g + 3], 0xee);
  }
  for (int c = 0; c < 4; ++c) {  // gather the four row groups of each 128-bit lane
    const __m512 lo01 = _mm512_mask_shuffle_f32x4(r[c], all, r[c], r[4 + c], 0x88);
    const __m512 hi01 = _mm512_mask_shuffle_f32x4(r[c], all, r[c], r[4 + c], 0xdd);
    const __m512 lo23 = _mm512_mask_shuffle_f32x4(r[8 + c], all, r[8 + c], r[12 + c], 0x88);
    const __m512 hi23 = _mm512_mask_shuffle_f32x4(r[8 + c], all, r[8 + c], r[12 + c], 0xdd);
    col[c] = _mm512_mask_shuffle_f32x4(lo01, all, lo01, lo23, 0x88);
    col[4 + c] = _mm512_mask_shuffle_f32x4(hi01, all, hi01, hi23, 0x88);
    col[8 + c] = _mm512_mask_shuffle_f32x4(lo01, all, lo01, lo23, 0xdd);
    col[12 + c] = _mm512_mask_shuffle_f32x4(hi01, all, hi01, hi23, 0xdd);
  }
}
#endif

// Column loads of a row-major block: out[j] lane l = rows[l][j] for j < count (rows[l] may repeat a row). AVX-512
// float: 16 x 16 in-register transposes of (masked) row loads, which never read past rows[l][count - 1]; otherwise
// a scalar transpose through the stack.
template <class V, class T>
inline void load_columns(const T* const* rows, int count, V* out) {
  constexpr int L = int(lane_count<V>::value);
#if defined(__AVX512F__)
  if constexpr (std::is_same_v<T, float> && L == 16) {
    for (int j0 = 0; j0 < count; j0 += 16) {
      __m512 col[16];
      transpose_rows_avx512(rows, j0, count, col);
      for (int k = 0; k < 16 && j0 + k < count; ++k) out[j0 + k] = col[k];
    }
    return;
  }
#endif
  alignas(64) T lanes[L];
  for (int j = 0; j < count; ++j) {
    for (int l = 0; l < L; ++l) lanes[l] = rows[l][j];
    out[j] = lane_load<V>(lanes);
  }
}

}  // namespace simd
}  // namespace v0
}  // namespace flexsplat
