#include <catch2/catch.hpp>

#include <atomic>
#include <vector>

#include "flexsplat/core/parallel.hpp"

using namespace flexsplat;

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

TEST_CASE("parallel_for rethrows a worker's exception", "[parallel]") {
  ThreadPool pool(2);
  CHECK_THROWS_WITH(parallel_for(10, [&](index_t b, index_t, int) {
    if (b > 0) fail("boom in worker");
  }, pool), "boom in worker");
}
