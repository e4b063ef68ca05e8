#include <catch2/catch.hpp>

#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "flexsplat/image/plot.hpp"

using namespace flexsplat;

namespace {
bool is(const Tensor<std::uint8_t, 3>& img, index_t x, index_t y, image::Rgb8 c) {
  return img(y, x, 0) == c[0] && img(y, x, 1) == c[1] && img(y, x, 2) == c[2];
}
index_t count(const Tensor<std::uint8_t, 3>& img, image::Rgb8 c) {
  index_t n = 0;
  for (index_t y = 0; y < img.shape(0); ++y)
    for (index_t x = 0; x < img.shape(1); ++x) n += is(img, x, y, c);
  return n;
}
}  // namespace

TEST_CASE("draw_text draws the font's glyph pixel for pixel at scale 1", "[image][plot]") {
  Tensor<std::uint8_t, 3> img(Shape<3>{7, 10, 3}, std::uint8_t(0));
  image::draw_text(img.view(), 1, 1, "7", {255, 255, 255}, 1);
  const char* seven = "111001010010010";
  for (int r = 0; r < 5; ++r)
    for (int c = 0; c < 3; ++c) CHECK(is(img, 1 + c, 1 + r, {255, 255, 255}) == (seven[3 * r + c] == '1'));
  CHECK(count(img, {255, 255, 255}) == 7);
  CHECK(image::text_width("ab", 1) == 7);
}

TEST_CASE("plot_lines puts a rising series from the bottom left to the top right of the plot area", "[image][plot]") {
  image::PlotSeries s{"loss", {0, 1, 2, 3}, {1, 2, 3, 4}, {200, 0, 0}};
  image::PlotOptions o;
  o.width = 400, o.height = 300, o.title = "t";
  const auto img = image::plot_lines(std::span<const image::PlotSeries>(&s, 1), o);
  REQUIRE(img.shape(0) == 300);
  REQUIRE(img.shape(1) == 400);
  index_t lo_left = 0, hi_right = 0;
  for (index_t y = 0; y < 300; ++y)
    for (index_t x = 0; x < 400; ++x)
      if (is(img, x, y, {200, 0, 0})) {
        if (x < 120 && y > 200) ++lo_left;
        if (x > 300 && y < 100) ++hi_right;
      }
  CHECK(lo_left > 0);
  CHECK(hi_right > 0);
}

TEST_CASE("plot_lines on a log scale leaves out non-positive and non-finite values", "[image][plot]") {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  image::PlotSeries s{"x", {0, 1, 2, 3}, {0.0, -1.0, nan, 0.0}, {0, 0, 200}};
  image::PlotOptions o;
  o.log_y = true;
  const auto img = image::plot_lines(std::span<const image::PlotSeries>(&s, 1), o);
  index_t legend = 14 * 4;  // the legend swatch is the only ink of the series colour
  CHECK(count(img, {0, 0, 200}) == legend);
  image::PlotSeries bad{"bad", {0, 1}, {1}, {0, 0, 0}};
  CHECK_THROWS_WITH(image::plot_lines(std::span<const image::PlotSeries>(&bad, 1), o),
                    Catch::Contains("series 'bad' has 2 x and 1 y values"));
}

TEST_CASE("image_grid places each image at an integer zoom and draws NaN magenta", "[image][plot]") {
  Tensor<float, 3> a(Shape<3>{4, 4, 3}, 0.f), b(Shape<3>{4, 4, 1}, 1.f);
  a(1, 2, 0) = 1.f;
  b(0, 0, 0) = std::numeric_limits<float>::quiet_NaN();
  std::vector<image::GridCell> cells{{a.view(), "a"}, {b.view(), "b"}, {TensorView<const float, 3>(), "blank"}};
  const auto img = image::image_grid(cells, 2, 16);
  // zoom 4: cells 16 x 16, padding 6, label rows 16.
  CHECK(img.shape(1) == 2 * (16 + 6) + 6);
  CHECK(img.shape(0) == 2 * (16 + 16 + 6) + 6);
  CHECK(is(img, 6 + 4, 6 + 38 + 4, {255, 255, 255}));
  CHECK(is(img, 6 + 2 * 4, 6 + 1 * 4, {255, 0, 0}));
  CHECK(is(img, 6 + 2 * 4 + 3, 6 + 1 * 4 + 3, {255, 0, 0}));
  CHECK(is(img, 6, 6, {0, 0, 0}));
  CHECK(is(img, 6 + 22, 6, {255, 0, 255}));
  CHECK(is(img, 6 + 22 + 4, 6, {255, 255, 255}));
  CHECK_THROWS_WITH(image::image_grid({}, 2), Catch::Contains("0 cells"));
}
