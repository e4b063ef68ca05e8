#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "flexsplat/optim/optimizer.hpp"

using namespace flexsplat;

namespace {
train::ParamStore<double> two_tensor_store() {
  train::ParamStore<double> store;
  store.add_segment("s", {{"layer.weight", {2, 2}}, {"layer.bias", {2}}});
  store.allocate();
  const double p[] = {0.5, -1.0, 2.0, 0.25}, g[] = {0.1, -0.2, 0.0, 3.0}, b[] = {1.0, -2.0}, gb[] = {0.5, -0.5};
  std::copy(p, p + 4, store.param("layer.weight").data());
  std::copy(g, g + 4, store.grad("layer.weight").data());
  std::copy(b, b + 2, store.param("layer.bias").data());
  std::copy(gb, gb + 2, store.grad("layer.bias").data());
  return store;
}
}  // namespace

TEST_CASE("AdamW steps match a hand computation, with decay on the matrix only", "[train][optimizer]") {
  auto store = two_tensor_store();
  const train::AdamWConfig c{0.9, 0.999, 1e-8, 0.1};
  const double lr = 0.01;
  train::adamw_step(store, c, lr, 1);
  // Step 1: m = 0.1 g, v = 0.001 g^2, m_hat = g, v_hat = g^2: update = lr * g / (|g| + eps).
  // weight[0]: 0.5 * (1 - 0.01 * 0.1) - 0.01 * 0.1 / (0.1 + 1e-8)
  CHECK(store.param("layer.weight")[0] == Approx(0.5 * 0.999 - 0.01 * 0.1 / (0.1 + 1e-8)).epsilon(1e-14));
  CHECK(store.param("layer.weight")[2] == Approx(2.0 * 0.999).epsilon(1e-14));  // zero gradient: decay only
  CHECK(store.param("layer.bias")[0] == Approx(1.0 - 0.01 * 0.5 / (0.5 + 1e-8)).epsilon(1e-14));  // no decay
  CHECK(store.adam_m()[store.info("layer.bias").offset + 1] == Approx(-0.05).epsilon(1e-14));
  CHECK(store.adam_v()[store.info("layer.weight").offset + 3] == Approx(0.001 * 9.0).epsilon(1e-14));
  // Step 2 with the same gradient on weight[3] = 0.25 -> p1: m = 0.19 * 3, v = 0.001999 * 9.
  const double p1 = store.param("layer.weight")[3];
  CHECK(p1 == Approx(0.25 * 0.999 - 0.01 * 3.0 / (3.0 + 1e-8)).epsilon(1e-14));
  train::adamw_step(store, c, lr, 2);
  const double m = 0.19 * 3.0, v = 0.001999 * 9.0;
  const double expected = p1 * 0.999 - lr * (m / (1 - 0.81)) / (std::sqrt(v / (1 - 0.998001)) + 1e-8);
  CHECK(store.param("layer.weight")[3] == Approx(expected).epsilon(1e-13));
  CHECK_THROWS_WITH(train::adamw_step(store, c, lr, 0), Catch::Contains("1-based"));
  // A per-tensor learning-rate scale acts as that tensor's own learning rate.
  auto scaled = two_tensor_store();
  scaled.set_lr_scale("layer.bias", 0.5);
  train::adamw_step(scaled, c, lr, 1);
  CHECK(scaled.param("layer.bias")[0] == Approx(1.0 - 0.005 * 0.5 / (0.5 + 1e-8)).epsilon(1e-14));
  CHECK(scaled.param("layer.weight")[2] == Approx(2.0 * 0.999).epsilon(1e-14));
}

TEST_CASE("gradient clipping: norm, scaling, and the first non-finite tensor named", "[train][optimizer]") {
  auto store = two_tensor_store();
  const double norm = std::sqrt(0.01 + 0.04 + 0.0 + 9.0 + 0.25 + 0.25);
  CHECK(train::clip_grad_norm(store, 0.0) == Approx(norm).epsilon(1e-15));
  CHECK(store.grad("layer.weight")[3] == 3.0);  // max_norm 0: measure only
  CHECK(train::clip_grad_norm(store, 1.0) == Approx(norm).epsilon(1e-15));
  CHECK(train::grad_norm(store) == Approx(1.0).epsilon(1e-6));
  store.grad("layer.bias")[1] = std::numeric_limits<double>::quiet_NaN();
  CHECK_THROWS_WITH(train::clip_grad_norm(store, 1.0),
                    Catch::Contains("tensor 'layer.bias' [2] has gradient nan at element 1"));
}

TEST_CASE("AdamW and the norm are identical for 1 and several threads", "[train][optimizer]") {
  auto run = [](int threads) {
    ThreadPool pool(threads);
    train::ParamStore<float> store;
    store.add_segment("s", {{"w", {300, 97}}, {"b", {97}}});
    store.allocate();
    for (index_t i = 0; i < store.size(); ++i) {
      store.params()[i] = std::sin(0.37f * static_cast<float>(i));
      store.grads()[i] = std::cos(1.3f * static_cast<float>(i)) * 1e-3f;
    }
    std::vector<double> norms;
    for (std::uint64_t s = 1; s <= 3; ++s) {
      norms.push_back(train::clip_grad_norm(store, 0.01, pool));
      train::adamw_step(store, {}, 1e-3, s, pool);
    }
    return std::make_pair(norms, std::vector<float>(store.params(), store.params() + store.size()));
  };
  const auto one = run(1), many = run(2);
  CHECK(one.first == many.first);
  CHECK(one.second == many.second);
}

TEST_CASE("warmup + cosine schedule values", "[train][optimizer]") {
  const train::CosineSchedule s{1e-3, 1e-5, 10, 110};
  CHECK(s.lr(0) == Approx(1e-4).epsilon(1e-15));
  CHECK(s.lr(9) == Approx(1e-3).epsilon(1e-15));
  CHECK(s.lr(10) == Approx(1e-3).epsilon(1e-15));
  CHECK(s.lr(60) == Approx(1e-5 + (1e-3 - 1e-5) * 0.5).epsilon(1e-12));  // half-way: cos(pi/2) = 0
  CHECK(s.lr(35) == Approx(1e-5 + (1e-3 - 1e-5) * 0.5 * (1 + std::cos(3.141592653589793 * 0.25))).epsilon(1e-12));
  CHECK(s.lr(110) == 1e-5);
  CHECK(s.lr(1000) == 1e-5);
  const train::CosineSchedule bad{1e-3, 0, 20, 10};
  CHECK_THROWS_WITH(bad.lr(0), Catch::Contains("warmup 20 steps must not exceed the total 10"));
}
