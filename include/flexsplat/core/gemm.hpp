#pragma once
// Row-major GEMM C = alpha * op(A) * op(B) + beta * C on a CBLAS (OpenBLAS) when the build links one
// (FLEXSPLAT_HAVE_CBLAS, set by the flexsplat CMake target), else on Eigen's kernels; C split over the pool.
// With oneDNN (FLEXSPLAT_HAVE_DNNL) float products may run on its fp32 matmul (GemmBackend::onednn, the default where
// oneDNN has AVX-512 kernels for the CPU) or in bf16 with fp32 accumulation (GemmBackend::bf16).
#include <Eigen/Core>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <climits>
#include <cstdint>
#include <cstdlib>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <tuple>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/half.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/tensor.hpp"

#if defined(FLEXSPLAT_HAVE_DNNL)
#include <oneapi/dnnl/dnnl.hpp>
// The OpenMP runtime oneDNN runs on (libgomp): declared here so that no compiler's omp.h is needed.
extern "C" void omp_set_num_threads(int);
#endif
#if defined(FLEXSPLAT_HAVE_CBLAS)
#include <cblas.h>
#endif

namespace flexsplat {
inline namespace v0 {

enum class Trans { no, yes };
// bf16: float products with both operands rounded to bf16, accumulated and returned in fp32 (oneDNN); double
// products and float ones below gemm_bf16_min_madds run on the BLAS (or Eigen) as with `blas`.
// onednn: float products on oneDNN's fp32 matmul; double products and float ones below gemm_onednn_min_madds run on
// the BLAS (or Eigen).
enum class GemmBackend { eigen, blas, bf16, onednn };

template <class T>
using RowMatrix = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <class T>
using ConstMatMap = Eigen::Map<const RowMatrix<T>, 0, Eigen::OuterStride<>>;
template <class T>
using MatMap = Eigen::Map<RowMatrix<T>, 0, Eigen::OuterStride<>>;

#if defined(FLEXSPLAT_HAVE_CBLAS)
inline constexpr bool have_blas = true;
#else
inline constexpr bool have_blas = false;
#endif
#if defined(FLEXSPLAT_HAVE_DNNL)
inline constexpr bool have_bf16_gemm = true;
#else
inline constexpr bool have_bf16_gemm = false;
#endif
inline constexpr bool have_onednn_gemm = have_bf16_gemm;  // the fp32 matmul comes with the same library

// Products below this many multiply-adds stay on Eigen even with a BLAS: there a CBLAS call's fixed cost loses to
// Eigen's inlined kernels (bench/gemm's small-shape table: Eigen 2-4x faster at 4^3, even at 8^3 = 512, OpenBLAS
// faster from 12^3 = 1728 on).
inline constexpr index_t gemm_blas_min_madds = index_t(1) << 10;

namespace detail {
inline std::atomic<int>& gemm_backend_override() {
  static std::atomic<int> choice{-1};
  return choice;
}

// Whether oneDNN runs its AVX-512 kernels on this CPU (its own run-time dispatch, capped by DNNL_MAX_CPU_ISA): there
// its fp32 matmul measured 1.6-2.7x OpenBLAS's Haswell kernels from 96^3 on (bench/gemm). Without AVX-512 it was not
// measured, so the BLAS stays the default.
inline bool onednn_has_avx512() {
#if defined(FLEXSPLAT_HAVE_DNNL)
  static const bool yes = [] {
    const int isa = static_cast<int>(dnnl::get_effective_cpu_isa());
    return (isa & dnnl_cpu_isa_avx512_core) == dnnl_cpu_isa_avx512_core;
  }();
  return yes;
#else
  return false;
#endif
}
}  // namespace detail

// The fp32 backend gemm() picks without FLEXSPLAT_GEMM or set_default_gemm_backend: oneDNN's fp32 matmul where it has
// AVX-512 kernels for the CPU, else the BLAS when the build has one, else Eigen.
inline GemmBackend fastest_fp32_gemm_backend() {
  if (have_onednn_gemm && detail::onednn_has_avx512()) return GemmBackend::onednn;
  return have_blas ? GemmBackend::blas : GemmBackend::eigen;
}

// What gemm() without a backend uses: set_default_gemm_backend's choice, else FLEXSPLAT_GEMM=eigen|blas|onednn|bf16
// (read once), else fastest_fp32_gemm_backend().
inline GemmBackend default_gemm_backend() {
  if (const int choice = detail::gemm_backend_override().load(std::memory_order_relaxed); choice >= 0)
    return static_cast<GemmBackend>(choice);
  static const GemmBackend backend = [] {
    const char* env = std::getenv("FLEXSPLAT_GEMM");
    if (!env || !*env) return fastest_fp32_gemm_backend();
    const std::string v = env;
    require(v == "eigen" || v == "blas" || v == "onednn" || v == "bf16", "FLEXSPLAT_GEMM='", v,
            "' is not 'eigen', 'blas', 'onednn' or 'bf16'");
    require(v != "blas" || have_blas, "FLEXSPLAT_GEMM=blas but this build has no BLAS (FLEXSPLAT_USE_BLAS=OFF or "
                                      "OpenBLAS not found at configure time)");
    require((v != "bf16" && v != "onednn") || have_onednn_gemm, "FLEXSPLAT_GEMM=", v, " but this build has no oneDNN "
            "(FLEXSPLAT_USE_DNNL=OFF or libdnnl-dev not found at configure time)");
    return v == "blas" ? GemmBackend::blas : v == "bf16" ? GemmBackend::bf16 : v == "onednn" ? GemmBackend::onednn
                                                                                               : GemmBackend::eigen;
  }();
  return backend;
}

// Selects the backend of every later gemm() call without one (e.g. bf16 for a whole forward pass); call it between
// passes, not while other threads multiply.
inline void set_default_gemm_backend(GemmBackend backend) {
  require(backend != GemmBackend::blas || have_blas, "set_default_gemm_backend: this build has no BLAS");
  require(backend != GemmBackend::bf16 || have_bf16_gemm, "set_default_gemm_backend: this build has no oneDNN (bf16)");
  require(backend != GemmBackend::onednn || have_onednn_gemm, "set_default_gemm_backend: this build has no oneDNN");
  detail::gemm_backend_override().store(static_cast<int>(backend), std::memory_order_relaxed);
}

// Float products below this many multiply-adds stay in fp32 under GemmBackend::bf16: oneDNN's per-call set-up
// (primitive look-up, two reorders) costs tens of microseconds.
inline constexpr index_t gemm_bf16_min_madds = index_t(1) << 20;
// Float products below this many multiply-adds leave GemmBackend::onednn for the BLAS (or Eigen): oneDNN's per-call
// set-up is about 9 us; it lost at 64^3 = 2^18 (0.74-0.95x) and won from 96^3 (1.5x) in bench/gemm's fp32 table.
inline constexpr index_t gemm_onednn_min_madds = index_t(1) << 19;

class GemmWeightCache;

namespace detail {
// The cache of the thread that made the innermost UseGemmWeightCache (null outside any).
inline GemmWeightCache*& active_gemm_weight_cache() noexcept {
  thread_local GemmWeightCache* cache = nullptr;
  return cache;
}

// A stored matrix of `rows` x `cols` with row stride ld; with one row the stride is never used, but CBLAS checks it.
inline int blas_ld(index_t rows, index_t cols, index_t ld) {
  return static_cast<int>(rows <= 1 ? std::max<index_t>({ld, cols, 1}) : ld);
}

#if defined(FLEXSPLAT_HAVE_DNNL)
inline const dnnl::engine& onednn_engine() {
  static const dnnl::engine engine(dnnl::engine::kind::cpu, 0);
  return engine;
}
inline dnnl::stream& onednn_stream() {
  thread_local dnnl::stream stream(onednn_engine());
  return stream;
}
// The fp32 matrix op(X) (rows x cols) stored row-major with row stride ld, as oneDNN describes it.
inline dnnl::memory::desc onednn_f32(index_t rows, index_t cols, Trans t, index_t ld) {
  using dims = dnnl::memory::dims;
  const index_t stride = t == Trans::no ? blas_ld(rows, cols, ld) : blas_ld(cols, rows, ld);
  return {{rows, cols}, dnnl::memory::data_type::f32, t == Trans::no ? dims{stride, 1} : dims{1, stride}};
}
// alpha as an output scale and beta C as a sum post-op.
inline dnnl::primitive_attr onednn_attr(float alpha, float beta) {
  dnnl::primitive_attr attr;
  if (alpha != 1.0f) attr.set_output_scales(0, {alpha});
  if (beta != 0.0f) {
    dnnl::post_ops ops;
    ops.append_sum(beta);
    attr.set_post_ops(ops);
  }
  return attr;
}

// Whether oneDNN has a bf16 matmul for this CPU (its bf16 kernels need AVX-512; without them it creates none).
inline bool onednn_bf16_matmul() {
  static const bool yes = [] {
    try {
      using dt = dnnl::memory::data_type;
      const auto any = dnnl::memory::format_tag::any;
      const dnnl::matmul::primitive_desc pd(
          dnnl::matmul::desc(dnnl::memory::desc({128, 96}, dt::bf16, any), dnnl::memory::desc({96, 128}, dt::bf16, any),
                             dnnl::memory::desc({128, 128}, dt::f32, dnnl::memory::format_tag::ab)),
          onednn_engine());
      return true;
    } catch (const dnnl::error&) {
      return false;
    }
  }();
  return yes;
}
#endif

// The stored rows x cols of X (row stride ld) rounded to bf16 values, dense (row stride cols) into out: GemmBackend::bf16
// where oneDNN has no bf16 kernels for the CPU.
inline void round_bf16_dense(std::vector<float>& out, const float* X, index_t rows, index_t cols, index_t ld) {
  out.resize(static_cast<std::size_t>(rows * cols));
  for (index_t r = 0; r < rows; ++r)
    for (index_t c = 0; c < cols; ++c) out[static_cast<std::size_t>(r * cols + c)] = float(bf16(X[r * ld + c]));
}
}  // namespace detail

// Whether GemmBackend::bf16 runs oneDNN's bf16 matmul on this CPU; otherwise it rounds both operands to bf16 and
// multiplies them in fp32 on the BLAS (or Eigen): the same product, without the speed.
inline bool bf16_gemm_native() {
#if defined(FLEXSPLAT_HAVE_DNNL)
  return detail::onednn_bf16_matmul();
#else
  return false;
#endif
}

// Weights that stay fixed while products use them (inference). Under GemmBackend::bf16, a float product whose whole
// op(B) lies inside a range given to freeze() reorders that B to bf16 once, into the layout oneDNN's matmul prefers,
// and reuses it; the matmul primitive and the reorder of A are kept per shape, so a call converts only A (bench/gemm,
// one thread at VGGT's shapes: 2.1-2.4x fp32 against 1.9x when every call converts both; at 4 rows 7.7x against
// 0.95x). The results are bitwise those without it. Costs 2 bytes per packed value (2.25 GB for VGGT-1B).
// Used by products called, outside parallel regions, on a thread inside a UseGemmWeightCache; thread-safe. The frozen
// values must not change while packed copies exist: clear() after changing them.
class GemmWeightCache {
public:
  GemmWeightCache() = default;
  GemmWeightCache(const GemmWeightCache&) = delete;
  GemmWeightCache& operator=(const GemmWeightCache&) = delete;

  void freeze(const float* data, std::size_t count) {
    require(data != nullptr || count == 0, "GemmWeightCache::freeze: null data for ", count, " values");
    std::lock_guard lock(mutex_);
    if (count > 0) ranges_.push_back({data, data + count});
  }
  // Drops the packed copies and primitives (after the frozen values changed); the ranges stay.
  void clear() {
    std::lock_guard lock(mutex_);
#if defined(FLEXSPLAT_HAVE_DNNL)
    kernels_.clear();
    packed_.clear();
    rounded_.clear();
#endif
    bytes_ = 0;
  }
  // Drops everything, ranges included.
  void reset() {
    clear();
    std::lock_guard lock(mutex_);
    ranges_.clear();
  }
  bool empty() const {
    std::lock_guard lock(mutex_);
    return ranges_.empty();
  }
  // Bytes of the bf16 copies held.
  std::size_t packed_bytes() const {
    std::lock_guard lock(mutex_);
    return bytes_;
  }
  // Whether every value of op(B) (K x N, row stride ldb) lies inside one frozen range.
  bool covers(const float* B, Trans tb, index_t K, index_t N, index_t ldb) const {
    if (!B || K <= 0 || N <= 0) return false;
    const index_t rows = tb == Trans::no ? K : N, cols = tb == Trans::no ? N : K;
    const float* end = B + (rows - 1) * ldb + cols;
    const std::less<const float*> less;
    std::lock_guard lock(mutex_);
    for (const Range& r : ranges_)
      if (!less(B, r.begin) && !less(r.end, end)) return true;
    return false;
  }

#if defined(FLEXSPLAT_HAVE_DNNL)
  // Makes the primitive of this block's shape and the packed copy of its B if missing; the packing's reorder runs on
  // `threads` OpenMP threads (gemm() calls this on the calling thread before splitting, with the pool's size).
  void prepare(Trans ta, Trans tb, index_t M, index_t N, index_t K, float alpha, index_t lda, const float* B,
               index_t ldb, float beta, index_t ldc, int threads) {
    if (!detail::onednn_bf16_matmul()) {
      rounded(tb, K, N, B, ldb);
      return;
    }
    try {
      entry(ta, tb, M, N, K, alpha, lda, B, ldb, beta, ldc, threads);
    } catch (const dnnl::error& e) {
      fail("gemm (bf16, oneDNN, packing weights): M ", M, " N ", N, " K ", K, " lda ", lda, " ldb ", ldb, " ldc ", ldc,
           ": ", e.what());
    }
  }

  // C[:M, :N] = alpha op(A) op(B) + beta C on the calling thread, B from the cache (packed on first use).
  void multiply(Trans ta, Trans tb, index_t M, index_t N, index_t K, float alpha, const float* A, index_t lda,
                const float* B, index_t ldb, float beta, float* C, index_t ldc) {
    const dnnl::engine& engine = detail::onednn_engine();
    dnnl::stream& stream = detail::onednn_stream();
    omp_set_num_threads(1);  // the pool splits the work
    try {
      const auto [kernel, packed] = entry(ta, tb, M, N, K, alpha, lda, B, ldb, beta, ldc, 1);
      thread_local AlignedVector<std::byte> a_buffer, scratch_buffer;
      const std::size_t a_bytes = kernel->pd.src_desc().get_size(), s_bytes = kernel->pd.scratchpad_desc().get_size();
      if (a_buffer.size() < a_bytes) a_buffer.resize(a_bytes);
      if (scratch_buffer.size() < s_bytes) scratch_buffer.resize(s_bytes);
      dnnl::memory a_in(kernel->a_f32, engine, const_cast<float*>(A)), c(kernel->c_f32, engine, C);
      dnnl::memory a(kernel->pd.src_desc(), engine, a_buffer.data());
      dnnl::memory scratch(kernel->pd.scratchpad_desc(), engine, scratch_buffer.data());
      kernel->a_reorder.execute(stream, a_in, a);
      kernel->matmul.execute(stream, {{DNNL_ARG_SRC, a}, {DNNL_ARG_WEIGHTS, *packed}, {DNNL_ARG_DST, c},
                                      {DNNL_ARG_SCRATCHPAD, scratch}});
      stream.wait();
    } catch (const dnnl::error& e) {
      fail("gemm (bf16, oneDNN, cached weights): M ", M, " N ", N, " K ", K, " lda ", lda, " ldb ", ldb, " ldc ", ldc,
           ": ", e.what());
    }
  }

  // Without oneDNN's bf16 kernels: op(B)'s values rounded to bf16, dense in B's own orientation (made once).
  const std::vector<float>& rounded(Trans tb, index_t K, index_t N, const float* B, index_t ldb) {
    std::lock_guard lock(mutex_);
    std::vector<float>& copy = rounded_[Operand{B, K, N, ldb, int(tb)}];
    if (copy.empty()) {
      detail::round_bf16_dense(copy, B, tb == Trans::no ? K : N, tb == Trans::no ? N : K, ldb);
      bytes_ += copy.size() * sizeof(float);
    }
    return copy;
  }
#endif

private:
  struct Range {
    const float* begin;
    const float* end;
  };
  mutable std::mutex mutex_;
  std::vector<Range> ranges_;
  std::size_t bytes_ = 0;
#if defined(FLEXSPLAT_HAVE_DNNL)
  struct Shape {
    index_t M, N, K, lda, ldc;
    int ta;
    std::uint32_t alpha, beta;  // bit patterns
    auto operator<=>(const Shape&) const = default;
  };
  struct Operand {
    const float* data;
    index_t K, N, ldb;
    int tb;
    bool operator<(const Operand& o) const {
      if (data != o.data) return std::less<const float*>()(data, o.data);
      return std::tie(K, N, ldb, tb) < std::tie(o.K, o.N, o.ldb, o.tb);
    }
  };
  struct Kernel {
    dnnl::memory::desc a_f32, c_f32;
    dnnl::matmul::primitive_desc pd;
    dnnl::matmul matmul;
    dnnl::reorder a_reorder;
  };
  std::map<Shape, std::unique_ptr<Kernel>> kernels_;  // by pointer: other threads run them while the map grows
  struct Packed {
    AlignedVector<std::byte> bytes;
    dnnl::memory memory;
  };
  std::map<Operand, std::vector<std::unique_ptr<Packed>>> packed_;
  std::map<Operand, std::vector<float>> rounded_;  // nodes never move: other threads read them while the map grows

  std::pair<const Kernel*, const dnnl::memory*> entry(Trans ta, Trans tb, index_t M, index_t N, index_t K,
                                                      float alpha, index_t lda, const float* B, index_t ldb,
                                                      float beta, index_t ldc, int threads) {
    using dt = dnnl::memory::data_type;
    const dnnl::engine& engine = detail::onednn_engine();
    const index_t a_ld = ta == Trans::no ? detail::blas_ld(M, K, lda) : detail::blas_ld(K, M, lda);
    const index_t b_ld = tb == Trans::no ? detail::blas_ld(K, N, ldb) : detail::blas_ld(N, K, ldb);
    const index_t c_ld = detail::blas_ld(M, N, ldc);
    std::lock_guard lock(mutex_);
    std::unique_ptr<Kernel>& slot = kernels_[Shape{M, N, K, a_ld, c_ld, int(ta), std::bit_cast<std::uint32_t>(alpha),
                                                   std::bit_cast<std::uint32_t>(beta)}];
    if (!slot) {
      dnnl::primitive_attr attr = detail::onednn_attr(alpha, beta);
      attr.set_scratchpad_mode(dnnl::scratchpad_mode::user);  // per-thread scratch: calls run concurrently
      const auto any = dnnl::memory::format_tag::any;
      const dnnl::memory::desc a_f32 = detail::onednn_f32(M, K, ta, lda);
      const dnnl::memory::desc c_f32 = detail::onednn_f32(M, N, Trans::no, ldc);
      const dnnl::matmul::primitive_desc pd(
          dnnl::matmul::desc(dnnl::memory::desc({M, K}, dt::bf16, any), dnnl::memory::desc({K, N}, dt::bf16, any),
                             c_f32),
          attr, engine);
      slot.reset(new Kernel{a_f32, c_f32, pd, dnnl::matmul(pd),
                            dnnl::reorder(dnnl::reorder::primitive_desc(engine, a_f32, engine, pd.src_desc()))});
    }
    const Kernel* kernel = slot.get();
    auto& copies = packed_[Operand{B, K, N, b_ld, int(tb)}];
    const dnnl::memory::desc want = kernel->pd.weights_desc();
    for (const auto& m : copies)
      if (m->memory.get_desc() == want) return {kernel, &m->memory};
    dnnl::memory in(detail::onednn_f32(K, N, tb, ldb), engine, const_cast<float*>(B));
    dnnl::stream& stream = detail::onednn_stream();
    auto out = std::make_unique<Packed>();
    const std::size_t size = want.get_size();
    out->bytes.resize(size);  // huge pages, mapped in on the pool's cores (AlignedAllocator)
    out->memory = dnnl::memory(want, engine, out->bytes.data());
    omp_set_num_threads(threads);
    dnnl::reorder(in, out->memory).execute(stream, in, out->memory);
    stream.wait();
    omp_set_num_threads(1);  // the pool splits the products
    bytes_ += size;
    copies.push_back(std::move(out));
    return {kernel, &copies.back()->memory};
  }
#endif
};

// Makes `cache` the one gemm() uses on this thread until destroyed (scopes nest; the previous one comes back).
class UseGemmWeightCache {
public:
  explicit UseGemmWeightCache(GemmWeightCache& cache) noexcept : previous_(detail::active_gemm_weight_cache()) {
    detail::active_gemm_weight_cache() = &cache;
  }
  ~UseGemmWeightCache() { detail::active_gemm_weight_cache() = previous_; }
  UseGemmWeightCache(const UseGemmWeightCache&) = delete;
  UseGemmWeightCache& operator=(const UseGemmWeightCache&) = delete;

private:
  GemmWeightCache* previous_;
};

namespace detail {
#if defined(FLEXSPLAT_HAVE_OPENBLAS)
// Once per process, before flexsplat's first BLAS call: OpenBLAS runs single-threaded, since the pool splits the work
// and OpenBLAS's own threads would oversubscribe the cores (Debian's libopenblas0-pthread keeps them spinning for a
// while after each call). Its kernels stay OpenBLAS's choice: run-time CPU dispatch, or OPENBLAS_CORETYPE.
inline void openblas_single_threaded() {
  static const bool done = [] {
    openblas_set_num_threads(1);
    return true;
  }();
  (void)done;
}
#endif

#if defined(FLEXSPLAT_HAVE_CBLAS)

template <class T>
void blas_gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda, const T* B,
               index_t ldb, T beta, T* C, index_t ldc) {
#if defined(FLEXSPLAT_HAVE_OPENBLAS)
  openblas_single_threaded();
#endif
  const auto op = [](Trans t) { return t == Trans::no ? CblasNoTrans : CblasTrans; };
  const int a_ld = ta == Trans::no ? blas_ld(M, K, lda) : blas_ld(K, M, lda);
  const int b_ld = tb == Trans::no ? blas_ld(K, N, ldb) : blas_ld(N, K, ldb);
  const int c_ld = blas_ld(M, N, ldc);
  if constexpr (std::is_same_v<T, float>)
    cblas_sgemm(CblasRowMajor, op(ta), op(tb), int(M), int(N), int(K), alpha, A, a_ld, B, b_ld, beta, C, c_ld);
  else
    cblas_dgemm(CblasRowMajor, op(ta), op(tb), int(M), int(N), int(K), alpha, A, a_ld, B, b_ld, beta, C, c_ld);
}
#endif

#if defined(FLEXSPLAT_HAVE_DNNL)
// The fp32 matmul primitive of one call's shape (a, b, c its operands' descriptors), kept per thread: making it took
// 1.9-3.3 us of a 13-21 us call at 64 x 128 x 64 and 256 x 96 x 32, and a training step repeats a few hundred shapes
// thousands of times.
inline const dnnl::matmul& onednn_f32_matmul(const dnnl::memory::desc& a, const dnnl::memory::desc& b,
                                             const dnnl::memory::desc& c, index_t M, index_t N, index_t K, Trans ta,
                                             Trans tb, index_t lda, index_t ldb, index_t ldc, float alpha, float beta) {
  using Key = std::array<index_t, 10>;
  thread_local std::map<Key, dnnl::matmul> kernels;
  const Key key{M, N, K, index_t(ta), index_t(tb), ta == Trans::no ? blas_ld(M, K, lda) : blas_ld(K, M, lda),
                tb == Trans::no ? blas_ld(K, N, ldb) : blas_ld(N, K, ldb), blas_ld(M, N, ldc),
                index_t(std::bit_cast<std::uint32_t>(alpha)), index_t(std::bit_cast<std::uint32_t>(beta))};
  if (auto it = kernels.find(key); it != kernels.end()) return it->second;
  if (kernels.size() >= 4096) kernels.clear();  // bounded for callers whose shapes never repeat
  const dnnl::matmul::primitive_desc pd(dnnl::matmul::desc(a, b, c), onednn_attr(alpha, beta), onednn_engine());
  return kernels.emplace(key, dnnl::matmul(pd)).first->second;
}

// C[:M, :N] = alpha op(A) op(B) + beta C on the calling thread with oneDNN's matmul. fp32: on the operands in place.
// bf16: oneDNN reorders A (into the layout its matmul prefers) and B (in its own orientation) to bf16, rounding to
// nearest even; the matmul accumulates in fp32 (AVX-512 BF16 kernels where the CPU has them).
inline void onednn_gemm(bool bf16, Trans ta, Trans tb, index_t M, index_t N, index_t K, float alpha, const float* A,
                        index_t lda, const float* B, index_t ldb, float beta, float* C, index_t ldc) {
  using dims = dnnl::memory::dims;
  using dt = dnnl::memory::data_type;
  try {
    const dnnl::engine& engine = onednn_engine();
    dnnl::stream& stream = onednn_stream();
    omp_set_num_threads(1);  // the pool splits the work, as with OpenBLAS: no OpenMP team per worker
    const dnnl::memory::desc a_f32 = onednn_f32(M, K, ta, lda), b_f32 = onednn_f32(K, N, tb, ldb);
    const dnnl::memory::desc c_f32 = onednn_f32(M, N, Trans::no, ldc);
    dnnl::memory a_in(a_f32, engine, const_cast<float*>(A)), b_in(b_f32, engine, const_cast<float*>(B));
    dnnl::memory c(c_f32, engine, C);
    if (!bf16) {
      onednn_f32_matmul(a_f32, b_f32, c_f32, M, N, K, ta, tb, lda, ldb, ldc, alpha, beta)
          .execute(stream, {{DNNL_ARG_SRC, a_in}, {DNNL_ARG_WEIGHTS, b_in}, {DNNL_ARG_DST, c}});
      stream.wait();
      return;
    }
    // B converted in its own orientation (plain bf16): oneDNN's reorder into its blocked layout took 12x as long
    // (4.0 against 0.32 ms for 3072 x 1024 on one thread), more than the blocked kernel saves per call.
    const auto any = dnnl::memory::format_tag::any;
    const dnnl::memory::desc b_bf16({K, N}, dt::bf16, tb == Trans::no ? dims{N, 1} : dims{1, K});
    const dnnl::matmul::desc desc(dnnl::memory::desc({M, K}, dt::bf16, any), b_bf16, c_f32);
    const dnnl::matmul::primitive_desc pd(desc, onednn_attr(alpha, beta), engine);
    thread_local AlignedVector<std::byte> a_buffer, b_buffer;
    if (a_buffer.size() < pd.src_desc().get_size()) a_buffer.resize(pd.src_desc().get_size());
    if (b_buffer.size() < b_bf16.get_size()) b_buffer.resize(b_bf16.get_size());
    dnnl::memory a(pd.src_desc(), engine, a_buffer.data()), b(b_bf16, engine, b_buffer.data());
    dnnl::reorder(a_in, a).execute(stream, a_in, a);
    dnnl::reorder(b_in, b).execute(stream, b_in, b);
    dnnl::matmul(pd).execute(stream, {{DNNL_ARG_SRC, a}, {DNNL_ARG_WEIGHTS, b}, {DNNL_ARG_DST, c}});
    stream.wait();
  } catch (const dnnl::error& e) {
    fail("gemm (", bf16 ? "bf16" : "fp32", ", oneDNN): M ", M, " N ", N, " K ", K, " lda ", lda, " ldb ", ldb, " ldc ",
         ldc, ": ", e.what());
  }
}

inline void bf16_gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, float alpha, const float* A, index_t lda,
                      const float* B, index_t ldb, float beta, float* C, index_t ldc) {
  onednn_gemm(true, ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
}
#endif

// One block on one thread: C[:M, :N] = alpha op(A) op(B) + beta C, A/B/C already offset to the block.
template <class T>
void gemm_block(GemmBackend backend, Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A,
                index_t lda, const T* B, index_t ldb, T beta, T* C, index_t ldc, GemmWeightCache* cache = nullptr) {
  MatMap<T> c(C, M, N, Eigen::OuterStride<>(ldc));
  if (K <= 0 || alpha == T(0)) {
    if (beta == T(0)) c.setZero();
    else if (beta != T(1)) c *= beta;
    return;
  }
#if defined(FLEXSPLAT_HAVE_DNNL)
  if constexpr (std::is_same_v<T, float>) {
    if (backend == GemmBackend::bf16 && !onednn_bf16_matmul()) {
      thread_local std::vector<float> a_round, b_round;
      const index_t a_cols = ta == Trans::no ? K : M, b_cols = tb == Trans::no ? N : K;
      round_bf16_dense(a_round, A, ta == Trans::no ? M : K, a_cols, lda);
      const float* b = b_round.data();
      if (cache) b = cache->rounded(tb, K, N, B, ldb).data();
      else round_bf16_dense(b_round, B, tb == Trans::no ? K : N, b_cols, ldb), b = b_round.data();
      gemm_block<float>(have_blas ? GemmBackend::blas : GemmBackend::eigen, ta, tb, M, N, K, alpha, a_round.data(),
                        a_cols, b, b_cols, beta, C, ldc);
      return;
    }
    if (backend == GemmBackend::bf16 && cache) {
      cache->multiply(ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
      return;
    }
    if (backend == GemmBackend::bf16 || backend == GemmBackend::onednn) {
      onednn_gemm(backend == GemmBackend::bf16, ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
      return;
    }
  }
#endif
  if (backend == GemmBackend::bf16 || backend == GemmBackend::onednn)
    backend = have_blas ? GemmBackend::blas : GemmBackend::eigen;
#if defined(FLEXSPLAT_HAVE_CBLAS)
  if constexpr (std::is_same_v<T, float> || std::is_same_v<T, double>) {
    if (backend == GemmBackend::blas && M * N * K >= gemm_blas_min_madds) {
      blas_gemm(ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
      return;
    }
  }
#else
  (void)backend;
#endif
  if (beta == T(0)) c.setZero();
  else if (beta != T(1)) c *= beta;
  auto b = [&](auto&& a_op) {
    if (tb == Trans::no) c.noalias() += alpha * (a_op * ConstMatMap<T>(B, K, N, Eigen::OuterStride<>(ldb)));
    else c.noalias() += alpha * (a_op * ConstMatMap<T>(B, N, K, Eigen::OuterStride<>(ldb)).transpose());
  };
  if (ta == Trans::no) b(ConstMatMap<T>(A, M, K, Eigen::OuterStride<>(lda)));
  else b(ConstMatMap<T>(A, K, M, Eigen::OuterStride<>(lda)).transpose());
}

}  // namespace detail

// "OpenBLAS 0.3.21 NO_LAPACKE DYNAMIC_ARCH NO_AFFINITY SkylakeX ...", "CBLAS" or "Eigen 3.4.0": what gemm runs on.
inline std::string gemm_backend_name(GemmBackend backend = default_gemm_backend()) {
  if (backend == GemmBackend::eigen)
    return concat("Eigen ", EIGEN_WORLD_VERSION, '.', EIGEN_MAJOR_VERSION, '.', EIGEN_MINOR_VERSION);
#if defined(FLEXSPLAT_HAVE_DNNL)
  if (backend == GemmBackend::bf16 && !bf16_gemm_native())
    return concat("bf16-rounded operands multiplied in fp32 on ",
                  gemm_backend_name(have_blas ? GemmBackend::blas : GemmBackend::eigen),
                  " (oneDNN has no bf16 kernels for this CPU)");
  if (backend == GemmBackend::bf16) {
    const dnnl_version_t* v = dnnl_version();
    return concat("oneDNN ", v->major, '.', v->minor, '.', v->patch, " bf16 matmul (fp32 accumulation), single-threaded "
                  "calls; small products on ", gemm_backend_name(have_blas ? GemmBackend::blas : GemmBackend::eigen));
  }
  if (backend == GemmBackend::onednn) {
    const dnnl_version_t* v = dnnl_version();
    return concat("oneDNN ", v->major, '.', v->minor, '.', v->patch, " fp32 matmul (",
                  detail::onednn_has_avx512() ? "AVX-512" : "no AVX-512", " kernels), single-threaded calls; products "
                  "under ", gemm_onednn_min_madds, " multiply-adds on ",
                  gemm_backend_name(have_blas ? GemmBackend::blas : GemmBackend::eigen));
  }
#endif
#if defined(FLEXSPLAT_HAVE_OPENBLAS)
  detail::openblas_single_threaded();
  std::string config = openblas_get_config();  // names the kernels in use
  config.erase(0, config.find_first_not_of(' '));
  return config + ", single-threaded calls";
#else
  return have_blas ? "CBLAS" : "no BLAS in this build";
#endif
}

// op(A) is M x K, op(B) is K x N, C is M x N; lda/ldb/ldc are row strides of the stored matrices. Deterministic for a
// given pool size: the split depends only on the shape and pool.size(), and each block runs single-threaded.
template <class T>
void gemm(GemmBackend backend, Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda,
          const T* B, index_t ldb, T beta, T* C, index_t ldc, ThreadPool& pool = global_pool()) {
  if (M <= 0 || N <= 0) return;
  const profile::Scope timed(profile::Op::gemm, 2.0 * double(M) * double(N) * double(K));
  const profile::GemmShapeScope shape({M, N, K, ta == Trans::yes, tb == Trans::yes});
  require(backend != GemmBackend::blas || have_blas, "gemm: the BLAS backend was requested but this build has none");
  require(backend != GemmBackend::bf16 || have_bf16_gemm, "gemm: bf16 was requested but this build has no oneDNN");
  require(backend != GemmBackend::onednn || have_onednn_gemm, "gemm: oneDNN was requested but this build has none");
  // Decided for the whole product, so that the pool's split never changes the precision or the summation order.
  if ((backend == GemmBackend::bf16 && (!std::is_same_v<T, float> || M * N * K < gemm_bf16_min_madds)) ||
      (backend == GemmBackend::onednn && (!std::is_same_v<T, float> || M * N * K < gemm_onednn_min_madds)))
    backend = have_blas ? GemmBackend::blas : GemmBackend::eigen;
  if (backend != GemmBackend::eigen) {
    const index_t a_cols = ta == Trans::no ? K : M, b_cols = tb == Trans::no ? N : K;
    const index_t a_rows = ta == Trans::no ? M : K, b_rows = tb == Trans::no ? K : N;
    if (std::max({M, N, K, lda, ldb, ldc}) > index_t(INT_MAX) || (a_rows > 1 && lda < a_cols) ||
        (b_rows > 1 && ldb < b_cols) || (M > 1 && ldc < N))
      fail("gemm: M ", M, " N ", N, " K ", K, " with lda ", lda, " ldb ", ldb, " ldc ", ldc,
           " is not a valid BLAS call (strides shorter than rows, or beyond 32-bit)");
  }
  // The weight cache of the calling thread, never inside a parallel region (the other workers' threads have none).
  GemmWeightCache* cache = nullptr;
  if constexpr (std::is_same_v<T, float>) {
    GemmWeightCache* active = detail::active_gemm_weight_cache();
    if (backend == GemmBackend::bf16 && active && ThreadPool::current_worker() < 0 && active->covers(B, tb, K, N, ldb))
      cache = active;
  }
  auto b_at = [&](index_t c0) { return tb == Trans::no ? B + c0 : B + c0 * ldb; };  // op(B)'s column c0
  auto block = [&](index_t r0, index_t r1, index_t c0, index_t c1) {
    const T* a = ta == Trans::no ? A + r0 * lda : A + r0;
    const T* b = b_at(c0);
    detail::gemm_block(backend, ta, tb, r1 - r0, c1 - c0, K, alpha, a, lda, b, ldb, beta, C + r0 * ldc + c0, ldc,
                       cache);
  };
  const index_t flops = M * N * (K > 0 ? K : 1);
  const index_t workers = pool.size();
  // Inside a parallel region every worker is busy already: one single-threaded call.
  if (flops < (index_t(1) << 18) || workers == 1 || ThreadPool::current_worker() >= 0) {
    block(0, M, 0, N);
    return;
  }
  // Few rows (e.g. one token per frame), or C at least 4x wider than tall (the DPT convolutions' weight x im2col):
  // split the columns, so that no worker multiplies a thin slice of rows against all of B (oneDNN on 2 threads:
  // 1.0-2.6x faster on the DPT shapes, bench/gemm's split table).
  const bool by_columns = (M < 4 * workers && N >= 16 * workers) || N >= 4 * M;
  const index_t extent = by_columns ? N : M;
  const index_t chunks = std::min<index_t>(workers, extent);
  // Chunk k's rows [r0, r1) and columns [c0, c1).
  auto part = [&](index_t k) -> std::array<index_t, 4> {
    const index_t lo = extent * k / chunks, hi = extent * (k + 1) / chunks;
    return by_columns ? std::array<index_t, 4>{0, M, lo, hi} : std::array<index_t, 4>{lo, hi, 0, N};
  };
#if defined(FLEXSPLAT_HAVE_DNNL)
  if constexpr (std::is_same_v<T, float>) {
    if (cache && K > 0 && alpha != 0.0f)  // made here, packed on all cores, not by one worker while the other waits
      for (index_t k = 0; k < chunks; ++k) {
        const auto [r0, r1, c0, c1] = part(k);
        cache->prepare(ta, tb, r1 - r0, c1 - c0, K, alpha, lda, b_at(c0), ldb, beta, ldc, int(workers));
      }
  }
#endif
  parallel_for(chunks, [&](index_t k0, index_t k1, int) {
    for (index_t k = k0; k < k1; ++k) {
      const auto [r0, r1, c0, c1] = part(k);
      block(r0, r1, c0, c1);
    }
  }, pool);
}

template <class T>
void gemm(Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A, index_t lda, const T* B,
          index_t ldb, T beta, T* C, index_t ldc, ThreadPool& pool = global_pool()) {
  gemm(default_gemm_backend(), ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc, pool);
}

// Batched: count independent products with fixed strides between consecutive matrices.
template <class T>
void gemm_batched(index_t count, Trans ta, Trans tb, index_t M, index_t N, index_t K, T alpha, const T* A,
                  index_t lda, index_t stride_a, const T* B, index_t ldb, index_t stride_b, T beta, T* C, index_t ldc,
                  index_t stride_c, ThreadPool& pool = global_pool()) {
  if (count <= 0) return;
  if (count == 1 || count < pool.size()) {
    for (index_t i = 0; i < count; ++i)
      gemm(ta, tb, M, N, K, alpha, A + i * stride_a, lda, B + i * stride_b, ldb, beta, C + i * stride_c, ldc, pool);
    return;
  }
  parallel_for(count, [&](index_t b0, index_t b1, int) {
    for (index_t i = b0; i < b1; ++i)
      gemm(ta, tb, M, N, K, alpha, A + i * stride_a, lda, B + i * stride_b, ldb, beta, C + i * stride_c, ldc, pool);
  }, pool);
}

}  // namespace v0
}  // namespace flexsplat
