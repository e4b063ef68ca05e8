#pragma once
// Run-time dispatch for kernels written against the lane helpers of core/simd.hpp: a portable build (compiled for
// SSE2) still runs them 8 or 16 lanes wide on CPUs with AVX2 or AVX-512. `wide<T, N>` wraps a GCC vector-extension
// vector with the lane-helper interface; a kernel instantiated with it and inlined (flatten) into a function
// compiled for the wider target gets that target's instructions. The compile-time path (xsimd batches) and the
// scalar path stay; tests compare all of them.
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <type_traits>

#include "flexsplat/core/simd.hpp"

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define FLEXSPLAT_SIMD_DISPATCH 1
#include <immintrin.h>
#else
#define FLEXSPLAT_SIMD_DISPATCH 0
#endif

namespace flexsplat {
inline namespace v0 {
namespace simd {

// Widest level the kernels may dispatch to: FLEXSPLAT_SIMD=scalar disables SIMD, =avx2 caps dispatch at AVX2.
enum class DispatchLevel { none, avx2, avx512 };

inline DispatchLevel dispatch_level() {
  static const DispatchLevel level = [] {
    if (!enabled()) return DispatchLevel::none;
    const CpuFeatures& f = cpu_features();
    const char* env = std::getenv("FLEXSPLAT_SIMD");
    const bool cap_avx2 = env && std::strcmp(env, "avx2") == 0;
    if (!cap_avx2 && f.avx512f && f.avx512bw && f.avx512dq && f.avx512vl && f.fma) return DispatchLevel::avx512;
    if (f.avx2 && f.fma) return DispatchLevel::avx2;
    return DispatchLevel::none;
  }();
  return level;
}

inline const char* dispatch_name(DispatchLevel level) {
  return level == DispatchLevel::avx512 ? "avx512" : level == DispatchLevel::avx2 ? "avx2" : "none";
}

// The vector-extension wrapper and its target-free helpers exist wherever GCC or Clang compiles (fixed-width rows of
// any kernel use them); what follows them needs x86 and its target attributes.
#if defined(__GNUC__)

namespace detail {
template <class T>
using lane_int = std::conditional_t<sizeof(T) == 4, std::int32_t, std::int64_t>;
}

template <class T, int N>
struct wide_mask {
  typedef detail::lane_int<T> native __attribute__((vector_size(sizeof(T) * N)));
  native m;
  wide_mask() = default;
  static wide_mask make(native x) {
    wide_mask w;
    w.m = x;
    return w;
  }
  friend wide_mask operator&(wide_mask a, wide_mask b) { return make(a.m & b.m); }
  friend wide_mask operator|(wide_mask a, wide_mask b) { return make(a.m | b.m); }
  friend wide_mask operator!(wide_mask a) { return make(~a.m); }
};

template <class T, int N>
struct wide {
  typedef T native __attribute__((vector_size(sizeof(T) * N)));
  native v;
  wide() = default;
  wide(T x) : v(native{} + x) {}  // broadcast, like xsimd's batch(T)
  static wide make(native x) {
    wide w;
    w.v = x;
    return w;
  }
  static wide load_unaligned(const T* p) {
    native x;
    std::memcpy(&x, p, sizeof(x));
    return make(x);
  }
  friend wide operator+(wide a, wide b) { return make(a.v + b.v); }
  friend wide operator-(wide a, wide b) { return make(a.v - b.v); }
  friend wide operator*(wide a, wide b) { return make(a.v * b.v); }
  friend wide operator/(wide a, wide b) { return make(a.v / b.v); }
  friend wide operator-(wide a) { return make(-a.v); }
  friend wide operator*(T a, wide b) { return make(a * b.v); }
  friend wide operator*(wide a, T b) { return make(a.v * b); }
  friend wide_mask<T, N> operator<(wide a, wide b) { return wide_mask<T, N>::make(a.v < b.v); }
  friend wide_mask<T, N> operator<=(wide a, wide b) { return wide_mask<T, N>::make(a.v <= b.v); }
  friend wide_mask<T, N> operator>(wide a, wide b) { return wide_mask<T, N>::make(a.v > b.v); }
  friend wide_mask<T, N> operator>=(wide a, wide b) { return wide_mask<T, N>::make(a.v >= b.v); }
  friend wide_mask<T, N> operator!=(wide a, wide b) { return wide_mask<T, N>::make(a.v != b.v); }
  friend wide_mask<T, N> operator==(wide a, wide b) { return wide_mask<T, N>::make(a.v == b.v); }
  wide& operator+=(wide b) {
    v += b.v;
    return *this;
  }
};

template <class T, int N>
struct lane_count<wide<T, N>> {
  static constexpr std::size_t value = std::size_t(N);
};

template <int N>
struct double_lanes<wide<float, N>> {
  using type = wide<double, N / 2>;
};

template <class T, int N>
inline wide<T, N> lane_select(wide_mask<T, N> c, wide<T, N> a, wide<T, N> b) {
  return wide<T, N>::make(c.m ? a.v : b.v);
}
template <class T, int N>
inline wide<T, N> lane_min(wide<T, N> a, wide<T, N> b) {
  return wide<T, N>::make(a.v < b.v ? a.v : b.v);
}
template <class T, int N>
inline wide<T, N> lane_max(wide<T, N> a, wide<T, N> b) {
  return wide<T, N>::make(a.v < b.v ? b.v : a.v);
}
template <class T, int N>
inline wide_mask<T, N> lane_not(wide_mask<T, N> c) {
  return !c;
}
template <class T, int N>
inline void lane_store(T* p, wide<T, N> x) {
  std::memcpy(p, &x.v, sizeof(x.v));
}
template <class T, int N>
inline T lane_sum(wide<T, N> x) {  // lanes in order, like reduce_add
  T s = x.v[0];
  for (int i = 1; i < N; ++i) s += x.v[i];
  return s;
}
#endif  // __GNUC__

#if FLEXSPLAT_SIMD_DISPATCH

// Any / all through the sign bits of the mask lanes (256-bit vectors); the overload carries the AVX2 target of the
// kernels that use it.
__attribute__((target("avx2"))) inline bool lane_any(wide_mask<float, 8> c) {
  __m256 x;
  std::memcpy(&x, &c.m, sizeof(x));
  return _mm256_movemask_ps(x) != 0;
}
__attribute__((target("avx2"))) inline bool lane_any(wide_mask<double, 4> c) {
  return _mm256_movemask_pd(reinterpret_cast<__m256d>(c.m)) != 0;
}
template <class T, int N>
inline bool lane_all(wide_mask<T, N> c) {
  return !lane_any(!c);
}
// x - x is 0 for a finite x and NaN otherwise.
template <class T, int N>
inline wide_mask<T, N> lane_isfinite(wide<T, N> x) {
  return wide_mask<T, N>::make((x.v - x.v) == 0);
}

// The 256-bit widths' square root (IEEE, as std::sqrt), floor and ceil, through the AVX intrinsics. Functions
// compiled for AVX2 call nothing compiled without it with a vector argument (Clang rejects that ABI change), so the
// results are assembled in place.
#define FLEXSPLAT_AVX2_TARGET __attribute__((target("avx2,fma")))
FLEXSPLAT_AVX2_TARGET inline wide<float, 8> lane_sqrt(wide<float, 8> x) {
  wide<float, 8> r;
  r.v = reinterpret_cast<wide<float, 8>::native>(_mm256_sqrt_ps(reinterpret_cast<__m256>(x.v)));
  return r;
}
FLEXSPLAT_AVX2_TARGET inline wide<double, 4> lane_sqrt(wide<double, 4> x) {
  wide<double, 4> r;
  r.v = reinterpret_cast<wide<double, 4>::native>(_mm256_sqrt_pd(reinterpret_cast<__m256d>(x.v)));
  return r;
}
FLEXSPLAT_AVX2_TARGET inline wide<double, 4> lane_floor(wide<double, 4> x) {
  wide<double, 4> r;
  r.v = reinterpret_cast<wide<double, 4>::native>(_mm256_floor_pd(reinterpret_cast<__m256d>(x.v)));
  return r;
}
FLEXSPLAT_AVX2_TARGET inline wide<double, 4> lane_ceil(wide<double, 4> x) {
  wide<double, 4> r;
  r.v = reinterpret_cast<wide<double, 4>::native>(_mm256_ceil_pd(reinterpret_cast<__m256d>(x.v)));
  return r;
}
#undef FLEXSPLAT_AVX2_TARGET
// a * b + c rounded as the scalar lane_mul_add of this build: fused only where the build itself has FMA (the
// dispatching functions turn off contraction otherwise, so the lanes match the scalar path bit for bit).
template <class T, int N>
inline wide<T, N> lane_mul_add(wide<T, N> a, wide<T, N> b, wide<T, N> c) {
#if defined(__FMA__)
  if constexpr (sizeof(T) * N == 32 && sizeof(T) == 4)
    return wide<T, N>::make(reinterpret_cast<typename wide<T, N>::native>(_mm256_fmadd_ps(
        reinterpret_cast<__m256>(a.v), reinterpret_cast<__m256>(b.v), reinterpret_cast<__m256>(c.v))));
  else if constexpr (sizeof(T) * N == 32)
    return wide<T, N>::make(reinterpret_cast<typename wide<T, N>::native>(_mm256_fmadd_pd(
        reinterpret_cast<__m256d>(a.v), reinterpret_cast<__m256d>(b.v), reinterpret_cast<__m256d>(c.v))));
  else
#endif
    return a * b + c;
}

// log of double lanes: x = 2^e m with m in [0.75, 1.5), log m = 2 atanh(s), s = (m - 1) / (m + 1) in [-1/7, 1/5),
// by its series to s^23 (truncation below 1e-18 relative), plus e ln 2 in two parts (ln2_hi has 32 significant
// bits, so e ln2_hi is exact). Within a few ulp of std::log (tested); for margins, like lane_log of the batches.
inline constexpr double log_ln2_hi = 0.693147180369123816490, log_ln2_lo = 1.90821492927058770002e-10;
inline constexpr double log_series[12] = {1.0,        1.0 / 3.0,  1.0 / 5.0,  1.0 / 7.0,  1.0 / 9.0,  1.0 / 11.0,
                                          1.0 / 13.0, 1.0 / 15.0, 1.0 / 17.0, 1.0 / 19.0, 1.0 / 21.0, 1.0 / 23.0};
// Vector-extension form (positive normal x; other inputs give unspecified values): exponent and mantissa through the
// bits, the exponent as a double by the 2^52 bias trick.
template <int N>
inline wide<double, N> lane_log(wide<double, N> x) {
  using W = typename wide<double, N>::native;
  using I = typename wide_mask<double, N>::native;
  I bits;
  std::memcpy(&bits, &x.v, sizeof(bits));
  const I mantissa_bits = (bits & 0x000fffffffffffffLL) | 0x3ff0000000000000LL;
  const I exponent_bits = ((bits >> 52) & 0x7ff) | 0x4330000000000000LL;
  W m, e;
  std::memcpy(&m, &mantissa_bits, sizeof(m));
  std::memcpy(&e, &exponent_bits, sizeof(e));
  e = e - (0x1p52 + 1023.0);
  const I high = m >= 1.5;
  m = high ? m * 0.5 : m;
  e = high ? e + 1.0 : e;
  const W s = (m - 1.0) / (m + 1.0), z = s * s;
  W series = W{} + log_series[11];
  for (int k = 10; k >= 0; --k) series = series * z + log_series[k];
  return wide<double, N>::make(e * log_ln2_hi + (e * log_ln2_lo + 2.0 * s * series));
}

// exp at float precision for the blending kernels: Cody-Waite reduction by ln 2, degree-7 Taylor polynomial on
// |r| <= ln(2)/2 (truncation 1e-8, below float rounding; evaluated for latency, as the blend waits on it), scaled
// by 2^k through the exponent bits. Inputs below -87 give 0; +inf and NaN are not expected (the kernels pass
// -sigma <= 0).
template <class T, int N>
inline wide<T, N> lane_exp(wide<T, N> x) {
  static_assert(sizeof(T) == 4, "lane_exp of dispatch vectors is accurate to float precision only");
  using W = typename wide<T, N>::native;
  using I = typename wide_mask<T, N>::native;
  constexpr T log2e = T(1.4426950408889634), ln2_hi = T(0.693145751953125), ln2_lo = T(1.4286068203094172e-06);
  constexpr T lowest = T(-87.0);
  constexpr T round_magic = T(12582912.0);  // 1.5 * 2^23: adding it rounds to an integer
  const W clamped = x.v < lowest ? W{} + lowest : x.v;
  const W k = (clamped * log2e + round_magic) - round_magic;  // round to nearest
  const W r = (clamped - k * ln2_hi) - k * ln2_lo;
  // exp(r) = 1 + (r + r^2 g(r)), g by Estrin's scheme (short dependency chains); adding the 1 last keeps the
  // rounding of Horner's form.
  const W r2 = r * r, r4 = r2 * r2;
  const W g = ((r * T(1.0 / 5040.0) + T(1.0 / 720.0)) * r4 + (r * T(1.0 / 120.0) + T(1.0 / 24.0)) * r2) +
              (r * T(1.0 / 6.0) + T(0.5));
  const W p = (r2 * g + r) + T(1.0);
  const I scale = (__builtin_convertvector(k, I) + 127) << 23;
  W scale_value;
  std::memcpy(&scale_value, &scale, sizeof(scale_value));
  W result = p * scale_value;
  result = x.v < lowest ? W{} : result;
  return wide<T, N>::make(result);
}

// erf at float precision for the dispatch vectors: the float kernel of xsimd 8 (from Boost.SIMD), x P(x^2) for
// |x| < 2/3, else 1 - exp(-x^2) Q(|x| / (1 + |x|) - 0.4), both sides evaluated and one selected per lane; |x| is
// capped at 10 (erf is 1 in float from 3.92 on), so infinities give +-1. Within a few ulp of std::erf (tested).
inline constexpr float erf_small[6] = {std::bit_cast<float>(0x3f906ebau), std::bit_cast<float>(0xbec0937eu),
                                       std::bit_cast<float>(0x3de70f22u), std::bit_cast<float>(0xbcdb61f4u),
                                       std::bit_cast<float>(0x3ba4468du), std::bit_cast<float>(0xba1fc83bu)};
inline constexpr float erfc_large[11] = {
    std::bit_cast<float>(0x3f0a0e8bu), std::bit_cast<float>(0xbf918a62u), std::bit_cast<float>(0x3e243828u),
    std::bit_cast<float>(0x3ec4ca6eu), std::bit_cast<float>(0x3e1175c7u), std::bit_cast<float>(0x3e2006f0u),
    std::bit_cast<float>(0xbfaea865u), std::bit_cast<float>(0x4050b063u), std::bit_cast<float>(0xc0cd1a85u),
    std::bit_cast<float>(0x40d67e3bu), std::bit_cast<float>(0xc0283611u)};
template <class V>
inline V erf_float_lanes(V x) {
  const V zero(0.0f), one(1.0f);
  const auto negative = x < zero;
  const V a = lane_min(lane_select(negative, -x, x), V(10.0f));
  const V a2 = a * a;
  V p(erf_small[5]);
  for (int k = 4; k >= 0; --k) p = p * a2 + V(erf_small[k]);
  V q(erfc_large[10]);
  const V z = a / (one + a) - V(0.4f);
  for (int k = 9; k >= 0; --k) q = q * z + V(erfc_large[k]);
  const V large = one - lane_exp(-a2) * q;
  return lane_select(a < V(2.0f / 3.0f), x * p, lane_select(negative, -large, large));
}
template <class T, int N>
inline wide<T, N> lane_erf(wide<T, N> x) {
  static_assert(sizeof(T) == 4, "lane_erf of dispatch vectors is accurate to float precision only");
  return erf_float_lanes(x);
}

// 16 floats and 8 doubles with AVX-512 mask registers: GCC lowers vector-extension comparisons of 512-bit vectors
// lane by lane, so this width is written with intrinsics (every function carries the AVX-512 target of the kernels
// that use it). avx512_ops<T> names the intrinsics of one lane type, and one template serves both types.
#define FLEXSPLAT_AVX512_TARGET __attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma")))
template <class T>
struct avx512_ops;
template <>
struct avx512_ops<float> {
  using vec = __m512;
  using mask = __mmask16;
  static constexpr mask all = 0xffff;
  static FLEXSPLAT_AVX512_TARGET inline vec set1(float x) { return _mm512_set1_ps(x); }
  static FLEXSPLAT_AVX512_TARGET inline vec loadu(const float* p) { return _mm512_loadu_ps(p); }
  static FLEXSPLAT_AVX512_TARGET inline void storeu(float* p, vec x) { _mm512_storeu_ps(p, x); }
  static FLEXSPLAT_AVX512_TARGET inline vec add(vec a, vec b) { return _mm512_add_ps(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec sub(vec a, vec b) { return _mm512_sub_ps(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec mul(vec a, vec b) { return _mm512_mul_ps(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec div(vec a, vec b) { return _mm512_div_ps(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec fmadd(vec a, vec b, vec c) { return _mm512_fmadd_ps(a, b, c); }
  static FLEXSPLAT_AVX512_TARGET inline vec sqrt(vec x) { return _mm512_mask_sqrt_ps(x, all, x); }
  static FLEXSPLAT_AVX512_TARGET inline vec blend(mask m, vec a, vec b) { return _mm512_mask_blend_ps(m, a, b); }
  template <int Predicate>
  static FLEXSPLAT_AVX512_TARGET inline mask cmp(vec a, vec b) { return _mm512_cmp_ps_mask(a, b, Predicate); }
};
template <>
struct avx512_ops<double> {
  using vec = __m512d;
  using mask = __mmask8;
  static constexpr mask all = 0xff;
  static FLEXSPLAT_AVX512_TARGET inline vec set1(double x) { return _mm512_set1_pd(x); }
  static FLEXSPLAT_AVX512_TARGET inline vec loadu(const double* p) { return _mm512_loadu_pd(p); }
  static FLEXSPLAT_AVX512_TARGET inline void storeu(double* p, vec x) { _mm512_storeu_pd(p, x); }
  static FLEXSPLAT_AVX512_TARGET inline vec add(vec a, vec b) { return _mm512_add_pd(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec sub(vec a, vec b) { return _mm512_sub_pd(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec mul(vec a, vec b) { return _mm512_mul_pd(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec div(vec a, vec b) { return _mm512_div_pd(a, b); }
  static FLEXSPLAT_AVX512_TARGET inline vec fmadd(vec a, vec b, vec c) { return _mm512_fmadd_pd(a, b, c); }
  static FLEXSPLAT_AVX512_TARGET inline vec sqrt(vec x) { return _mm512_mask_sqrt_pd(x, all, x); }
  static FLEXSPLAT_AVX512_TARGET inline vec blend(mask m, vec a, vec b) { return _mm512_mask_blend_pd(m, a, b); }
  template <int Predicate>
  static FLEXSPLAT_AVX512_TARGET inline mask cmp(vec a, vec b) { return _mm512_cmp_pd_mask(a, b, Predicate); }
};

template <class T, int N>
concept avx512_lanes = sizeof(T) * N == 64;

template <class T, int N>
  requires avx512_lanes<T, N>
struct wide_mask<T, N> {
  using bits = typename avx512_ops<T>::mask;
  bits m;
  static FLEXSPLAT_AVX512_TARGET inline wide_mask make(bits x) {
    wide_mask w;
    w.m = x;
    return w;
  }
  friend FLEXSPLAT_AVX512_TARGET inline wide_mask operator&(wide_mask a, wide_mask b) { return make(bits(a.m & b.m)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide_mask operator|(wide_mask a, wide_mask b) { return make(bits(a.m | b.m)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide_mask operator!(wide_mask a) { return make(bits(~a.m)); }
};

template <class T, int N>
  requires avx512_lanes<T, N>
struct wide<T, N> {
  using ops = avx512_ops<T>;
  using mask = wide_mask<T, N>;
  typename ops::vec v;
  FLEXSPLAT_AVX512_TARGET wide() = default;
  FLEXSPLAT_AVX512_TARGET wide(T x) : v(ops::set1(x)) {}
  static FLEXSPLAT_AVX512_TARGET inline wide make(typename ops::vec x) {
    wide w;
    w.v = x;
    return w;
  }
  static FLEXSPLAT_AVX512_TARGET inline wide load_unaligned(const T* p) { return make(ops::loadu(p)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator+(wide a, wide b) { return make(ops::add(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator-(wide a, wide b) { return make(ops::sub(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator*(wide a, wide b) { return make(ops::mul(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator/(wide a, wide b) { return make(ops::div(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator-(wide a) { return make(ops::sub(ops::set1(T(0)), a.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator*(T a, wide b) { return make(ops::mul(ops::set1(a), b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline wide operator*(wide a, T b) { return make(ops::mul(a.v, ops::set1(b))); }
  friend FLEXSPLAT_AVX512_TARGET inline mask operator<(wide a, wide b) { return mask::make(ops::template cmp<_CMP_LT_OQ>(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline mask operator<=(wide a, wide b) { return mask::make(ops::template cmp<_CMP_LE_OQ>(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline mask operator>(wide a, wide b) { return mask::make(ops::template cmp<_CMP_GT_OQ>(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline mask operator>=(wide a, wide b) { return mask::make(ops::template cmp<_CMP_GE_OQ>(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline mask operator!=(wide a, wide b) { return mask::make(ops::template cmp<_CMP_NEQ_UQ>(a.v, b.v)); }
  friend FLEXSPLAT_AVX512_TARGET inline mask operator==(wide a, wide b) { return mask::make(ops::template cmp<_CMP_EQ_OQ>(a.v, b.v)); }
  FLEXSPLAT_AVX512_TARGET wide& operator+=(wide b) {
    v = ops::add(v, b.v);
    return *this;
  }
};

template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline wide<T, N> lane_select(wide_mask<T, N> c, wide<T, N> a, wide<T, N> b) {
  return wide<T, N>::make(avx512_ops<T>::blend(c.m, b.v, a.v));
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline wide<T, N> lane_min(wide<T, N> a, wide<T, N> b) {
  return lane_select(a < b, a, b);  // same lane choice as the generic a < b ? a : b
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline wide<T, N> lane_max(wide<T, N> a, wide<T, N> b) {
  return lane_select(a < b, b, a);
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline void lane_store(T* p, wide<T, N> x) {
  avx512_ops<T>::storeu(p, x.v);
}
template <>
FLEXSPLAT_AVX512_TARGET inline wide<float, 16> lane_load<wide<float, 16>, float>(const float* p) {
  return wide<float, 16>::load_unaligned(p);
}
template <>
FLEXSPLAT_AVX512_TARGET inline wide<double, 8> lane_load<wide<double, 8>, double>(const double* p) {
  return wide<double, 8>::load_unaligned(p);
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline bool lane_any(wide_mask<T, N> c) {
  return c.m != 0;
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline bool lane_all(wide_mask<T, N> c) {
  return c.m == avx512_ops<T>::all;
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline T lane_sum(wide<T, N> x) {  // lanes in order, like reduce_add
  alignas(64) T lanes[N];
  avx512_ops<T>::storeu(lanes, x.v);
  T s = lanes[0];
  for (int i = 1; i < N; ++i) s += lanes[i];
  return s;
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline wide<T, N> lane_sqrt(wide<T, N> x) {
  return wide<T, N>::make(avx512_ops<T>::sqrt(x.v));
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline wide_mask<T, N> lane_isfinite(wide<T, N> x) {
  return x - x == wide<T, N>(T(0));  // x - x is 0 for a finite x and NaN otherwise
}
template <class T, int N>
  requires avx512_lanes<T, N>
FLEXSPLAT_AVX512_TARGET inline wide<T, N> lane_mul_add(wide<T, N> a, wide<T, N> b, wide<T, N> c) {
#if defined(__FMA__)
  return wide<T, N>::make(avx512_ops<T>::fmadd(a.v, b.v, c.v));
#else
  return a * b + c;
#endif
}

// exp of float lanes with AVX-512's own rounding and scaling: k = round(x log2 e), r = x - k ln 2 in two parts,
// degree-7 Taylor polynomial on |r| <= ln(2)/2 (truncation 1e-8, below float rounding), times 2^k by scalef. Inputs
// below -87 give 0, as lane_exp. The blend's alpha test waits on this chain, so its latency matters more than its
// instruction count. The masked intrinsic forms keep GCC 12 from warning about its own headers.
// OneStepReduction: r = x - k ln 2 with one multiply-add and ln 2 rounded to float, whose error grows with |k|
// (about 2e-9 |k| relative): for the blend, whose lanes that matter have x >= -sigma_max > -6 (|k| <= 9).
template <bool OneStepReduction = false>
FLEXSPLAT_AVX512_TARGET inline __m512 exp_avx512(__m512 x) {
  constexpr __mmask16 all = 0xffff;
  const __mmask16 in_range = _mm512_cmp_ps_mask(x, _mm512_set1_ps(-87.0f), _CMP_GE_OQ);
  const __m512 k = _mm512_mask_roundscale_ps(x, all, _mm512_mul_ps(x, _mm512_set1_ps(1.4426950408889634f)),
                                             _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r;
  if constexpr (OneStepReduction) {
    r = _mm512_fnmadd_ps(k, _mm512_set1_ps(0.6931471805599453f), x);
  } else {
    r = _mm512_fnmadd_ps(k, _mm512_set1_ps(0.693145751953125f), x);
    r = _mm512_fnmadd_ps(k, _mm512_set1_ps(1.4286068203094172e-06f), r);
  }
  // exp(r) = 1 + (r + r^2 g(r)), g by Estrin's scheme (short dependency chains); adding the 1 last keeps the
  // rounding of Horner's form.
  const __m512 r2 = _mm512_mul_ps(r, r), r4 = _mm512_mul_ps(r2, r2);
  const __m512 g67 = _mm512_fmadd_ps(_mm512_set1_ps(1.0f / 5040.0f), r, _mm512_set1_ps(1.0f / 720.0f));
  const __m512 g45 = _mm512_fmadd_ps(_mm512_set1_ps(1.0f / 120.0f), r, _mm512_set1_ps(1.0f / 24.0f));
  const __m512 g23 = _mm512_fmadd_ps(_mm512_set1_ps(1.0f / 6.0f), r, _mm512_set1_ps(0.5f));
  const __m512 g = _mm512_fmadd_ps(g67, r4, _mm512_fmadd_ps(g45, r2, g23));
  const __m512 p = _mm512_add_ps(_mm512_fmadd_ps(r2, g, r), _mm512_set1_ps(1.0f));
  return _mm512_maskz_scalef_ps(in_range, p, k);
}
FLEXSPLAT_AVX512_TARGET inline wide<float, 16> lane_exp(wide<float, 16> x) {
  return wide<float, 16>::make(exp_avx512(x.v));
}
FLEXSPLAT_AVX512_TARGET inline wide<float, 16> lane_erf(wide<float, 16> x) { return erf_float_lanes(x); }
// (An overload with the target: a 64-byte vector passed to a function without it draws a GCC ABI note.)
FLEXSPLAT_AVX512_TARGET inline wide<float, 16> lane_exp_blend(wide<float, 16> x) {
  return wide<float, 16>::make(exp_avx512<true>(x.v));
}
// Columns of 16 rows through 16 x 16 in-register transposes (simd::load_columns).
template <>
FLEXSPLAT_AVX512_TARGET inline void load_columns<wide<float, 16>, float>(const float* const* rows, int count,
                                                                        wide<float, 16>* out) {
  for (int j0 = 0; j0 < count; j0 += 16) {
    __m512 col[16];
    transpose_rows_avx512(rows, j0, count, col);
    for (int k = 0; k < 16 && j0 + k < count; ++k) out[j0 + k] = wide<float, 16>::make(col[k]);
  }
}

// The double lanes of the 16-float kernels: floor, ceil and log.
FLEXSPLAT_AVX512_TARGET inline wide<double, 8> lane_floor(wide<double, 8> x) {
  return wide<double, 8>::make(_mm512_mask_roundscale_pd(x.v, __mmask8(0xff), x.v, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC));
}
FLEXSPLAT_AVX512_TARGET inline wide<double, 8> lane_ceil(wide<double, 8> x) {
  return wide<double, 8>::make(_mm512_mask_roundscale_pd(x.v, __mmask8(0xff), x.v, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC));
}
// AVX-512: exponent and mantissa in [1, 2) by getexp / getmant (positive normal x; other inputs give unspecified
// values), then the series of the vector-extension form.
FLEXSPLAT_AVX512_TARGET inline wide<double, 8> lane_log(wide<double, 8> x) {
  constexpr __mmask8 all = 0xff;
  const __m512d m1 = _mm512_mask_getmant_pd(x.v, all, x.v, _MM_MANT_NORM_1_2, _MM_MANT_SIGN_zero);
  const __m512d e1 = _mm512_mask_getexp_pd(x.v, all, x.v);
  const __mmask8 high = _mm512_cmp_pd_mask(m1, _mm512_set1_pd(1.5), _CMP_GE_OQ);
  const __m512d m = _mm512_mask_mul_pd(m1, high, m1, _mm512_set1_pd(0.5));
  const __m512d e = _mm512_mask_add_pd(e1, high, e1, _mm512_set1_pd(1.0));
  const __m512d one = _mm512_set1_pd(1.0);
  const __m512d s = _mm512_div_pd(_mm512_sub_pd(m, one), _mm512_add_pd(m, one)), z = _mm512_mul_pd(s, s);
  __m512d series = _mm512_set1_pd(log_series[11]);
  for (int k = 10; k >= 0; --k) series = _mm512_add_pd(_mm512_mul_pd(series, z), _mm512_set1_pd(log_series[k]));
  const __m512d tail = _mm512_add_pd(_mm512_mul_pd(e, _mm512_set1_pd(log_ln2_lo)),
                                     _mm512_mul_pd(_mm512_mul_pd(_mm512_set1_pd(2.0), s), series));
  return wide<double, 8>::make(_mm512_add_pd(_mm512_mul_pd(e, _mm512_set1_pd(log_ln2_hi)), tail));
}
#undef FLEXSPLAT_AVX512_TARGET

// Calls body(V*) (the pointer only carries the type) with V = wide<float, 16> / wide<float, 8>, inlined (flatten) into
// a function compiled for AVX-512 / AVX2, for kernels whose lanes must round as the scalar path of this build: a build
// without FMA has no fused multiply-adds for the compiler to form, so the wider target must not form them either.
#if defined(__FMA__) || defined(__clang__)
#define FLEXSPLAT_SCALAR_ROUNDING  // (Clang contracts only within one source expression, and has no such attribute)
#else
#define FLEXSPLAT_SCALAR_ROUNDING __attribute__((optimize("fp-contract=off")))
#endif
template <class Body>
__attribute__((target("avx512f,avx512bw,avx512dq,avx512vl,avx2,fma"), flatten)) FLEXSPLAT_SCALAR_ROUNDING void
run_avx512_exact(Body& body) {
  body(static_cast<wide<float, 16>*>(nullptr));
}
template <class Body>
__attribute__((target("avx2,fma"), flatten)) FLEXSPLAT_SCALAR_ROUNDING void run_avx2_exact(Body& body) {
  body(static_cast<wide<float, 8>*>(nullptr));
}
#undef FLEXSPLAT_SCALAR_ROUNDING

// The same without the rounding constraint: the wider target may fuse multiply-adds.
template <class Body>
__attribute__((target("avx512f,avx512bw,avx512dq,avx512vl,avx2,fma"), flatten)) void run_avx512(Body& body) {
  body(static_cast<wide<float, 16>*>(nullptr));
}
template <class Body>
__attribute__((target("avx2,fma"), flatten)) void run_avx2(Body& body) {
  body(static_cast<wide<float, 8>*>(nullptr));
}

#endif  // FLEXSPLAT_SIMD_DISPATCH

// Which lanes a kernel written against the lane helpers runs with: scalar, the build's compiled batches, or a wider
// run-time dispatched vector (float only: the dispatch vectors' exp is accurate to float precision).
enum class Lanes { scalar, compiled, avx2, avx512 };

inline const char* lanes_name(Lanes lanes) {
  return lanes == Lanes::scalar ? "scalar" : lanes == Lanes::compiled ? "compiled" : lanes == Lanes::avx2 ? "avx2" : "avx512";
}

// The widest lanes for T on this CPU, at most `cap` (FLEXSPLAT_SIMD=scalar / avx2 apply through dispatch_level).
template <class T>
Lanes best_lanes(DispatchLevel cap = DispatchLevel::avx512) {
  if (!enabled()) return Lanes::scalar;
#if FLEXSPLAT_SIMD_DISPATCH
  const DispatchLevel level = std::min(dispatch_level(), cap);
  const std::size_t compiled_bytes = width<T> * sizeof(T);
  if (sizeof(T) == 4 && level == DispatchLevel::avx512 && compiled_bytes < 64) return Lanes::avx512;
  if (sizeof(T) == 4 && level != DispatchLevel::none && compiled_bytes < 32) return Lanes::avx2;
#else
  (void)cap;
#endif
  return Lanes::compiled;
}

// Calls body(V*) with the lane type V of `lanes` (the pointer only carries the type): T, batch<T>, or a dispatch
// vector inlined into a function compiled for its target. Call it inside a parallel_for body, not around one: a
// worker's lambda is not inlined, so it would not get the target.
template <class T, class Body>
void with_lanes(Lanes lanes, Body&& body) {
#if FLEXSPLAT_SIMD_DISPATCH
  if constexpr (sizeof(T) == 4) {
    if (lanes == Lanes::avx512) return run_avx512(body);
    if (lanes == Lanes::avx2) return run_avx2(body);
  }
#endif
  if (lanes == Lanes::scalar) body(static_cast<T*>(nullptr));
  else body(static_cast<batch<T>*>(nullptr));
}

template <class V>
struct is_avx512_float_batch : std::false_type {};
template <class A>
struct is_avx512_float_batch<xsimd::batch<float, A>> : std::bool_constant<std::is_base_of_v<xsimd::avx512f, A>> {};

// exp at float precision for the blending kernels: exp_avx512 on the AVX-512 float batches of a native build (half
// the instructions of xsimd::exp), lane_exp elsewhere.
template <class V>
FLEXSPLAT_ALWAYS_INLINE V lane_exp_blend(V x) {
#if FLEXSPLAT_SIMD_DISPATCH && defined(__AVX512F__)
  if constexpr (is_avx512_float_batch<V>::value) return V(exp_avx512<true>(x));
  else
#endif
    return lane_exp(x);
}

}  // namespace simd
}  // namespace v0
}  // namespace flexsplat
