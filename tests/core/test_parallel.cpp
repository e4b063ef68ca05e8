#include <catch2/catch.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "flexsplat/core/parallel.hpp"

using namespace flexsplat;

namespace {
using Chunk = std::tuple<index_t, index_t, int>;

std::vector<Chunk> record_chunks(ThreadPool& pool, index_t n) {
  std::vector<Chunk> chunks(static_cast<std::size_t>(pool.size()), Chunk{-1, -1, -1});
  parallel_for(n, [&](index_t b, index_t e, int w) { chunks[static_cast<std::size_t>(w)] = {b, e, w}; }, pool);
  return chunks;
}

// Restores an environment variable when the test ends, pass or fail.
struct ScopedEnv {
  std::string name, old;
  bool had;
  ScopedEnv(const char* n, const char* value) : name(n) {
    const char* o = std::getenv(n);
    had = o != nullptr;
    if (had) old = o;
    ::setenv(n, value, 1);
  }
  ~ScopedEnv() {
    if (had) ::setenv(name.c_str(), old.c_str(), 1);
    else ::unsetenv(name.c_str());
  }
};
}  // namespace

TEST_CASE("parallel_for covers every index exactly once with fixed chunks", "[parallel]") {
  ThreadPool pool(3);
  std::vector<int> hits(1000, 0), owner(1000, -1);
  parallel_for(1000, [&](index_t b, index_t e, int w) {
    for (index_t i = b; i < e; ++i) {
      ++hits[i];
      owner[i] = w;
    }
  }, pool);
  for (int h : hits) CHECK(h == 1);
  CHECK(owner[0] == 0);
  CHECK(owner[999] == 2);
  CHECK(owner[332] == 0);
  CHECK(owner[333] == 1);
}

TEST_CASE("parallel_for partitions identically on every run", "[parallel]") {
  ThreadPool pool(4);
  const auto first = record_chunks(pool, 10);
  for (int run = 0; run < 50; ++run) REQUIRE(record_chunks(pool, 10) == first);
  CHECK(first == std::vector<Chunk>{{0, 2, 0}, {2, 5, 1}, {5, 7, 2}, {7, 10, 3}});
  // Fewer items than workers: one item per worker, the rest idle.
  const auto small = record_chunks(pool, 2);
  CHECK(small[0] == Chunk{0, 1, 0});
  CHECK(small[1] == Chunk{1, 2, 1});
  CHECK(std::get<2>(small[2]) == -1);
  // A float reduction through per-worker partial sums is bitwise reproducible.
  std::vector<float> values(10007);
  for (std::size_t i = 0; i < values.size(); ++i) values[i] = 1.0f / static_cast<float>(i + 1);
  auto reduce = [&] {
    std::vector<float> partial(4, 0.0f);
    parallel_for(static_cast<index_t>(values.size()), [&](index_t b, index_t e, int w) {
      for (index_t i = b; i < e; ++i) partial[static_cast<std::size_t>(w)] += values[static_cast<std::size_t>(i)];
    }, pool);
    return partial[0] + partial[1] + partial[2] + partial[3];
  };
  const float reference = reduce();
  for (int run = 0; run < 20; ++run) REQUIRE(reduce() == reference);
}

TEST_CASE("parallel_for rethrows a worker's exception and the pool keeps working", "[parallel]") {
  ThreadPool pool(2);
  CHECK_THROWS_WITH(parallel_for(10, [&](index_t b, index_t, int) {
    if (b > 0) fail("boom in worker");
  }, pool), "boom in worker");
  CHECK_THROWS_WITH(parallel_for(10, [&](index_t b, index_t, int) {
    if (b == 0) fail("boom in caller");
  }, pool), "boom in caller");
  std::atomic<index_t> total{0};
  parallel_for(100, [&](index_t b, index_t e, int) { total += e - b; }, pool);
  CHECK(total == 100);
}

TEST_CASE("a parallel_for inside a parallel_for body runs serially without deadlock", "[parallel]") {
  // Catch2 assertions are not thread-safe: record inside the bodies, check afterwards.
  ThreadPool pool(3);
  std::vector<std::atomic<int>> hits(3 * 50);
  std::vector<Chunk> inner_chunk(3, Chunk{-1, -1, -1});
  std::vector<int> inner_calls(3, 0), outer_worker_seen(3, -2);
  parallel_for(3, [&](index_t b, index_t e, int w) {
    for (index_t outer = b; outer < e; ++outer) {
      const auto o = static_cast<std::size_t>(outer);
      parallel_for(50, [&](index_t ib, index_t ie, int iw) {
        ++inner_calls[o];
        inner_chunk[o] = {ib, ie, iw};
        for (index_t i = ib; i < ie; ++i) ++hits[static_cast<std::size_t>(outer * 50 + i)];
      }, pool);
      outer_worker_seen[o] = ThreadPool::current_worker() == w ? w : -1;
    }
  }, pool);
  for (auto& h : hits) CHECK(h == 1);
  CHECK(inner_calls == std::vector<int>{1, 1, 1});
  // The nested body gets the whole range and runs as its caller's worker.
  CHECK(inner_chunk == std::vector<Chunk>{{0, 50, 0}, {0, 50, 1}, {0, 50, 2}});
  CHECK(outer_worker_seen == std::vector<int>{0, 1, 2});
  CHECK(ThreadPool::current_worker() == -1);
  // Nesting into the global pool (another pool) from inside a region is serial too.
  std::atomic<int> inner_total{0};
  parallel_for(4, [&](index_t b, index_t e, int) {
    for (index_t outer = b; outer < e; ++outer)
      parallel_for(10, [&](index_t ib, index_t ie, int) { inner_total += static_cast<int>(ie - ib); });
  }, pool);
  CHECK(inner_total == 40);
}

TEST_CASE("FLEXSPLAT_NUM_THREADS is validated", "[parallel]") {
  {
    ScopedEnv env("FLEXSPLAT_NUM_THREADS", "3");
    CHECK(default_thread_count() == 3);
  }
  for (const char* bad : {"0", "-2", "abc", "4x", "100000", " "}) {
    ScopedEnv env("FLEXSPLAT_NUM_THREADS", bad);
    CHECK_THROWS_WITH(default_thread_count(), Catch::Contains("FLEXSPLAT_NUM_THREADS='" + std::string(bad) + "'"));
  }
  {
    ScopedEnv env("FLEXSPLAT_NUM_THREADS", "");
    CHECK(default_thread_count() >= 1);
  }
}

TEST_CASE("parallel_for ignores empty ranges and a single-thread pool runs inline", "[parallel]") {
  ThreadPool single(1);
  int calls = 0;
  parallel_for(0, [&](index_t, index_t, int) { ++calls; }, single);
  parallel_for(-5, [&](index_t, index_t, int) { ++calls; }, single);
  CHECK(calls == 0);
  parallel_for(7, [&](index_t b, index_t e, int w) {
    ++calls;
    CHECK((b == 0 && e == 7 && w == 0));
  }, single);
  CHECK(calls == 1);
}

TEST_CASE("try_run_on_all runs every worker when the pool is free and declines otherwise", "[parallel]") {
  ThreadPool pool(3);
  std::vector<std::atomic<int>> ran(3);
  CHECK(pool.try_run_on_all([&](int w) { ++ran[static_cast<std::size_t>(w)]; }));
  for (auto& r : ran) CHECK(r == 1);
  // inside a region (of any pool) and on one worker it declines without running the task
  std::atomic<int> inner_ran{0}, inner_ok{0};
  pool.run_on_all([&](int) { inner_ok += pool.try_run_on_all([&](int) { ++inner_ran; }) ? 1 : 0; });
  CHECK(inner_ok == 0);
  CHECK(inner_ran == 0);
  ThreadPool one(1);
  CHECK_FALSE(one.try_run_on_all([&](int) { ++inner_ran; }));
  CHECK(inner_ran == 0);
  // while another thread's region runs it declines at once instead of waiting
  std::atomic<bool> started{false}, release{false};
  std::thread other([&] {
    pool.run_on_all([&](int w) {
      if (w != 0) return;
      started = true;
      while (!release) std::this_thread::yield();
    });
  });
  while (!started) std::this_thread::yield();
  const bool ran_while_busy = pool.try_run_on_all([&](int) { ++inner_ran; });
  release = true;
  other.join();
  CHECK_FALSE(ran_while_busy);
  CHECK(inner_ran == 0);
  CHECK(pool.try_run_on_all([&](int) { ++inner_ran; }));
  CHECK(inner_ran == 3);
}

TEST_CASE("regions back to back (workers polling) and after pauses (workers asleep) all run and all finish",
          "[parallel]") {
  // Each region's sum is read after it returns: a worker that ran late, ran twice or missed a region shows here.
  for (const int threads : {2, 3, 4}) {
    ThreadPool pool(threads);
    std::vector<index_t> sums;
    for (int round = 0; round < 2000; ++round) {
      std::atomic<index_t> sum{0};
      parallel_for(64, [&](index_t b, index_t e, int) {
        for (index_t i = b; i < e; ++i) sum += i;
      }, pool);
      sums.push_back(sum.load());
      if (round % 250 == 0) std::this_thread::sleep_for(std::chrono::milliseconds(2));  // past the polling time
    }
    CHECK(std::count(sums.begin(), sums.end(), index_t{64 * 63 / 2}) == 2000);
    // A worker's exception after a pause reaches the caller, and the next region runs on every worker.
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
    CHECK_THROWS_WITH(parallel_for(threads, [&](index_t b, index_t, int) {
      if (b == threads - 1) fail("late boom");
    }, pool), "late boom");
    std::vector<int> ran(static_cast<std::size_t>(threads), 0);
    pool.run_on_all([&](int w) { ran[static_cast<std::size_t>(w)] = 1; });
    CHECK(std::count(ran.begin(), ran.end(), 1) == threads);
  }
}

TEST_CASE("two threads submitting to one pool take turns", "[parallel]") {
  ThreadPool pool(2);
  std::atomic<index_t> total{0};
  auto submit = [&] {
    for (int round = 0; round < 500; ++round)
      parallel_for(8, [&](index_t b, index_t e, int) { total += e - b; }, pool);
  };
  std::thread a(submit), b(submit);
  a.join(), b.join();
  CHECK(total == 2 * 500 * 8);
}

TEST_CASE("SerialScope makes the calling thread a one-thread process and restores it", "[parallel]") {
  ThreadPool two(2);
  const UsePool use(two);
  REQUIRE(&global_pool() == &two);
  {
    const SerialScope serial;
    CHECK(global_pool().size() == 1);
    CHECK(ThreadPool::current_worker() == -1);
    CHECK(serial_scope_open());
    std::vector<Chunk> seen;
    parallel_for(10, [&](index_t b, index_t e, int w) { seen.push_back({b, e, w}); });
    CHECK(seen == std::vector<Chunk>{{0, 10, 0}});  // one chunk, as on one thread
  }
  CHECK(&global_pool() == &two);
  CHECK(!serial_scope_open());
  // Inside a region, on worker 1: the worker index comes back after the scope.
  std::vector<int> after(2, -2);
  two.run_on_all([&](int w) {
    { const SerialScope serial; }
    after[static_cast<std::size_t>(w)] = ThreadPool::current_worker();
  });
  CHECK(after == std::vector<int>{0, 1});
}

TEST_CASE("parallel_tasks runs every task once, each as on one thread, and rethrows", "[parallel]") {
  ThreadPool two(2);
  const index_t n = 7;
  std::vector<int> runs(n, 0), pool_sizes(n, 0), workers(n, -1);
  parallel_tasks(n, [&](index_t i, int w) {
    ++runs[static_cast<std::size_t>(i)];
    pool_sizes[static_cast<std::size_t>(i)] = global_pool().size();
    workers[static_cast<std::size_t>(i)] = w;
  }, two);
  CHECK(runs == std::vector<int>(n, 1));
  CHECK(pool_sizes == std::vector<int>(n, 1));
  for (int w : workers) CHECK((w == 0 || w == 1));
  // One task, or a one-worker pool: a loop on the caller with the pool as it is (worker 0).
  ThreadPool one(1);
  ThreadPool& outer = global_pool();
  bool as_is = false;
  parallel_tasks(1, [&](index_t, int w) { as_is = &global_pool() == &outer && w == 0; }, two);
  CHECK(as_is);
  parallel_tasks(3, [&](index_t, int w) { CHECK(w == 0); }, one);
  CHECK_THROWS_WITH(parallel_tasks(5, [&](index_t i, int) { if (i == 3) throw std::runtime_error("task 3"); }, two),
                    "task 3");
  std::atomic<int> count{0};
  parallel_tasks(4, [&](index_t, int) { ++count; }, two);  // the pool still works
  CHECK(count == 4);
}
