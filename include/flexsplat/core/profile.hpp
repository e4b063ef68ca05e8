#pragma once
// Op-family profiler: self time (a GEMM inside a convolution counts as GEMM, not twice), calls and FLOPs per family,
// summed over threads. Off by default; a disabled scope costs one relaxed atomic load. bench/train_step turns it on.
//   profile::set_enabled(true); ... profile::Scope s(profile::Op::gemm, 2.0 * m * n * k); ...
//   const profile::Totals t = profile::totals();
// With set_gemm_shapes(true) as well, every gemm() call's wall time is also kept per shape (gemm_shapes()).
// Stages name the parts of a run (bench/reconstruct's roofline): profile::Stage s("dino") times its lifetime (wall
// and process CPU) and the FLOPs the op scopes counted meanwhile on every thread; nested stages make paths
// ("geometry/dino"); profile::stages() lists them, a parent before its children.
#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <compare>
#include <cstdint>
#include <ctime>
#include <map>
#include <mutex>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace flexsplat {
inline namespace v0 {
namespace profile {

enum class Op : int {
  attention_forward,
  attention_backward,
  deformable_forward,
  deformable_backward,
  conv_forward,
  conv_backward,
  gemm,
  raster_forward,
  raster_backward,
  data,
  update,
  count
};

inline constexpr const char* op_name(Op op) {
  constexpr const char* names[] = {"attention forward",  "attention backward", "deformable forward",
                                   "deformable backward", "conv forward",       "conv backward",
                                   "GEMM",                "raster forward",     "raster backward",
                                   "data generation",     "optimizer update"};
  static_assert(sizeof(names) / sizeof(names[0]) == static_cast<int>(Op::count));
  return names[static_cast<int>(op)];
}

inline constexpr int op_count = static_cast<int>(Op::count);

struct Totals {
  std::array<double, op_count> seconds{}, flops{};
  std::array<std::uint64_t, op_count> calls{};
};

// One GEMM shape: op(A) is m x k, op(B) k x n; ta / tb whether A / B are stored transposed.
struct GemmShape {
  std::int64_t m = 0, n = 0, k = 0;
  bool ta = false, tb = false;
  auto operator<=>(const GemmShape&) const = default;
};

namespace detail {

struct Counters {
  std::atomic<bool> enabled{false};
  std::array<std::atomic<std::int64_t>, op_count> nanoseconds{}, calls{};
  std::array<std::atomic<double>, op_count> flops{};
};

inline Counters& counters() {
  static Counters c;
  return c;
}

// The innermost open scope of this thread: its clock pauses while a nested scope runs.
struct Frame {
  Op op = Op::count;
  std::chrono::steady_clock::time_point since;
};
inline thread_local Frame* current = nullptr;
// The FLOPs of the scopes opened on this thread.
inline thread_local double thread_flops = 0;

struct ShapeTable {
  std::atomic<bool> on{false};
  std::mutex mutex;
  std::map<GemmShape, std::pair<std::uint64_t, double>> totals;  // calls, seconds
};

inline ShapeTable& shape_table() {
  static ShapeTable t;
  return t;
}

}  // namespace detail

// One stage's totals over its calls: wall and process-CPU seconds, and the FLOPs counted while it ran.
struct StageTotals {
  std::string path;  // the names of the enclosing stages and its own, joined by '/'
  int depth = 0;     // the number of enclosing stages
  std::uint64_t calls = 0;
  double seconds = 0, cpu_seconds = 0, flops = 0;
};

namespace detail {

struct StageTable {
  std::mutex mutex;
  std::vector<StageTotals> rows;  // in the order the stages first opened
};

inline StageTable& stage_table() {
  static StageTable t;
  return t;
}

// The path of the stages open on this thread.
inline thread_local std::string stage_path;

inline void add_time(Op op, std::chrono::steady_clock::duration d) {
  counters().nanoseconds[static_cast<int>(op)].fetch_add(
      std::chrono::duration_cast<std::chrono::nanoseconds>(d).count(), std::memory_order_relaxed);
}

}  // namespace detail

inline void set_enabled(bool on) { detail::counters().enabled.store(on, std::memory_order_relaxed); }
inline bool enabled() { return detail::counters().enabled.load(std::memory_order_relaxed); }

inline void set_gemm_shapes(bool on) { detail::shape_table().on.store(on, std::memory_order_relaxed); }

inline void reset() {
  {
    auto& t = detail::shape_table();
    const std::lock_guard lock(t.mutex);
    t.totals.clear();
  }
  {
    auto& t = detail::stage_table();
    const std::lock_guard lock(t.mutex);
    t.rows.clear();
  }
  auto& c = detail::counters();
  for (int i = 0; i < op_count; ++i) {
    c.nanoseconds[i].store(0, std::memory_order_relaxed);
    c.calls[i].store(0, std::memory_order_relaxed);
    c.flops[i].store(0.0, std::memory_order_relaxed);
  }
}

// The FLOPs of the scopes this thread opened since the process started (only while enabled).
inline double thread_flops() { return detail::thread_flops; }

inline Totals totals() {
  const auto& c = detail::counters();
  Totals t;
  for (int i = 0; i < op_count; ++i) {
    t.seconds[i] = double(c.nanoseconds[i].load(std::memory_order_relaxed)) * 1e-9;
    t.calls[i] = static_cast<std::uint64_t>(c.calls[i].load(std::memory_order_relaxed));
    t.flops[i] = c.flops[i].load(std::memory_order_relaxed);
  }
  return t;
}

struct GemmShapeTotals {
  GemmShape shape;
  std::uint64_t calls = 0;
  double seconds = 0;  // wall time of the calls, summed over the threads that made them
};

// The shapes gemm() ran while shapes were on, the most time first.
inline std::vector<GemmShapeTotals> gemm_shapes() {
  auto& t = detail::shape_table();
  std::vector<GemmShapeTotals> out;
  {
    const std::lock_guard lock(t.mutex);
    for (const auto& [shape, v] : t.totals) out.push_back({shape, v.first, v.second});
  }
  std::sort(out.begin(), out.end(), [](const GemmShapeTotals& a, const GemmShapeTotals& b) {
    return a.seconds != b.seconds ? a.seconds > b.seconds : a.shape < b.shape;
  });
  return out;
}

// Adds its lifetime to its shape's totals when the profiler and the shape table are both on.
class GemmShapeScope {
public:
  explicit GemmShapeScope(GemmShape shape) {
    if (!enabled() || !detail::shape_table().on.load(std::memory_order_relaxed)) return;
    active_ = true;
    shape_ = shape;
    since_ = std::chrono::steady_clock::now();
  }
  GemmShapeScope(const GemmShapeScope&) = delete;
  GemmShapeScope& operator=(const GemmShapeScope&) = delete;
  ~GemmShapeScope() {
    if (!active_) return;
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - since_).count();
    auto& t = detail::shape_table();
    const std::lock_guard lock(t.mutex);
    auto& v = t.totals[shape_];
    v.first += 1;
    v.second += s;
  }

private:
  bool active_ = false;
  GemmShape shape_;
  std::chrono::steady_clock::time_point since_;
};

// Times its lifetime as `op` on this thread, minus the nested scopes' time; `flops` are added to the family.
class Scope {
public:
  explicit Scope(Op op, double flops = 0) {
    if (!enabled()) return;
    active_ = true;
    const auto now = std::chrono::steady_clock::now();
    if (detail::current) detail::add_time(detail::current->op, now - detail::current->since);
    frame_ = {op, now};
    parent_ = detail::current;
    detail::current = &frame_;
    auto& c = detail::counters();
    c.calls[static_cast<int>(op)].fetch_add(1, std::memory_order_relaxed);
    if (flops > 0) {
      c.flops[static_cast<int>(op)].fetch_add(flops, std::memory_order_relaxed);
      detail::thread_flops += flops;
    }
  }
  Scope(const Scope&) = delete;
  Scope& operator=(const Scope&) = delete;
  ~Scope() {
    if (!active_) return;
    const auto now = std::chrono::steady_clock::now();
    detail::add_time(frame_.op, now - frame_.since);
    detail::current = parent_;
    if (parent_) parent_->since = now;
  }

private:
  bool active_ = false;
  detail::Frame frame_;
  detail::Frame* parent_ = nullptr;
};

// The FLOPs every op family counted so far.
inline double counted_flops() {
  const auto& c = detail::counters();
  double f = 0;
  for (int i = 0; i < op_count; ++i) f += c.flops[i].load(std::memory_order_relaxed);
  return f;
}

// Every stage run while enabled, a parent before its children.
inline std::vector<StageTotals> stages() {
  auto& t = detail::stage_table();
  const std::lock_guard lock(t.mutex);
  return t.rows;
}

// Times its lifetime as the stage `name` inside the stages open on this thread. Stages are opened by the thread that
// drives a run; the FLOPs of its worker threads count (so two stages must not run at once).
class Stage {
public:
  explicit Stage(std::string_view name) {
    if (!enabled()) return;
    active_ = true;
    outer_length_ = detail::stage_path.size();
    if (!detail::stage_path.empty()) detail::stage_path += '/';
    detail::stage_path += name;
    flops0_ = counted_flops();
    cpu0_ = std::clock();
    since_ = std::chrono::steady_clock::now();
  }
  Stage(const Stage&) = delete;
  Stage& operator=(const Stage&) = delete;
  ~Stage() {
    if (!active_) return;
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - since_).count();
    const double cpu = static_cast<double>(std::clock() - cpu0_) / CLOCKS_PER_SEC;
    const double flops = counted_flops() - flops0_;
    {
      auto& t = detail::stage_table();
      const std::lock_guard lock(t.mutex);
      auto row = std::find_if(t.rows.begin(), t.rows.end(),
                              [](const StageTotals& r) { return r.path == detail::stage_path; });
      if (row == t.rows.end()) {
        // A parent closes after its children: it goes before the first row under its path.
        const std::string prefix = detail::stage_path + '/';
        auto first_child = std::find_if(t.rows.begin(), t.rows.end(),
                                        [&](const StageTotals& r) { return r.path.starts_with(prefix); });
        const int depth = static_cast<int>(std::count(detail::stage_path.begin(), detail::stage_path.end(), '/'));
        row = t.rows.insert(first_child, StageTotals{detail::stage_path, depth});
      }
      row->calls += 1;
      row->seconds += seconds;
      row->cpu_seconds += cpu;
      row->flops += flops;
    }
    detail::stage_path.resize(outer_length_);
  }

private:
  bool active_ = false;
  std::size_t outer_length_ = 0;
  double flops0_ = 0;
  std::clock_t cpu0_ = 0;
  std::chrono::steady_clock::time_point since_;
};

}  // namespace profile
}  // namespace v0
}  // namespace flexsplat
