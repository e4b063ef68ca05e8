#include <catch2/catch.hpp>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/loss/lpips_reference.hpp"
#include "flexsplat/testing/gradcheck.hpp"

using namespace flexsplat;

namespace {
// FLEXSPLAT_SHARED_DIR in the environment overrides the configured shared folder (a missing bundle must fail).
std::string lpips_bundle() {
  const char* env = std::getenv("FLEXSPLAT_SHARED_DIR");
  return std::string(env && *env ? env : FLEXSPLAT_SHARED_DIR) + "/reference-new/lpips_2024.safetensors";
}

std::vector<double> uniform_images(std::size_t n, unsigned seed, double lo, double hi) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(lo, hi);
  std::vector<double> v(n);
  for (auto& x : v) x = u(rng);
  return v;
}

// Narrow trunk: same structure as VGG16, few channels, so float64 finite differences stay fast.
struct TinyLpips {
  loss::LpipsConfig config{{4, 5, 6, 6, 8}};
  loss::LpipsWeights<double> weights{config};
  TinyLpips() {
    std::mt19937_64 rng(7);
    loss::lpips_init_random(std::span<double>(weights.params), weights.layout, rng);
  }
};
}  // namespace

TEST_CASE("lpips parameter layout uses the package's state_dict names and VGG16 shapes", "[loss][lpips]") {
  const loss::LpipsParamLayout L;
  REQUIRE(L.entries.size() == 2 + 2 * 13 + 5);
  CHECK(L.find("net.slice1.0.weight")->shape == std::vector<index_t>{64, 3, 3, 3});
  CHECK(L.find("net.slice3.14.bias")->shape == std::vector<index_t>{256});
  CHECK(L.find("net.slice5.28.weight")->shape == std::vector<index_t>{512, 512, 3, 3});
  CHECK(L.find("lin2.model.1.weight")->shape == std::vector<index_t>{1, 256, 1, 1});
  CHECK(L.find("scaling_layer.scale")->shape == std::vector<index_t>{1, 3, 1, 1});
  // VGG16's 14,714,688 trunk parameters, 1,472 lin weights, 6 scaling values.
  CHECK(L.size == 14714688 + 1472 + 6);
}

TEST_CASE("lpips float64 gradient check on a narrow trunk, both images, both outputs", "[loss][lpips]") {
  TinyLpips m;
  const index_t B = 2, H = 20, W = 18;
  for (const bool unit : {false, true}) {
    auto x0 = uniform_images(static_cast<std::size_t>(B * 3 * H * W), 11, unit ? 0.0 : -1.0, 1.0);
    auto x1 = uniform_images(x0.size(), 12, unit ? 0.0 : -1.0, 1.0);
    std::vector<double> d0(x0.size()), d1(x1.size());
    loss::LpipsCache<double> cache;
    const auto forward = [&](std::span<double> out) {
      loss::lpips_forward(out.data(), out.data() + B, x0.data(), x1.data(), B, H, W, m.weights.params.data(),
                          m.weights.layout, cache, unit);
    };
    const auto backward = [&](std::span<const double> d) {
      loss::lpips_backward(d0.data(), d1.data(), d.data(), d.data() + B, m.weights.params.data(), m.weights.layout, cache);
    };
    auto result = testing::check_gradients({{"in0", x0, d0}, {"in1", x1, d1}}, static_cast<std::size_t>(B * 6), forward,
                                           backward);
    INFO("unit_input " << unit << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("lpips is zero for identical images, symmetric, the sum of its layers, and skips a null image gradient",
          "[loss][lpips]") {
  TinyLpips m;
  const index_t B = 2, H = 17, W = 23;
  auto x0 = uniform_images(static_cast<std::size_t>(B * 3 * H * W), 21, -1.0, 1.0);
  auto x1 = uniform_images(x0.size(), 22, -1.0, 1.0);
  loss::LpipsCache<double> cache;
  double same[2], ab[2], ba[2], layers[10];
  const auto* p = m.weights.params.data();
  loss::lpips_forward(same, static_cast<double*>(nullptr), x0.data(), x0.data(), B, H, W, p, m.weights.layout, cache);
  CHECK(same[0] == 0.0);
  CHECK(same[1] == 0.0);
  loss::lpips_forward(ba, static_cast<double*>(nullptr), x1.data(), x0.data(), B, H, W, p, m.weights.layout, cache);
  loss::lpips_forward(ab, layers, x0.data(), x1.data(), B, H, W, p, m.weights.layout, cache);
  for (int b = 0; b < 2; ++b) {
    CHECK(ab[b] > 0.0);
    CHECK(ab[b] == Approx(ba[b]).epsilon(1e-14));
    double sum = 0;
    for (int k = 0; k < 5; ++k) sum += layers[b * 5 + k];
    CHECK(ab[b] == Approx(sum).epsilon(1e-14));
  }
  // A constant target: only d_in0 is asked for; the d_in1 slot must not be written.
  std::vector<double> d0(x0.size(), 0.0), d0_both(x0.size(), 0.0), d1(x1.size(), 0.0);
  const double ones[2] = {1.0, 1.0};
  loss::lpips_backward(d0.data(), static_cast<double*>(nullptr), ones, static_cast<const double*>(nullptr), p,
                       m.weights.layout, cache);
  loss::lpips_backward(d0_both.data(), d1.data(), ones, static_cast<const double*>(nullptr), p, m.weights.layout, cache);
  CHECK(d0 == d0_both);
}

TEST_CASE("lpips reuse_in1 (a fixed target) gives the same values and gradients as a full pass", "[loss][lpips]") {
  TinyLpips m;
  const index_t B = 2, H = 16, W = 21;
  const auto* p = m.weights.params.data();
  auto x0 = uniform_images(static_cast<std::size_t>(B * 3 * H * W), 31, 0.0, 1.0);
  auto x1 = uniform_images(x0.size(), 32, 0.0, 1.0), x2 = uniform_images(x0.size(), 33, 0.0, 1.0);
  loss::LpipsCache<double> full, reused;
  double a[2], b[2], la[10], lb[10];
  const double ones[2] = {1.0, 1.0};
  loss::lpips_forward(a, la, x2.data(), x1.data(), B, H, W, p, m.weights.layout, full, true);
  loss::lpips_forward(b, lb, x0.data(), x1.data(), B, H, W, p, m.weights.layout, reused, true);
  loss::lpips_forward(b, lb, x2.data(), static_cast<const double*>(nullptr), B, H, W, p, m.weights.layout, reused, true,
                      true);
  for (int i = 0; i < 2; ++i) CHECK(a[i] == b[i]);
  for (int i = 0; i < 10; ++i) CHECK(la[i] == lb[i]);
  std::vector<double> da(x0.size(), 0.0), db(x0.size(), 0.0);
  loss::lpips_backward(da.data(), static_cast<double*>(nullptr), ones, static_cast<const double*>(nullptr), p,
                       m.weights.layout, full);
  loss::lpips_backward(db.data(), static_cast<double*>(nullptr), ones, static_cast<const double*>(nullptr), p,
                       m.weights.layout, reused);
  CHECK(da == db);
  // Another size, or the other input range, cannot reuse the cached target.
  CHECK_THROWS_WITH(loss::lpips_forward(b, lb, x2.data(), static_cast<const double*>(nullptr), B, H, W, p,
                                        m.weights.layout, reused, false, true),
                    Catch::Contains("reuse_in1 needs a previous call"));
  loss::LpipsCache<double> empty;
  CHECK_THROWS_WITH(loss::lpips_forward(b, lb, x2.data(), static_cast<const double*>(nullptr), 1, H, W, p,
                                        m.weights.layout, empty, true, true),
                    Catch::Contains("reuse_in1 needs a previous call"));
}

TEST_CASE("lpips rejects images below 16x16 and non-finite pixels, and lists every missing or mis-shaped weight", "[loss][lpips]") {
  TinyLpips m;
  loss::LpipsCache<double> cache;
  std::vector<double> img(3 * 15 * 40), out(1);
  CHECK_THROWS_WITH(loss::lpips_forward(out.data(), static_cast<double*>(nullptr), img.data(), img.data(), 1, 15, 40,
                                        m.weights.params.data(), m.weights.layout, cache),
                    Catch::Contains("15x40"));
  img.assign(3 * 16 * 16, 0.25);
  img[2 * 256 + 16 * 5 + 7] = std::numeric_limits<double>::quiet_NaN();
  const std::vector<double> ok(img.size(), 0.5);
  CHECK_THROWS_WITH(loss::lpips_forward(out.data(), static_cast<double*>(nullptr), ok.data(), img.data(), 1, 16, 16,
                                        m.weights.params.data(), m.weights.layout, cache),
                    Catch::Contains("in1 image 0 channel 2 pixel (7, 5) is nan"));
  // A file with a narrow slice1 but the wrong lin0 width, and no slice5.28 at all.
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_test_lpips_bad.safetensors";
  safetensors::Writer writer;
  for (const auto& e : m.weights.layout.entries) {
    if (e.name == "net.slice5.28.weight") continue;
    std::vector<index_t> shape = e.shape;
    if (e.name == "lin0.model.1.weight") shape[1] += 1;
    index_t n = 1;
    for (auto d : shape) n *= d;
    std::vector<float> zeros(static_cast<std::size_t>(n));
    writer.add_raw(e.name, safetensors::Dtype::F32, shape, zeros.data(), zeros.size() * sizeof(float));
  }
  writer.write(path);
  const auto file = safetensors::File::open(path);
  CHECK(loss::lpips_config_from(file).widths == m.config.widths);
  loss::LpipsWeights<double> w(m.config);
  CHECK_THROWS_WITH(loss::lpips_load(std::span<double>(w.params), w.layout, file),
                    Catch::Contains("missing 'net.slice5.28.weight' [8, 8, 3, 3]") &&
                        Catch::Contains("'lin0.model.1.weight' has shape [1, 5, 1, 1], expected [1, 4, 1, 1]"));
  std::filesystem::remove(path);
}

TEST_CASE("lpips in-memory binding by name, including the lins.<k> alias", "[loss][lpips]") {
  TinyLpips m;
  loss::LpipsWeights<double> w(m.config);
  for (const auto& e : m.weights.layout.entries) {
    const std::string name = e.name.rfind("lin", 0) == 0 ? "lins." + e.name.substr(3) : e.name;
    loss::lpips_set_tensor(std::span<double>(w.params), w.layout, name,
                           std::span<const double>(m.weights.params.data() + e.offset, static_cast<std::size_t>(e.size)));
  }
  CHECK(w.params == m.weights.params);
  CHECK_THROWS_WITH(loss::lpips_set_tensor(std::span<double>(w.params), w.layout, "net.slice1.1.weight",
                                           std::span<const double>(m.weights.params.data(), 3)),
                    Catch::Contains("no parameter named 'net.slice1.1.weight'"));
}

// The bundle's smallest case here (time); ctest's "check-reference: lpips_2024" runs every case through the CLI.
TEST_CASE("lpips matches the reference package on the shared lpips bundle (float64 all, float32 values)",
          "[loss][lpips][reference]") {
  const std::string bundle = lpips_bundle();
  INFO("bundle " << bundle);
  REQUIRE(std::filesystem::exists(bundle));
  const auto file = safetensors::File::open(bundle);
  std::string smallest;
  index_t smallest_size = 0;
  for (const auto& c : loss::lpips_cases(file)) {
    const index_t n = file.info(c + "in0").numel();
    if (smallest.empty() || n < smallest_size) smallest = c, smallest_size = n;
  }
  ReferenceReport report;
  loss::check_lpips_bundle(file, report, {smallest});
  for (const auto& row : report.rows) {
    INFO(row.name << ": max_abs " << row.max_abs_error << " max_rel " << row.max_rel_error << " " << row.note);
    CHECK(row.pass);
    // The README's tolerances: float32 values 1e-5 relative; float64 values 1e-7, float64 gradients 1e-5 of max abs.
    const bool f32 = row.name.rfind("float32 ", 0) == 0, gradient = row.name.find("grad_in") != std::string::npos;
    CHECK(row.tolerance.value == (f32 || gradient ? 1e-5 : 1e-7));
  }
  CHECK(report.rows.size() == 8);
}
