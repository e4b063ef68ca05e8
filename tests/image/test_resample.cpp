#include <catch2/catch.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "flexsplat/image/resample.hpp"

using namespace flexsplat;

namespace {

std::vector<std::uint8_t> random_bytes(std::size_t n, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> d(0, 255);
  std::vector<std::uint8_t> v(n);
  for (auto& x : v) x = static_cast<std::uint8_t>(d(rng));
  return v;
}

template <class T>
std::vector<T> random_values(std::size_t n, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> d(0.0, 1.0);
  std::vector<T> v(n);
  for (auto& x : v) x = static_cast<T>(d(rng));
  return v;
}

// Keys cubic, a = -0.5, from its textbook definition (independent of the library's operation order).
double keys(double x) {
  x = std::abs(x);
  if (x < 1) return 1.5 * x * x * x - 2.5 * x * x + 1;
  if (x < 2) return -0.5 * x * x * x + 2.5 * x * x - 4 * x + 2;
  return 0;
}

// Normalised antialiased bicubic weights of one output sample, in double, straight from the definition:
// the kernel stretched by max(scale, 1) centred on the output sample's source position, restricted to the
// source samples whose centres lie within the support.
std::vector<double> reference_weights(int in_size, int out_size, int i, int& first) {
  const double scale = double(in_size) / out_size;
  const double stretch = std::max(scale, 1.0);
  const double center = (i + 0.5) * scale;
  const double support = 2.0 * stretch;
  first = std::max(0, int(center - support + 0.5));
  const int last = std::min(in_size, int(center + support + 0.5));
  std::vector<double> w;
  double sum = 0;
  for (int j = first; j < last; ++j) {
    w.push_back(keys((j + 0.5 - center) / stretch));
    sum += w.back();
  }
  for (auto& x : w) x /= sum;
  return w;
}

}  // namespace

// ------------------------------------------------------------------------------------------------ filter

TEST_CASE("keys cubic filter matches its textbook form and both references' operation orders", "[resample]") {
  for (double x = -2.5; x <= 2.5; x += 0.0625) {
    CHECK(keys_cubic_filter<double>(x) == Approx(keys(x)).margin(1e-15));
    CHECK(pillow_bicubic_filter(x) == Approx(keys(x)).margin(1e-15));
  }
  CHECK(keys_cubic_filter<double>(0.0) == 1.0);
  CHECK(keys_cubic_filter<double>(1.0) == 0.0);
  CHECK(keys_cubic_filter<double>(2.0) == 0.0);
  // Worked by hand: f(0.25) = 111/128, f(0.75) = 29/128, f(1.25) = -9/128.
  CHECK(pillow_bicubic_filter(0.25) == 0.8671875);
  CHECK(pillow_bicubic_filter(0.75) == 0.2265625);
  CHECK(pillow_bicubic_filter(1.25) == -0.0703125);
}

// ------------------------------------------------------------------------------------------------ Pillow

TEST_CASE("pillow coefficients: hand-computed 2x down and 2x up", "[resample][pillow]") {
  PillowAxisCoefficients c;
  // 4 -> 2: scale 2, support 4, output 0 centred at 1.0 reads f((x - 0.5) / 2) for x = 0..3.
  pillow_bicubic_coefficients(4, 0.0f, 4.0f, 2, c);
  REQUIRE(c.ksize == 9);
  REQUIRE(c.first[0] == 0);
  REQUIRE(c.count[0] == 4);
  const double sum = 2 * 0.8671875 + 0.2265625 - 0.0703125;
  CHECK(c.weights[0] == Approx(0.8671875 / sum).epsilon(1e-15));
  CHECK(c.weights[1] == Approx(0.8671875 / sum).epsilon(1e-15));
  CHECK(c.weights[2] == Approx(0.2265625 / sum).epsilon(1e-15));
  CHECK(c.weights[3] == Approx(-0.0703125 / sum).epsilon(1e-15));
  CHECK(c.fixed[3] == static_cast<std::int32_t>(-0.5 + (-0.0703125 / sum) * (1 << 22)));
  CHECK(c.first[1] == 0);
  CHECK(c.count[1] == 4);
  CHECK(c.weights[c.ksize + 1] == Approx(0.2265625 / sum).epsilon(1e-15));

  // 2 -> 4: scale 0.5, support 2; output 0 (centre 0.25) reads f(0.25), f(1.25); output 1 f(-0.25), f(0.75).
  pillow_bicubic_coefficients(2, 0.0f, 2.0f, 4, c);
  REQUIRE(c.ksize == 5);
  REQUIRE(c.count[0] == 2);
  CHECK(c.weights[0] == Approx(0.8671875 / 0.796875).epsilon(1e-15));
  CHECK(c.weights[1] == Approx(-0.0703125 / 0.796875).epsilon(1e-15));
  CHECK(c.weights[c.ksize] == Approx(0.8671875 / 1.09375).epsilon(1e-15));
  CHECK(c.weights[c.ksize + 1] == Approx(0.2265625 / 1.09375).epsilon(1e-15));
}

TEST_CASE("pillow coefficients sum to one (double) and to 2^22 within rounding (fixed point)", "[resample][pillow]") {
  PillowAxisCoefficients c;
  for (auto [in, out] : {std::pair{256, 518}, {320, 518}, {200, 322}, {1000, 37}, {7, 3}, {3, 7}, {518, 518}}) {
    pillow_bicubic_coefficients(in, 0.0f, float(in), out, c);
    for (int i = 0; i < out; ++i) {
      double s = 0;
      std::int64_t f = 0;
      for (int j = 0; j < c.count[i]; ++j) {
        s += c.weights[i * c.ksize + j];
        f += c.fixed[i * c.ksize + j];
      }
      CHECK(s == Approx(1.0).margin(1e-12));
      CHECK(std::abs(f - (std::int64_t(1) << 22)) <= c.count[i]);
      CHECK(c.first[i] >= 0);
      CHECK(c.first[i] + c.count[i] <= in);
      CHECK(c.count[i] <= c.ksize);
    }
  }
}

TEST_CASE("pillow resize: hand-computed 1-D cases", "[resample][pillow]") {
  // 4 -> 2 on [0, 255, 0, 0]: 255 * (111/128) / (242/128) = 116.96 -> 117; 255 * (29/242) = 30.56 -> 31.
  const std::vector<std::uint8_t> row{0, 255, 0, 0};
  CHECK(resize_pillow_bicubic(row, 4, 1, 1, 2, 1) == std::vector<std::uint8_t>{117, 31});
  // Same along the vertical axis.
  CHECK(resize_pillow_bicubic(row, 1, 4, 1, 1, 2) == std::vector<std::uint8_t>{117, 31});
  // 2 -> 4 on [100, 200]: 91.18, 120.71, 179.29, 208.82.
  const std::vector<std::uint8_t> two{100, 200};
  CHECK(resize_pillow_bicubic(two, 2, 1, 1, 4, 1) == std::vector<std::uint8_t>{91, 121, 179, 209});
  // Overshoot is clipped: [255, 0] -> 277.5 at the left, -22.5 at the right.
  const std::vector<std::uint8_t> edge{255, 0};
  const auto up = resize_pillow_bicubic(edge, 2, 1, 1, 4, 1);
  CHECK(up.front() == 255);
  CHECK(up.back() == 0);
}

TEST_CASE("pillow resize: identity size is an exact copy", "[resample][pillow]") {
  for (int ch : {1, 2, 3, 4}) {
    const auto img = random_bytes(13 * 7 * ch, 11 + ch);
    CHECK(resize_pillow_bicubic(img, 13, 7, ch, 13, 7) == img);  // no premultiplication round trip either
  }
}

TEST_CASE("pillow resize: a constant image stays constant", "[resample][pillow]") {
  for (auto [w, h, ow, oh] : {std::array{37, 23, 518, 322}, {320, 200, 518, 322}, {256, 256, 518, 518},
                              {150, 260, 294, 518}, {500, 40, 7, 3}}) {
    for (std::uint8_t v : {std::uint8_t(0), std::uint8_t(1), std::uint8_t(128), std::uint8_t(254), std::uint8_t(255)}) {
      const std::vector<std::uint8_t> img(std::size_t(w) * h * 3, v);
      const auto out = resize_pillow_bicubic(img, w, h, 3, ow, oh);
      REQUIRE(out.size() == std::size_t(ow) * oh * 3);
      const auto differing = std::count_if(out.begin(), out.end(), [&](std::uint8_t x) { return x != v; });
      CHECK(differing == 0);
    }
  }
  // RGBA with constant colour and alpha: premultiply / unpremultiply must give the same colour back.
  std::vector<std::uint8_t> rgba(20 * 10 * 4);
  for (std::size_t p = 0; p < rgba.size(); p += 4) {
    rgba[p] = 200;
    rgba[p + 1] = 100;
    rgba[p + 2] = 0;
    rgba[p + 3] = 255;
  }
  const auto out = resize_pillow_bicubic(rgba, 20, 10, 4, 33, 17);
  std::size_t differing = 0;
  for (std::size_t p = 0; p < out.size(); p += 4)
    differing += out[p] != 200 || out[p + 1] != 100 || out[p + 2] != 0 || out[p + 3] != 255;
  CHECK(differing == 0);
}

TEST_CASE("pillow resize: horizontal pass first, uint8 in between (separability)", "[resample][pillow]") {
  const int w = 41, h = 29, ow = 67, oh = 13;
  const auto img = random_bytes(std::size_t(w) * h * 3, 5);
  const auto both = resize_pillow_bicubic(img, w, h, 3, ow, oh);
  const auto horizontal = resize_pillow_bicubic(img, w, h, 3, ow, h);
  const auto then_vertical = resize_pillow_bicubic(horizontal, ow, h, 3, ow, oh);
  CHECK(both == then_vertical);
}

TEST_CASE("pillow resize: channels are independent without alpha", "[resample][pillow]") {
  const int w = 30, h = 22, ow = 17, oh = 40;
  const auto img = random_bytes(std::size_t(w) * h * 3, 9);
  const auto out = resize_pillow_bicubic(img, w, h, 3, ow, oh);
  for (int c = 0; c < 3; ++c) {
    std::vector<std::uint8_t> plane(std::size_t(w) * h);
    for (std::size_t p = 0; p < plane.size(); ++p) plane[p] = img[p * 3 + c];
    const auto one = resize_pillow_bicubic(plane, w, h, 1, ow, oh);
    for (std::size_t p = 0; p < one.size(); ++p) REQUIRE(one[p] == out[p * 3 + c]);
  }
}

TEST_CASE("pillow resize: fixed point is within one unit per pass of a double evaluation", "[resample][pillow]") {
  const int w = 61, h = 47, ow = 128, oh = 20;
  const auto img = random_bytes(std::size_t(w) * h, 21);
  const auto out = resize_pillow_bicubic(img, w, h, 1, ow, oh);
  PillowAxisCoefficients ch, cv;
  pillow_bicubic_coefficients(w, 0.0f, float(w), ow, ch);
  pillow_bicubic_coefficients(h, 0.0f, float(h), oh, cv);
  const auto round_clip = [](double v) { return std::clamp(std::floor(v + 0.5), 0.0, 255.0); };
  std::vector<double> temp(std::size_t(ow) * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < ow; ++x) {
      double s = 0;
      for (int j = 0; j < ch.count[x]; ++j) s += img[y * w + ch.first[x] + j] * ch.weights[x * ch.ksize + j];
      temp[y * ow + x] = round_clip(s);
    }
  int max_diff = 0;
  for (int y = 0; y < oh; ++y)
    for (int x = 0; x < ow; ++x) {
      double s = 0;
      for (int j = 0; j < cv.count[y]; ++j) s += temp[(cv.first[y] + j) * ow + x] * cv.weights[y * cv.ksize + j];
      max_diff = std::max(max_diff, std::abs(int(round_clip(s)) - int(out[y * ow + x])));
    }
  CHECK(max_diff <= 2);
}

TEST_CASE("pillow resize: RGBA is resampled premultiplied (transparent colour does not bleed)", "[resample][pillow]") {
  const int w = 16, h = 4;
  std::vector<std::uint8_t> rgba(std::size_t(w) * h * 4);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      std::uint8_t* p = &rgba[(std::size_t(y) * w + x) * 4];
      const bool left = x < w / 2;
      p[0] = 0;
      p[1] = left ? 255 : 0;  // green, but fully transparent
      p[2] = left ? 0 : 255;  // opaque blue
      p[3] = left ? 0 : 255;
    }
  const auto out = resize_pillow_bicubic(rgba, w, h, 4, 7, 3);
  bool saw_partial = false;
  for (std::size_t p = 0; p < out.size(); p += 4) {
    if (out[p + 3] == 0) continue;
    saw_partial = saw_partial || out[p + 3] < 255;
    CHECK(int(out[p + 1]) == 0);
    CHECK(int(out[p + 2]) == 255);
  }
  CHECK(saw_partial);
  // Premultiplication helpers, by hand: 200 * 128 / 255 = 100.39 -> 100; 100 * 255 / 128 = 199.2 -> 199.
  CHECK(pillow_muldiv255(200, 128) == 100);
  CHECK(pillow_unpremultiply(100, 128) == 199);
  CHECK(pillow_unpremultiply(77, 0) == 77);
  CHECK(pillow_unpremultiply(200, 100) == 255);
}

TEST_CASE("pillow resize: SIMD vertical pass equals the scalar path", "[resample][pillow][simd]") {
  const int w = 53, h = 91, ow = 45, oh = 518;
  const auto img = random_bytes(std::size_t(w) * h * 3, 77);
  std::vector<std::uint8_t> a(std::size_t(ow) * oh * 3), b(a.size());
  PillowResampleWorkspace ws;
  ws.use_simd = true;
  resize_pillow_bicubic(img.data(), w, h, 3, a.data(), ow, oh, ws);
  ws.use_simd = false;
  resize_pillow_bicubic(img.data(), w, h, 3, b.data(), ow, oh, ws);
  CHECK(a == b);
  // Vertical-only path (no horizontal pass) too.
  std::vector<std::uint8_t> c(std::size_t(w) * 17 * 3), d(c.size());
  ws.use_simd = true;
  resize_pillow_bicubic(img.data(), w, h, 3, c.data(), w, 17, ws);
  ws.use_simd = false;
  resize_pillow_bicubic(img.data(), w, h, 3, d.data(), w, 17, ws);
  CHECK(c == d);
}

TEST_CASE("pillow resize: bad input is a clear error", "[resample][pillow][errors]") {
  const std::vector<std::uint8_t> img(12, 0);
  CHECK_THROWS_WITH(resize_pillow_bicubic(img, 2, 2, 3, 0, 5), Catch::Contains("height and width must be > 0"));
  CHECK_THROWS_WITH(resize_pillow_bicubic(img, 2, 2, 5, 3, 3), Catch::Contains("does not hold"));
  CHECK_THROWS_WITH(resize_pillow_bicubic(img, 3, 3, 3, 3, 3), Catch::Contains("does not hold a 3x3x3 image"));
  std::vector<std::uint8_t> out(100);
  PillowResampleWorkspace ws;
  CHECK_THROWS_WITH(resize_pillow_bicubic(img.data(), 2, 2, 6, out.data(), 2, 2, ws), Catch::Contains("6 channels"));
}

// ------------------------------------------------------------------------------------------------ PyTorch AA

TEST_CASE("antialias weights: hand-computed 2x down and 2x up, sum to one", "[resample][antialias]") {
  AntialiasAxisWeights<double> w;
  bicubic_antialias_weights<double>(4, 2, antialias_axis_scale<double>(4, 2), w);
  REQUIRE(w.max_taps == 9);
  REQUIRE(w.first[0] == 0);
  REQUIRE(w.count[0] == 4);
  const double sum = 2 * 0.8671875 + 0.2265625 - 0.0703125;
  CHECK(w.weights[0] == Approx(0.8671875 / sum).epsilon(1e-15));
  CHECK(w.weights[2] == Approx(0.2265625 / sum).epsilon(1e-15));
  CHECK(w.weights[3] == Approx(-0.0703125 / sum).epsilon(1e-15));
  bicubic_antialias_weights<double>(2, 4, antialias_axis_scale<double>(2, 4), w);
  REQUIRE(w.max_taps == 5);
  CHECK(w.weights[0] == Approx(0.8671875 / 0.796875).epsilon(1e-15));
  CHECK(w.weights[1] == Approx(-0.0703125 / 0.796875).epsilon(1e-15));

  AntialiasAxisWeights<float> wf;
  for (auto [in, out] : {std::pair{37, 16}, {16, 37}, {37, 37}, {518, 37}, {5, 3}, {3, 100}}) {
    bicubic_antialias_weights<float>(in, out, antialias_axis_scale<float>(in, out), wf);
    for (index_t i = 0; i < out; ++i) {
      double s = 0;
      for (index_t j = 0; j < wf.count[i]; ++j) s += wf.weights[i * wf.max_taps + j];
      CHECK(s == Approx(1.0).margin(1e-6));
      int first = 0;
      const auto ref = reference_weights(int(in), int(out), int(i), first);
      REQUIRE(wf.first[i] == first);
      REQUIRE(wf.count[i] == index_t(ref.size()));
      for (std::size_t j = 0; j < ref.size(); ++j) CHECK(wf.weights[i * wf.max_taps + j] == Approx(ref[j]).margin(1e-6));
    }
  }
}

TEST_CASE("antialias interpolate: identity, constant, hand 1-D case", "[resample][antialias]") {
  const auto x = random_values<float>(3 * 5 * 7, 1);
  std::vector<float> y(x.size());
  AntialiasWorkspace<float> ws;
  interpolate_bicubic_antialias<float>(x.data(), 3, 5, 7, y.data(), 5, 7, ws);
  CHECK(x == y);

  for (auto [h, w, oh, ow] : {std::array<index_t, 4>{37, 37, 16, 22}, {16, 16, 37, 37}, {10, 3, 4, 9}}) {
    std::vector<double> c(std::size_t(2 * h * w), 0.625);
    std::vector<double> out(std::size_t(2 * oh * ow));
    AntialiasWorkspace<double> wsd;
    interpolate_bicubic_antialias<double>(c.data(), 2, h, w, out.data(), oh, ow, wsd);
    for (double v : out) REQUIRE(v == Approx(0.625).epsilon(1e-14));
  }

  // [0, 1, 0, 0] from 4 to 2 along width: 111/242 and 29/242.
  const std::vector<double> row{0, 1, 0, 0};
  std::vector<double> two(2);
  AntialiasWorkspace<double> wsd;
  interpolate_bicubic_antialias<double>(row.data(), 1, 1, 4, two.data(), 1, 2, wsd);
  CHECK(two[0] == Approx(111.0 / 242.0).epsilon(1e-15));
  CHECK(two[1] == Approx(29.0 / 242.0).epsilon(1e-15));
  // Same along height.
  interpolate_bicubic_antialias<double>(row.data(), 1, 4, 1, two.data(), 2, 1, wsd);
  CHECK(two[0] == Approx(111.0 / 242.0).epsilon(1e-15));
}

TEST_CASE("antialias interpolate: matches a direct double-precision 2-D evaluation", "[resample][antialias]") {
  for (auto [h, w, oh, ow] : {std::array<int, 4>{37, 37, 16, 22}, {16, 16, 37, 29}, {37, 37, 74, 10}}) {
    const int C = 3;
    const auto x = random_values<double>(std::size_t(C * h * w), 7);
    std::vector<double> y(std::size_t(C * oh * ow));
    AntialiasWorkspace<double> ws;
    interpolate_bicubic_antialias<double>(x.data(), C, h, w, y.data(), oh, ow, ws);
    std::vector<float> xf(x.begin(), x.end()), yf(y.size());
    AntialiasWorkspace<float> wsf;
    interpolate_bicubic_antialias<float>(xf.data(), C, h, w, yf.data(), oh, ow, wsf);
    double max_err = 0, max_err_f = 0;
    for (int c = 0; c < C; ++c)
      for (int i = 0; i < oh; ++i) {
        int fy = 0;
        const auto wy = reference_weights(h, oh, i, fy);
        for (int j = 0; j < ow; ++j) {
          int fx = 0;
          const auto wx = reference_weights(w, ow, j, fx);
          double s = 0;
          for (std::size_t a = 0; a < wy.size(); ++a)
            for (std::size_t b = 0; b < wx.size(); ++b)
              s += wy[a] * wx[b] * x[(std::size_t(c) * h + fy + a) * w + fx + b];
          const std::size_t o = (std::size_t(c) * oh + i) * ow + j;
          max_err = std::max(max_err, std::abs(y[o] - s));
          max_err_f = std::max(max_err_f, std::abs(double(yf[o]) - s));
        }
      }
    CHECK(max_err < 1e-13);
    CHECK(max_err_f < 2e-6);
  }
}

TEST_CASE("antialias interpolate: width pass then height pass (separability)", "[resample][antialias]") {
  const index_t C = 4, h = 23, w = 31, oh = 50, ow = 12;
  const auto x = random_values<float>(std::size_t(C * h * w), 3);
  std::vector<float> both(std::size_t(C * oh * ow)), wide(std::size_t(C * h * ow)), two(both.size());
  AntialiasWorkspace<float> ws;
  interpolate_bicubic_antialias<float>(x.data(), C, h, w, both.data(), oh, ow, ws);
  interpolate_bicubic_antialias<float>(x.data(), C, h, w, wide.data(), h, ow, ws);
  interpolate_bicubic_antialias<float>(wide.data(), C, h, ow, two.data(), oh, ow, ws);
  CHECK(both == two);
}

TEST_CASE("antialias interpolate: SIMD height pass equals the scalar path", "[resample][antialias][simd]") {
  const index_t C = 8, h = 37, w = 37, oh = 23, ow = 41;
  const auto x = random_values<float>(std::size_t(C * h * w), 4);
  std::vector<float> a(std::size_t(C * oh * ow)), b(a.size());
  AntialiasWorkspace<float> ws;
  ws.use_simd = true;
  interpolate_bicubic_antialias<float>(x.data(), C, h, w, a.data(), oh, ow, ws);
  ws.use_simd = false;
  interpolate_bicubic_antialias<float>(x.data(), C, h, w, b.data(), oh, ow, ws);
  CHECK(a == b);
}

TEST_CASE("antialias interpolate: tensor overload, scale factors and errors", "[resample][antialias]") {
  Tensor<float, 3> t(Shape<3>{2, 6, 6});
  for (index_t i = 0; i < t.size(); ++i) t.data()[i] = float(i % 7) / 7.0f;
  const auto out = interpolate_bicubic_antialias<float>(t.view(), 3, 9);
  CHECK(out.shape() == Shape<3>{2, 3, 9});
  std::vector<float> raw(2 * 3 * 9);
  AntialiasWorkspace<float> ws;
  interpolate_bicubic_antialias<float>(t.data(), 2, 6, 6, raw.data(), 3, 9, ws);
  CHECK(std::vector<float>(out.data(), out.data() + out.size()) == raw);
  // scale_factor = 0.5 / 1.5 gives the same scales as the sizes here.
  std::vector<float> scaled(raw.size());
  interpolate_bicubic_antialias<float>(t.data(), 2, 6, 6, scaled.data(), 3, 9, ws, {0.5, 1.5});
  CHECK(scaled == raw);
  CHECK_THROWS_WITH(interpolate_bicubic_antialias<float>(t.view(), 0, 4), Catch::Contains("must be positive"));
  CHECK_THROWS_AS(interpolate_bicubic_antialias<float>(t.data(), 0, 6, 6, raw.data(), 3, 9, ws), Error);
}
