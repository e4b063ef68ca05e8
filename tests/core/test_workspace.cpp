#include <catch2/catch.hpp>

#include <cstdint>
#include <cstring>

#include "flexsplat/core/workspace.hpp"

using namespace flexsplat;

namespace {
bool aligned64(const void* p) { return reinterpret_cast<std::uintptr_t>(p) % 64 == 0; }
}  // namespace

TEST_CASE("workspace hands out 64-byte aligned, non-overlapping buffers", "[workspace]") {
  Workspace ws(1024);
  auto a = ws.allocate<float>(3);
  auto b = ws.allocate<double>(5);
  auto c = ws.allocate<std::uint8_t>(1);
  CHECK(aligned64(a.data()));
  CHECK(aligned64(b.data()));
  CHECK(aligned64(c.data()));
  CHECK(reinterpret_cast<std::byte*>(b.data()) >= reinterpret_cast<std::byte*>(a.data() + 3));
  CHECK(reinterpret_cast<std::byte*>(c.data()) >= reinterpret_cast<std::byte*>(b.data() + 5));
  CHECK(ws.used_bytes() == 3 * 64);
  CHECK(ws.allocate<float>(0).empty());
  auto t = ws.tensor<float, 2>({4, 5});
  CHECK(t.shape() == Shape<2>{4, 5});
  CHECK(t.is_contiguous());
  CHECK(aligned64(t.data()));
  CHECK_THROWS_WITH(ws.allocate<float>(-1), Catch::Contains("invalid element count -1"));
}

TEST_CASE("workspace mark/reset frees in stack order and reports the peak", "[workspace]") {
  Workspace ws(4096);
  auto keep = ws.allocate<float>(16);
  const auto m = ws.mark();
  auto scratch = ws.allocate<float>(256);
  CHECK(ws.used_bytes() == 64 + 1024);
  ws.reset(m);
  CHECK(ws.used_bytes() == 64);
  auto again = ws.allocate<float>(256);
  CHECK(again.data() == scratch.data());  // space is reused
  {
    Workspace::Scope scope(ws);
    ws.allocate<float>(100);
    CHECK(ws.used_bytes() == 64 + 1024 + 448);
  }
  CHECK(ws.used_bytes() == 64 + 1024);
  CHECK(ws.peak_bytes() == 64 + 1024 + 448);
  ws.reset();
  CHECK(ws.used_bytes() == 0);
  CHECK(ws.peak_bytes() == 64 + 1024 + 448);
  (void)keep;
}

TEST_CASE("workspace overflow keeps earlier buffers valid and grows only at the next full reset", "[workspace]") {
  Workspace ws(256);
  const std::size_t allocations_before = ws.heap_allocations();
  auto run = [&] {
    auto a = ws.allocate<std::uint8_t>(200);
    std::memset(a.data(), 7, a.size());
    auto b = ws.allocate<std::uint8_t>(1000);  // does not fit: a second block
    std::memset(b.data(), 9, b.size());
    const bool a_intact = a[0] == 7 && a[199] == 7;
    ws.reset();
    return a_intact;
  };
  CHECK(run());
  CHECK(ws.heap_allocations() == allocations_before + 2);  // overflow block, then the consolidated block
  CHECK(ws.capacity_bytes() >= ws.peak_bytes());
  const std::size_t warmed = ws.heap_allocations();
  for (int i = 0; i < 5; ++i) CHECK(run());
  CHECK(ws.heap_allocations() == warmed);  // steady state: no allocations
}

TEST_CASE("workspace with growth disabled refuses to exceed its reservation", "[workspace]") {
  Workspace ws(512);
  ws.set_growth_allowed(false);
  ws.allocate<float>(64);
  ws.allocate<float>(64);
  CHECK_THROWS_WITH(ws.allocate<float>(1), Catch::Contains("exceeds the reserved capacity of 512 bytes"));
  ws.reset();
  CHECK_NOTHROW(ws.allocate<float>(128));
  CHECK_THROWS_WITH(ws.reserve(1 << 20), Catch::Contains("while 512 bytes are in use"));
  Workspace empty;
  empty.set_growth_allowed(false);
  CHECK_THROWS(empty.allocate<float>(1));
}

TEST_CASE("workspace rejects stale marks and moves cleanly", "[workspace]") {
  Workspace ws;
  ws.allocate<float>(10);
  const auto m = ws.mark();
  ws.reset();
  CHECK_THROWS_WITH(ws.reset(m), Catch::Contains("no longer valid"));
  Workspace moved(std::move(ws));
  auto p = moved.allocate<double>(4);
  CHECK(aligned64(p.data()));
}
