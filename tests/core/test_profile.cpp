#include <catch2/catch.hpp>

#include <chrono>
#include <thread>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/profile.hpp"

using namespace flexsplat;

namespace {
void busy(std::chrono::milliseconds d) {
  const auto until = std::chrono::steady_clock::now() + d;
  while (std::chrono::steady_clock::now() < until) {
  }
}
double seconds(const profile::Totals& t, profile::Op op) { return t.seconds[static_cast<int>(op)]; }
std::uint64_t calls(const profile::Totals& t, profile::Op op) { return t.calls[static_cast<int>(op)]; }
}  // namespace

TEST_CASE("profile scopes count nothing while disabled", "[core][profile]") {
  profile::set_enabled(false);
  profile::reset();
  {
    const profile::Scope s(profile::Op::conv_forward, 1e6);
    busy(std::chrono::milliseconds(2));
  }
  const auto t = profile::totals();
  for (int i = 0; i < profile::op_count; ++i) {
    CHECK(t.seconds[i] == 0.0);
    CHECK(t.calls[i] == 0);
    CHECK(t.flops[i] == 0.0);
  }
}

TEST_CASE("profile scopes record self time: a nested scope's time goes to its own family only", "[core][profile]") {
  profile::reset();
  profile::set_enabled(true);
  {
    const profile::Scope outer(profile::Op::conv_backward);
    busy(std::chrono::milliseconds(20));
    {
      const profile::Scope inner(profile::Op::gemm, 1234.0);
      busy(std::chrono::milliseconds(40));
    }
    busy(std::chrono::milliseconds(20));
  }
  profile::set_enabled(false);
  const auto t = profile::totals();
  CHECK(calls(t, profile::Op::conv_backward) == 1);
  CHECK(calls(t, profile::Op::gemm) == 1);
  CHECK(t.flops[static_cast<int>(profile::Op::gemm)] == 1234.0);
  // Busy-waits are at least as long as asked; a preempted thread only makes a scope longer.
  CHECK(seconds(t, profile::Op::gemm) >= 0.040);
  CHECK(seconds(t, profile::Op::conv_backward) >= 0.040);
  // Inclusive timing would give the outer scope >= 80 ms (busy-waits end at wall-clock deadlines); self time is
  // about 40 ms, more only if the thread is descheduled between a deadline and the end of its scope.
  CHECK(seconds(t, profile::Op::conv_backward) < 0.075);
  profile::reset();
  CHECK(profile::totals().calls[static_cast<int>(profile::Op::gemm)] == 0);
}

TEST_CASE("gemm reports its calls and 2 M N K FLOPs to the profiler", "[core][profile]") {
  const index_t M = 7, N = 5, K = 3;
  std::vector<float> a(M * K, 1.0f), b(K * N, 1.0f), c(M * N, 0.0f);
  profile::reset();
  profile::set_enabled(true);
  gemm(Trans::no, Trans::no, M, N, K, 1.0f, a.data(), K, b.data(), N, 0.0f, c.data(), N);
  gemm(Trans::no, Trans::no, M, N, K, 1.0f, a.data(), K, b.data(), N, 0.0f, c.data(), N);
  profile::set_enabled(false);
  const auto t = profile::totals();
  CHECK(calls(t, profile::Op::gemm) == 2);
  CHECK(t.flops[static_cast<int>(profile::Op::gemm)] == 2 * 2.0 * M * N * K);
  CHECK(c[0] == 3.0f);
  profile::reset();
}

TEST_CASE("gemm shapes: each call lands on its own M N K and transposes, only with shapes and the profiler on", "[core][profile]") {
  // b holds 6 x 4 for the transposed-B call (N = 6, K = 4), more than the 4 x 5 of the others.
  std::vector<float> a(6 * 4, 1.0f), b(6 * 4, 1.0f), c(6 * 5, 0.0f);
  profile::reset();
  profile::set_enabled(true);
  gemm(Trans::no, Trans::no, 6, 5, 4, 1.0f, a.data(), 4, b.data(), 5, 0.0f, c.data(), 5);  // shapes off: not kept
  profile::set_gemm_shapes(true);
  gemm(Trans::no, Trans::no, 6, 5, 4, 1.0f, a.data(), 4, b.data(), 5, 0.0f, c.data(), 5);
  gemm(Trans::no, Trans::no, 6, 5, 4, 1.0f, a.data(), 4, b.data(), 5, 0.0f, c.data(), 5);
  gemm(Trans::yes, Trans::no, 6, 5, 4, 1.0f, a.data(), 6, b.data(), 5, 0.0f, c.data(), 5);
  gemm(Trans::no, Trans::yes, 5, 6, 4, 1.0f, a.data(), 4, b.data(), 4, 0.0f, c.data(), 6);
  profile::set_enabled(false);
  gemm(Trans::no, Trans::no, 6, 5, 4, 1.0f, a.data(), 4, b.data(), 5, 0.0f, c.data(), 5);  // profiler off: not kept
  const std::vector<profile::GemmShapeTotals> shapes = profile::gemm_shapes();
  profile::set_gemm_shapes(false);
  REQUIRE(shapes.size() == 3);
  auto find = [&](profile::GemmShape s) -> const profile::GemmShapeTotals* {
    for (const auto& g : shapes)
      if (g.shape == s) return &g;
    return nullptr;
  };
  const auto* plain = find({6, 5, 4, false, false});
  const auto* ta = find({6, 5, 4, true, false});
  const auto* tb = find({5, 6, 4, false, true});
  REQUIRE(plain);
  REQUIRE(ta);
  REQUIRE(tb);
  CHECK(plain->calls == 2);
  CHECK(ta->calls == 1);
  CHECK(tb->calls == 1);
  for (std::size_t i = 1; i < shapes.size(); ++i) CHECK(shapes[i - 1].seconds >= shapes[i].seconds);
  CHECK(plain->seconds > 0);
  profile::reset();
  CHECK(profile::gemm_shapes().empty());
}

TEST_CASE("profile stages: nested paths, a parent listed before its children, inclusive time and the FLOPs inside",
          "[core][profile]") {
  profile::reset();
  {
    const profile::Stage off("not recorded");  // disabled: nothing
  }
  CHECK(profile::stages().empty());
  profile::set_enabled(true);
  for (int round = 0; round < 2; ++round) {
    const profile::Stage outer("outer");
    busy(std::chrono::milliseconds(5));
    {
      const profile::Stage a("a");
      const profile::Scope s(profile::Op::gemm, 100.0);
      busy(std::chrono::milliseconds(10));
    }
    {
      const profile::Stage b("b");
      const profile::Scope s(profile::Op::attention_forward, 7.0);
    }
  }
  {
    const profile::Stage other("other");
  }
  profile::set_enabled(false);
  const std::vector<profile::StageTotals> st = profile::stages();
  REQUIRE(st.size() == 4);
  CHECK(st[0].path == "outer");
  CHECK(st[1].path == "outer/a");
  CHECK(st[2].path == "outer/b");
  CHECK(st[3].path == "other");
  CHECK(st[0].depth == 0);
  CHECK(st[1].depth == 1);
  for (std::size_t i = 0; i < 3; ++i) CHECK(st[i].calls == 2);
  // A stage's FLOPs are every op scope's inside it, its children's included; its time too (inclusive, unlike scopes).
  CHECK(st[0].flops == 214.0);
  CHECK(st[1].flops == 200.0);
  CHECK(st[2].flops == 14.0);
  CHECK(st[3].flops == 0.0);
  CHECK(st[1].seconds >= 0.020);
  CHECK(st[0].seconds >= st[1].seconds + 0.010);
  profile::reset();
  CHECK(profile::stages().empty());
}
