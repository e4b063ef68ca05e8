#pragma once
// Fixed worker pool with static, deterministic partitioning: chunk k of a range always goes to worker k.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <exception>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <type_traits>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/index.hpp"

namespace flexsplat {
inline namespace v0 {

// FLEXSPLAT_NUM_THREADS overrides the hardware concurrency; invalid values are an error.
inline int default_thread_count() {
  if (const char* env = std::getenv("FLEXSPLAT_NUM_THREADS"); env && *env) {
    char* end = nullptr;
    const long n = std::strtol(env, &end, 10);
    require(end && *end == '\0' && n >= 1 && n <= 1024, "FLEXSPLAT_NUM_THREADS='", env,
            "' is not a thread count in [1, 1024]");
    return static_cast<int>(n);
  }
  const unsigned hw = std::thread::hardware_concurrency();
  return hw ? static_cast<int>(hw) : 1;
}

class SerialScope;

class ThreadPool {
public:
  explicit ThreadPool(int threads = default_thread_count()) : size_(threads < 1 ? 1 : threads) {
    for (int i = 1; i < size_; ++i) workers_.emplace_back([this, i] { worker_loop(i); });
  }
  ~ThreadPool() {
    {
      std::lock_guard lock(mutex_);
      stop_.store(true, std::memory_order_release);
    }
    wake_.notify_all();
    for (auto& w : workers_) w.join();
  }
  ThreadPool(const ThreadPool&) = delete;
  ThreadPool& operator=(const ThreadPool&) = delete;

  int size() const noexcept { return size_; }

  // Index of the calling thread inside a parallel region (0 for the submitting thread), -1 outside any region.
  static int current_worker() noexcept { return worker_index(); }

  // Runs task(worker) on every worker (the caller is worker 0) and waits; the first exception is rethrown.
  // From inside a region (any pool) it runs task(current worker) alone on the calling thread: nesting never blocks.
  template <class Task>
  void run_on_all(Task&& task) {
    if (worker_index() >= 0) {
      task(worker_index());
      return;
    }
    if (size_ == 1) {
      RegionGuard guard(0);
      task(0);
      return;
    }
    std::lock_guard submit(submit_mutex_);  // one parallel region at a time from outside the pool
    run_locked(task);
  }

  // As run_on_all, but only when that runs at once on every worker: outside any region, with more than one worker and
  // no region submitted by another thread. Returns false, without running task, otherwise.
  template <class Task>
  bool try_run_on_all(Task&& task) {
    if (worker_index() >= 0 || size_ == 1) return false;
    std::unique_lock submit(submit_mutex_, std::try_to_lock);
    if (!submit.owns_lock()) return false;
    run_locked(task);
    return true;
  }

private:
  friend class SerialScope;
  // Waiting threads poll this long before they sleep: a training step opens thousands of regions of tens of
  // microseconds each, and a sleeping thread takes about as long to wake (bench/train_step, 2 threads).
  static constexpr std::chrono::microseconds spin_time{50};

  static void cpu_relax() noexcept {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    asm volatile("yield");
#endif
  }
  // Polls done() for spin_time; returns whether it became true.
  template <class Done>
  static bool spin_until(Done&& done) {
    const auto until = std::chrono::steady_clock::now() + spin_time;
    for (int i = 1;; ++i) {
      if (done()) return true;
      cpu_relax();
      if (i % 64 == 0 && std::chrono::steady_clock::now() >= until) return false;
    }
  }

  template <class Task>
  void run_locked(Task& task) {
    auto trampoline = [](void* context, int worker) { (*static_cast<std::remove_reference_t<Task>*>(context))(worker); };
    task_context_ = static_cast<void*>(std::addressof(task));
    task_fn_ = trampoline;
    error_ = nullptr;
    pending_.store(size_ - 1, std::memory_order_relaxed);
    int sleeping = 0;
    {
      std::lock_guard lock(mutex_);  // a worker between its check and its sleep cannot miss the new generation
      generation_.fetch_add(1, std::memory_order_release);
      sleeping = sleeping_;
    }
    if (sleeping > 0) wake_.notify_all();
    std::exception_ptr mine;
    {
      RegionGuard guard(0);
      try {
        task(0);
      } catch (...) {
        mine = std::current_exception();
      }
    }
    auto finished = [this] { return pending_.load(std::memory_order_acquire) == 0; };
    if (!spin_until(finished)) {
      std::unique_lock lock(mutex_);
      done_.wait(lock, finished);
    }
    task_context_ = nullptr;
    task_fn_ = nullptr;
    if (mine) std::rethrow_exception(mine);
    if (error_) std::rethrow_exception(error_);
  }

  static int& worker_index() {
    thread_local int index = -1;
    return index;
  }
  struct RegionGuard {
    explicit RegionGuard(int index) { worker_index() = index; }
    ~RegionGuard() { worker_index() = -1; }
    RegionGuard(const RegionGuard&) = delete;
    RegionGuard& operator=(const RegionGuard&) = delete;
  };

  void worker_loop(int index) {
    std::size_t seen = 0;
    auto woken = [&] {
      return stop_.load(std::memory_order_acquire) || generation_.load(std::memory_order_acquire) != seen;
    };
    for (;;) {
      if (!spin_until(woken)) {
        std::unique_lock lock(mutex_);
        ++sleeping_;
        wake_.wait(lock, woken);
        --sleeping_;
      }
      if (stop_.load(std::memory_order_acquire)) return;
      seen = generation_.load(std::memory_order_acquire);
      std::exception_ptr err;
      {
        RegionGuard guard(index);
        try {
          task_fn_(task_context_, index);
        } catch (...) {
          err = std::current_exception();
        }
      }
      if (err) {
        std::lock_guard lock(mutex_);
        if (!error_) error_ = err;
      }
      if (pending_.fetch_sub(1, std::memory_order_acq_rel) == 1) {
        std::lock_guard lock(mutex_);  // the submitter checks pending_ under it before it sleeps
        done_.notify_one();
      }
    }
  }

  int size_;
  std::vector<std::thread> workers_;
  std::mutex mutex_, submit_mutex_;
  std::condition_variable wake_, done_;
  void* task_context_ = nullptr;
  void (*task_fn_)(void*, int) = nullptr;
  std::atomic<std::size_t> generation_{0};
  std::atomic<int> pending_{0};
  std::atomic<bool> stop_{false};
  int sleeping_ = 0;  // workers waiting on wake_ (guarded by mutex_)
  std::exception_ptr error_;
};

namespace parallel_detail {
// The pool global_pool() gives on this thread instead of the process's (UsePool).
inline ThreadPool*& pool_override() noexcept {
  thread_local ThreadPool* pool = nullptr;
  return pool;
}
inline bool& serial_scope_flag() noexcept {
  thread_local bool open = false;
  return open;
}
}  // namespace parallel_detail

inline ThreadPool& global_pool() {
  if (ThreadPool* p = parallel_detail::pool_override()) return *p;
  static ThreadPool pool;
  return pool;
}

// While it lives, global_pool() on the calling thread is `pool` (scopes nest; the previous one comes back).
class UsePool {
public:
  explicit UsePool(ThreadPool& pool) noexcept : previous_(parallel_detail::pool_override()) {
    parallel_detail::pool_override() = &pool;
  }
  ~UsePool() { parallel_detail::pool_override() = previous_; }
  UsePool(const UsePool&) = delete;
  UsePool& operator=(const UsePool&) = delete;

private:
  ThreadPool* previous_;
};

// While it lives, the calling thread runs as a one-thread process: global_pool() is a pool of one worker and the thread
// is outside any region, so work split by the pool's size is split as on one thread and gives its results to the bit.
class SerialScope {
public:
  SerialScope() : use_(one()), worker_(ThreadPool::worker_index()), open_(parallel_detail::serial_scope_flag()) {
    ThreadPool::worker_index() = -1;
    parallel_detail::serial_scope_flag() = true;
  }
  ~SerialScope() {
    ThreadPool::worker_index() = worker_;
    parallel_detail::serial_scope_flag() = open_;
  }
  SerialScope(const SerialScope&) = delete;
  SerialScope& operator=(const SerialScope&) = delete;

private:
  static ThreadPool& one() {
    thread_local ThreadPool pool(1);
    return pool;
  }
  UsePool use_;
  int worker_;
  bool open_;
};

// Whether a SerialScope is open on this thread (other threads may be running other tasks meanwhile).
inline bool serial_scope_open() noexcept { return parallel_detail::serial_scope_flag(); }

// Calls body(begin, end, worker) on contiguous chunks of [0, n); chunk boundaries depend only on n and the pool size.
// Inside another parallel region it runs body(0, n, current worker) serially on the calling thread.
template <class Body>
void parallel_for(index_t n, Body&& body, ThreadPool& pool = global_pool()) {
  if (n <= 0) return;
  if (const int self = ThreadPool::current_worker(); self >= 0) {
    body(index_t{0}, n, self);
    return;
  }
  const int workers = static_cast<int>(std::min<index_t>(pool.size(), n));
  if (workers == 1) {
    body(index_t{0}, n, 0);
    return;
  }
  pool.run_on_all([&](int w) {
    if (w >= workers) return;
    const index_t begin = n * w / workers, end = n * (w + 1) / workers;
    body(begin, end, w);
  });
}

// Runs task(i, worker) once for every i in [0, n), each call on one worker inside a SerialScope: independent tasks
// too small for their operations to split well (a training step's scenes) run side by side, each as on one thread.
// Which worker (in [0, pool.size())) runs which task varies from run to run: results must not depend on it. With one
// worker, one task or inside a region it is a plain loop on the calling thread (worker 0), operations split as usual.
template <class Task>
void parallel_tasks(index_t n, Task&& task, ThreadPool& pool = global_pool()) {
  if (n <= 0) return;
  if (pool.size() == 1 || n == 1 || ThreadPool::current_worker() >= 0) {
    for (index_t i = 0; i < n; ++i) task(i, 0);
    return;
  }
  std::atomic<index_t> next{0};
  pool.run_on_all([&](int worker) {
    const SerialScope serial;
    for (index_t i; (i = next.fetch_add(1, std::memory_order_relaxed)) < n;) task(i, worker);
  });
}

}  // namespace v0
}  // namespace flexsplat
