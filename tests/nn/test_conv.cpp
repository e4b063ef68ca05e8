#include <catch2/catch.hpp>

#include "flexsplat/nn/conv.hpp"
#include "flexsplat/testing/gradcheck.hpp"
#include "nn_test_util.hpp"

using namespace flexsplat;

namespace {
// Direct definitions of both convolutions, the reference for the im2col kernels.
std::vector<double> direct_conv(const std::vector<double>& x, const std::vector<double>& w, const std::vector<double>& b,
                                const nn::Conv2dShape& s) {
  const index_t oh = s.conv_out_h(), ow = s.conv_out_w();
  std::vector<double> y(s.batch * s.out_channels * oh * ow);
  for (index_t n = 0; n < s.batch; ++n)
    for (index_t o = 0; o < s.out_channels; ++o)
      for (index_t oy = 0; oy < oh; ++oy)
        for (index_t ox = 0; ox < ow; ++ox) {
          double acc = b[o];
          for (index_t c = 0; c < s.in_channels; ++c)
            for (index_t i = 0; i < s.kernel_h; ++i)
              for (index_t j = 0; j < s.kernel_w; ++j) {
                const index_t yy = oy * s.stride - s.padding + i, xx = ox * s.stride - s.padding + j;
                if (yy < 0 || yy >= s.in_h || xx < 0 || xx >= s.in_w) continue;
                acc += w[((o * s.in_channels + c) * s.kernel_h + i) * s.kernel_w + j] *
                       x[((n * s.in_channels + c) * s.in_h + yy) * s.in_w + xx];
              }
          y[((n * s.out_channels + o) * oh + oy) * ow + ox] = acc;
        }
  return y;
}

// The float64 gradient check of conv2d_forward / conv2d_backward with the given scratch, into x, weight and bias.
testing::GradCheckResult conv2d_gradient_check(std::vector<double>& x, std::vector<double>& w, std::vector<double>& b,
                                               const nn::Conv2dShape& s, std::vector<double>& scratch) {
  std::vector<double> dx(x.size()), dw(w.size()), db(b.size());
  return testing::check_gradients(
      {{"x", x, dx}, {"weight", w, dw}, {"bias", b, db}}, s.batch * s.out_channels * s.conv_out_h() * s.conv_out_w(),
      [&](std::span<double> o) { nn::conv2d_forward(o.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch)); },
      [&](std::span<const double> d) {
        nn::conv2d_backward(dx.data(), dw.data(), db.data(), d.data(), x.data(), w.data(), s, std::span<double>(scratch));
      });
}

std::vector<double> direct_conv_transpose(const std::vector<double>& x, const std::vector<double>& w,
                                          const std::vector<double>& b, const nn::Conv2dShape& s) {
  const index_t oh = s.transposed_out_h(), ow = s.transposed_out_w();
  std::vector<double> y(s.batch * s.out_channels * oh * ow);
  for (index_t n = 0; n < s.batch; ++n)
    for (index_t o = 0; o < s.out_channels; ++o)
      for (index_t p = 0; p < oh * ow; ++p) y[(n * s.out_channels + o) * oh * ow + p] = b[o];
  for (index_t n = 0; n < s.batch; ++n)
    for (index_t c = 0; c < s.in_channels; ++c)
      for (index_t iy = 0; iy < s.in_h; ++iy)
        for (index_t ix = 0; ix < s.in_w; ++ix)
          for (index_t o = 0; o < s.out_channels; ++o)
            for (index_t i = 0; i < s.kernel_h; ++i)
              for (index_t j = 0; j < s.kernel_w; ++j) {
                const index_t yy = iy * s.stride - s.padding + i, xx = ix * s.stride - s.padding + j;
                if (yy < 0 || yy >= oh || xx < 0 || xx >= ow) continue;
                y[((n * s.out_channels + o) * oh + yy) * ow + xx] +=
                    w[((c * s.out_channels + o) * s.kernel_h + i) * s.kernel_w + j] *
                    x[((n * s.in_channels + c) * s.in_h + iy) * s.in_w + ix];
              }
  return y;
}
}  // namespace

TEST_CASE("conv2d matches the direct definition and passes the float64 gradient check", "[nn][conv]") {
  for (auto [k, stride, pad] : {std::tuple{3, 1, 1}, std::tuple{3, 2, 1}, std::tuple{1, 1, 0}, std::tuple{4, 4, 0}}) {
    nn::Conv2dShape s{2, 3, 4, 9, 8, k, k, stride, pad};
    auto x = random_vector(2 * 3 * 9 * 8, 31), w = random_vector(4 * 3 * k * k, 32), b = random_vector(4, 33);
    std::vector<double> y(2 * 4 * s.conv_out_h() * s.conv_out_w()), scratch(nn::conv2d_scratch_size(s));
    nn::conv2d_forward(y.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch));
    auto expect = direct_conv(x, w, b, s);
    for (std::size_t i = 0; i < y.size(); ++i) REQUIRE(y[i] == Approx(expect[i]).margin(1e-12));
    const auto result = conv2d_gradient_check(x, w, b, s, scratch);
    INFO("kernel " << k << " stride " << stride << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("conv2d's input gradient as a correlation (stride 1, C_out <= C_in) passes the float64 gradient check and "
          "equals the column path in bands of any height",
          "[nn][conv]") {
  for (auto [k, pad] : {std::pair{3, 1}, std::pair{5, 2}, std::pair{3, 0}, std::pair{5, 1}, std::pair{2, 1}, std::pair{2, 0}}) {
    const nn::Conv2dShape s{2, 4, 3, 9, 7, k, k, 1, pad};
    INFO("kernel " << k << " padding " << pad);
    REQUIRE(nn::detail::conv2d_use_correlate(s, nn::conv2d_scratch_size(s)));
    auto x = random_vector(2 * 4 * 9 * 7, 91), w = random_vector(3 * 4 * k * k, 92), b = random_vector(3, 93);
    std::vector<double> y(2 * 3 * s.conv_out_h() * s.conv_out_w()), scratch(nn::conv2d_scratch_size(s));
    const auto result = conv2d_gradient_check(x, w, b, s, scratch);
    INFO(result.summary());
    CHECK(result.ok());
    const auto dy = random_vector(y.size(), 94);
    std::vector<double> columns(x.size(), 0.5), big(nn::conv2d_scratch_size(s));
    nn::detail::conv2d_backward_input_columns(columns.data(), dy.data(), w.data(), s, std::span<double>(big));
    for (index_t rows : {index_t(1), index_t(2), s.in_h}) {
      INFO("rows per band " << rows);
      // One element short of the next row: the band height is what the scratch holds.
      std::vector<double> band(nn::conv2d_correlate_scratch_size(s, rows + 1) - 1), dx1(x.size(), 0.5);
      CHECK(nn::detail::conv2d_correlate_band_rows(s, band.size()) == std::min(rows, s.in_h));
      nn::detail::conv2d_backward_input_correlate(dx1.data(), dy.data(), w.data(), s, std::span<double>(band));
      for (std::size_t i = 0; i < x.size(); ++i) REQUIRE(dx1[i] == Approx(columns[i]).margin(1e-12));
    }
    std::vector<double> short_scratch(nn::conv2d_correlate_scratch_size(s, 1) - 1), dx1(x.size());
    CHECK_FALSE(nn::detail::conv2d_use_correlate(s, short_scratch.size()));
    CHECK_THROWS_WITH(nn::detail::conv2d_backward_input_correlate(dx1.data(), dy.data(), w.data(), s,
                                                                  std::span<double>(short_scratch)),
                      Catch::Contains("conv2d backward (correlated): needs stride 1"));
  }
  // More output than input channels, a stride, a 1 x 1 kernel, padding as wide as it or a map of fewer than 8 C_out
  // pixels (batch included) keep the column path.
  for (const nn::Conv2dShape& s : {nn::Conv2dShape{1, 3, 4, 9, 7, 3, 3, 1, 1}, nn::Conv2dShape{1, 4, 3, 9, 7, 3, 3, 2, 1},
                                   nn::Conv2dShape{1, 4, 3, 9, 7, 1, 1, 1, 0}, nn::Conv2dShape{1, 4, 3, 9, 7, 3, 3, 1, 3},
                                   nn::Conv2dShape{3, 64, 32, 4, 5, 3, 3, 1, 1}})
    CHECK_FALSE(nn::detail::conv2d_use_correlate(s, std::size_t(1) << 20));
}

TEST_CASE("conv_transpose2d matches the direct definition and passes the float64 gradient check", "[nn][conv]") {
  for (auto [k, stride, pad, outpad] : {std::tuple{4, 4, 0, 0}, std::tuple{2, 2, 0, 0}, std::tuple{3, 2, 1, 1}}) {
    nn::Conv2dShape s{2, 3, 2, 4, 5, k, k, stride, pad, outpad};
    auto x = random_vector(2 * 3 * 4 * 5, 41), w = random_vector(3 * 2 * k * k, 42), b = random_vector(2, 43);
    std::vector<double> y(2 * 2 * s.transposed_out_h() * s.transposed_out_w()), scratch(nn::conv_transpose2d_scratch_size(s));
    nn::conv_transpose2d_forward(y.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch));
    auto expect = direct_conv_transpose(x, w, b, s);
    for (std::size_t i = 0; i < y.size(); ++i) REQUIRE(y[i] == Approx(expect[i]).margin(1e-12));
    std::vector<double> dx(x.size()), dw(w.size()), db(b.size());
    auto result = testing::check_gradients(
        {{"x", x, dx}, {"weight", w, dw}, {"bias", b, db}}, y.size(),
        [&](std::span<double> o) {
          nn::conv_transpose2d_forward(o.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch));
        },
        [&](std::span<const double> d) {
          nn::conv_transpose2d_backward(dx.data(), dw.data(), db.data(), d.data(), x.data(), w.data(), s,
                                        std::span<double>(scratch));
        });
    INFO("kernel " << k << " stride " << stride << ": " << result.summary());
    CHECK(result.ok());
  }
}

TEST_CASE("zero-size feature maps are a clear error", "[nn][conv]") {
  nn::Conv2dShape s{1, 3, 4, 0, 8, 3, 3, 1, 1};
  std::vector<double> buf(64);
  CHECK_THROWS_WITH(nn::conv2d_forward(buf.data(), buf.data(), buf.data(), (const double*)nullptr, s, std::span<double>(buf)),
                    Catch::Contains("0x8 (zero-size)"));
}

TEST_CASE("conv2d in bands of output rows equals the whole-image product, and a scratch below one row is an error",
          "[nn][conv]") {
  for (auto [k, stride, pad] : {std::tuple{3, 1, 1}, std::tuple{3, 2, 1}, std::tuple{5, 2, 2}, std::tuple{4, 4, 0}}) {
    const nn::Conv2dShape s{2, 3, 4, 11, 6, k, k, stride, pad};
    INFO("kernel " << k << " stride " << stride << " padding " << pad);
    auto x = random_vector(2 * 3 * 11 * 6, 51), w = random_vector(4 * 3 * k * k, 52), b = random_vector(4, 53);
    auto dy = random_vector(2 * 4 * s.conv_out_h() * s.conv_out_w(), 54);
    const auto full = static_cast<std::size_t>(nn::conv2d_scratch_size(s)),
               row = static_cast<std::size_t>(nn::conv2d_row_scratch_size(s));
    auto run = [&](std::size_t scratch_size, std::vector<double>& y, std::vector<double>& dx, std::vector<double>& dw,
                   std::vector<double>& db) {
      std::vector<double> scratch(scratch_size);
      y.assign(dy.size(), 0.0), dx.assign(x.size(), 0.5), dw.assign(w.size(), 0.25), db.assign(b.size(), 0.125);
      nn::conv2d_forward(y.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch));
      nn::conv2d_backward(dx.data(), dw.data(), db.data(), dy.data(), x.data(), w.data(), s, std::span<double>(scratch));
    };
    std::vector<double> y0, dx0, dw0, db0;
    run(full, y0, dx0, dw0, db0);
    for (std::size_t scratch_size : {row, 2 * row + 1}) {
      std::vector<double> y1, dx1, dw1, db1;
      run(scratch_size, y1, dx1, dw1, db1);
      // The same sums up to rounding: a GEMM over fewer columns may order a dot product's terms otherwise, and dx, dw
      // add the bands' parts in another order. The bias gradient does not depend on the bands.
      CHECK(db1 == db0);
      for (std::size_t i = 0; i < y0.size(); ++i) REQUIRE(y1[i] == Approx(y0[i]).margin(1e-12));
      for (std::size_t i = 0; i < dx0.size(); ++i) REQUIRE(dx1[i] == Approx(dx0[i]).margin(1e-12));
      for (std::size_t i = 0; i < dw0.size(); ++i) REQUIRE(dw1[i] == Approx(dw0[i]).margin(1e-12));
    }
    std::vector<double> y(dy.size()), scratch(row - 1);
    CHECK_THROWS_WITH(nn::conv2d_forward(y.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch)),
                      Catch::Contains("cannot hold one output row's columns"));
  }
}

TEST_CASE("conv2d's shifted path (one GEMM per kernel tap) matches the direct definition in bands of any height",
          "[nn][conv]") {
  for (auto [kh, kw, pad] : {std::tuple{3, 3, 1}, std::tuple{5, 5, 2}, std::tuple{3, 3, 0}, std::tuple{2, 4, 1}}) {
    const nn::Conv2dShape s{1, 3, 4, 9, 7, kh, kw, 1, pad};
    INFO("kernel " << kh << "x" << kw << " padding " << pad);
    const auto x = random_vector(3 * 9 * 7, 61), w = random_vector(4 * 3 * kh * kw, 62), b = random_vector(4, 63);
    const std::vector<double> zero(4, 0.0);
    const index_t oh = s.conv_out_h();
    for (index_t rows : {index_t(1), index_t(2), oh}) {
      for (const double* bias : {b.data(), static_cast<const double*>(nullptr)}) {
        INFO("rows per band " << rows << (bias ? ", bias" : ", no bias"));
        // One element short of the next row: the band height is what the scratch holds.
        std::vector<double> scratch(nn::conv2d_shifted_scratch_size(s, rows + 1) - 1), y(4 * oh * s.conv_out_w(), -7.0);
        CHECK(nn::detail::conv2d_shifted_band_rows(s, scratch.size()) == std::min(rows, oh));
        nn::detail::conv2d_forward_shifted(y.data(), x.data(), w.data(), bias, s, std::span<double>(scratch));
        const auto ref = direct_conv(x, w, bias ? b : zero, s);
        for (std::size_t i = 0; i < ref.size(); ++i) REQUIRE(y[i] == Approx(ref[i]).margin(1e-12));
      }
    }
    std::vector<double> y(4 * oh * s.conv_out_w()), scratch(nn::conv2d_shifted_scratch_size(s, 1) - 1);
    CHECK_THROWS_WITH(
        nn::detail::conv2d_forward_shifted(y.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch)),
        Catch::Contains("conv2d (shifted): needs stride 1 and"));
  }
}

TEST_CASE("conv2d takes the shifted path for large stride-1 maps when the scratch holds a row of it, batch included",
          "[nn][conv]") {
  // A map just at the threshold: the smallest square with that many pixels.
  index_t side = 1;
  while (side * side < std::max<index_t>(nn::detail::conv2d_shifted_min_pixels, 1)) ++side;
  const nn::Conv2dShape s{2, 2, 3, side, side, 3, 3, 1, 1}, strided{2, 2, 3, side, side, 3, 3, 2, 1};
  CHECK(nn::detail::conv2d_use_shifted(s, nn::conv2d_shifted_scratch_size(s, 1)));
  CHECK_FALSE(nn::detail::conv2d_use_shifted(s, nn::conv2d_shifted_scratch_size(s, 1) - 1));
  CHECK_FALSE(nn::detail::conv2d_use_shifted(strided, nn::conv2d_shifted_scratch_size(strided, side)));
  if (side > 1) {
    const nn::Conv2dShape small{2, 2, 3, side - 1, side - 1, 3, 3, 1, 1};
    CHECK_FALSE(nn::detail::conv2d_use_shifted(small, nn::conv2d_shifted_scratch_size(small, side)));
  }
  const auto x = random_vector(2 * 2 * side * side, 71), w = random_vector(3 * 2 * 9, 72), b = random_vector(3, 73);
  std::vector<double> y(2 * 3 * side * side), scratch(nn::conv2d_shifted_scratch_size(s, 2));
  nn::conv2d_forward(y.data(), x.data(), w.data(), b.data(), s, std::span<double>(scratch));
  const auto ref = direct_conv(x, w, b, s);
  for (std::size_t i = 0; i < ref.size(); ++i) REQUIRE(y[i] == Approx(ref[i]).margin(1e-12));
}

TEST_CASE("conv2d_forward_scratch_size: the same output as the full column scratch, from no more memory",
          "[nn][conv]") {
  index_t side = 1;
  while (side * side < std::max<index_t>(nn::detail::conv2d_shifted_min_pixels, 1)) ++side;
  // few input channels (the column matrix is the smaller), many (the shifted band is), strided, 1 x 1, a small map
  const nn::Conv2dShape shapes[] = {{2, 1, 6, side, side + 3, 3, 3, 1, 1}, {1, 8, 8, side, side, 3, 3, 1, 1},
                                    {2, 4, 5, side, side, 3, 3, 2, 1},     {2, 4, 5, side, side, 1, 1, 1, 0},
                                    {2, 4, 5, 9, 7, 3, 3, 1, 1}};
  for (const auto& s : shapes) {
    INFO(s.in_channels << "->" << s.out_channels << " " << s.in_h << "x" << s.in_w << " k" << s.kernel_h << " s"
                       << s.stride);
    const index_t full = nn::conv2d_scratch_size(s), least = nn::conv2d_forward_scratch_size(s);
    CHECK(least <= full);
    const auto x = random_vector(s.batch * s.in_channels * s.in_h * s.in_w, 81);
    const auto w = random_vector(s.out_channels * s.in_channels * s.kernel_h * s.kernel_w, 82);
    const auto b = random_vector(s.out_channels, 83);
    std::vector<double> a(s.batch * s.out_channels * s.conv_out_h() * s.conv_out_w()), c(a.size());
    std::vector<double> big(static_cast<std::size_t>(full)), small(static_cast<std::size_t>(least));
    nn::conv2d_forward(a.data(), x.data(), w.data(), b.data(), s, std::span<double>(big));
    nn::conv2d_forward(c.data(), x.data(), w.data(), b.data(), s, std::span<double>(small));
    CHECK(a == c);
  }
  const nn::Conv2dShape wide{1, 8, 8, side, side, 3, 3, 1, 1};
  CHECK(nn::conv2d_forward_scratch_size(wide) < nn::conv2d_scratch_size(wide));
}
