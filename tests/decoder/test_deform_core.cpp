#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "decoder_test_util.hpp"
#include "flexsplat/decoder/deform_core.hpp"
#include "flexsplat/decoder/reference.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
const std::string bundle = std::string(FLEXSPLAT_SHARED_DIR) + "/reference/deform_core_4242.safetensors";

// grid_sample written out directly from its definition, the reference for the tap-based kernel.
double sample_direct(const std::vector<double>& value, const decoder::DeformCoreLayout& L, index_t b, index_t v, index_t h,
                     index_t d, double x, double y) {
  const double px = x * L.width[v] - 0.5, py = y * L.height[v] - 0.5;
  const double x0 = std::floor(px), y0 = std::floor(py);
  double acc = 0;
  for (int dy = 0; dy < 2; ++dy)
    for (int dx = 0; dx < 2; ++dx) {
      const double xi = x0 + dx, yi = y0 + dy;
      if (xi < 0 || yi < 0 || xi >= L.width[v] || yi >= L.height[v]) continue;
      const double w = (dx ? px - x0 : 1 - (px - x0)) * (dy ? py - y0 : 1 - (py - y0));
      const index_t pix = L.start[v] + static_cast<index_t>(yi) * L.width[v] + static_cast<index_t>(xi);
      acc += w * value[((b * L.value_len() + pix) * L.heads + h) * L.head_dim + d];
    }
  return acc;
}

struct SmallCase {
  std::vector<index_t> hw{5, 7, 3, 4};
  decoder::DeformCoreLayout L = decoder::make_deform_core_layout(2, 6, 2, 5, 3, hw);
  std::vector<double> value = random_normal(2 * L.value_len() * 2 * 5, 11);
  // Wider than [0,1] so taps fall off every edge.
  std::vector<double> loc = random_uniform(L.location_count() * 2, 12, -0.3, 1.3);
  std::vector<double> w = random_uniform(L.location_count(), 13, 0.0, 1.0);
};
}  // namespace

TEST_CASE("deform_core matches the golden bundle in float64", "[decoder][deform_core]") {
  const auto file = safetensors::File::open(bundle);
  ReferenceReport report;
  decoder::check_deform_core_bundle<double>(file, report, 1e-10);
  report.print(stdout);
  CHECK(report.rows.size() == 4 * decoder::deform_core_cases(file).size());
  CHECK(report.all_pass());
}

TEST_CASE("deform_core matches the golden bundle in float32", "[decoder][deform_core]") {
  const auto file = safetensors::File::open(bundle);
  ReferenceReport report;
  decoder::check_deform_core_bundle<float>(file, report, 1e-5);
  report.print(stdout);
  CHECK(report.all_pass());
}

TEST_CASE("deform_core forward equals grid_sample written out", "[decoder][deform_core]") {
  SmallCase c;
  const auto& L = c.L;
  std::vector<double> out(L.batch * L.n_queries * L.heads * L.head_dim);
  decoder::deform_core_forward(out.data(), c.value.data(), c.loc.data(), c.w.data(), L);
  for (index_t b = 0; b < L.batch; ++b)
    for (index_t q = 0; q < L.n_queries; ++q)
      for (index_t h = 0; h < L.heads; ++h)
        for (index_t d = 0; d < L.head_dim; ++d) {
          double expect = 0;
          for (index_t v = 0; v < L.views(); ++v)
            for (index_t p = 0; p < L.points; ++p) {
              const index_t s = (((b * L.n_queries + q) * L.heads + h) * L.views() + v) * L.points + p;
              expect += c.w[s] * sample_direct(c.value, L, b, v, h, d, c.loc[2 * s], c.loc[2 * s + 1]);
            }
          REQUIRE(out[((b * L.n_queries + q) * L.heads + h) * L.head_dim + d] == Approx(expect).margin(1e-13));
        }
}

TEST_CASE("deform_core passes the float64 gradient check", "[decoder][deform_core]") {
  SmallCase c;
  const auto& L = c.L;
  std::vector<double> dv(c.value.size()), dl(c.loc.size()), dw(c.w.size());
  const std::size_t n_out = L.batch * L.n_queries * L.heads * L.head_dim;
  auto result = testing::check_gradients(
      {{"value", c.value, dv}, {"locations", c.loc, dl}, {"weights", c.w, dw}}, n_out,
      [&](std::span<double> o) { decoder::deform_core_forward(o.data(), c.value.data(), c.loc.data(), c.w.data(), L); },
      [&](std::span<const double> g) {
        decoder::deform_core_backward(dv.data(), dl.data(), dw.data(), g.data(), c.value.data(), c.loc.data(), c.w.data(), L);
      });
  INFO(result.summary());
  CHECK(result.ok());
}

TEST_CASE("deform_core results do not depend on the thread count", "[decoder][deform_core]") {
  SmallCase c;
  const auto& L = c.L;
  ThreadPool one(1), three(3);
  const std::size_t n_out = L.batch * L.n_queries * L.heads * L.head_dim;
  std::vector<double> o1(n_out), o3(n_out), g = random_normal(n_out, 5);
  std::vector<double> dv1(c.value.size()), dv3(c.value.size()), dl1(c.loc.size()), dl3(c.loc.size());
  decoder::deform_core_forward(o1.data(), c.value.data(), c.loc.data(), c.w.data(), L, one);
  decoder::deform_core_forward(o3.data(), c.value.data(), c.loc.data(), c.w.data(), L, three);
  decoder::deform_core_backward(dv1.data(), dl1.data(), (double*)nullptr, g.data(), c.value.data(), c.loc.data(), c.w.data(), L, one);
  decoder::deform_core_backward(dv3.data(), dl3.data(), (double*)nullptr, g.data(), c.value.data(), c.loc.data(), c.w.data(), L, three);
  CHECK(o1 == o3);
  CHECK(dv1 == dv3);
  CHECK(dl1 == dl3);
}

TEST_CASE("deform_core stays finite for extreme and non-finite locations", "[decoder][deform_core]") {
  SmallCase c;
  const auto& L = c.L;
  const double inf = std::numeric_limits<double>::infinity(), nan = std::numeric_limits<double>::quiet_NaN();
  const double extremes[] = {1e30, -1e30, inf, -inf, nan, 1e18, -1.0 / 7.0, 1.0 + 1.0 / 7.0};
  for (std::size_t i = 0; i < c.loc.size(); ++i) c.loc[i] = extremes[i % 8];
  const std::size_t n_out = L.batch * L.n_queries * L.heads * L.head_dim;
  std::vector<double> out(n_out), g = random_normal(n_out, 6), dv(c.value.size()), dl(c.loc.size()), dw(c.w.size());
  decoder::deform_core_forward(out.data(), c.value.data(), c.loc.data(), c.w.data(), L);
  decoder::deform_core_backward(dv.data(), dl.data(), dw.data(), g.data(), c.value.data(), c.loc.data(), c.w.data(), L);
  for (double x : out) REQUIRE(std::isfinite(x));
  for (double x : dv) REQUIRE(std::isfinite(x));
  for (double x : dl) REQUIRE(std::isfinite(x));
  for (double x : dw) REQUIRE(std::isfinite(x));
}

TEST_CASE("deform_core rejects zero-size feature maps with a clear error", "[decoder][deform_core]") {
  const std::vector<index_t> hw{4, 4, 0, 6};
  CHECK_THROWS_WITH(decoder::make_deform_core_layout(1, 3, 2, 4, 2, hw), Catch::Contains("view 1 is 0x6 (zero-size)"));
}
