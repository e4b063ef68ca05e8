#pragma once
// Pictures a person would rather look at than read: line charts (training curves) and labelled image grids, drawn
// into 8-bit RGB images with a built-in 3x5 bitmap font, so no plotting or font dependency is needed.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace image {

using Rgb8 = std::array<std::uint8_t, 3>;

namespace detail {
// Rows top to bottom, '1' = ink; lower-case letters are drawn as upper case, unknown characters as '?'.
inline const char* glyph_rows(char c) {
  if (c >= 'a' && c <= 'z') c = static_cast<char>(c - 'a' + 'A');
  switch (c) {
    case '0': return "111101101101111";
    case '1': return "010110010010111";
    case '2': return "111001111100111";
    case '3': return "111001111001111";
    case '4': return "101101111001001";
    case '5': return "111100111001111";
    case '6': return "111100111101111";
    case '7': return "111001010010010";
    case '8': return "111101111101111";
    case '9': return "111101111001111";
    case 'A': return "010101111101101";
    case 'B': return "110101110101110";
    case 'C': return "011100100100011";
    case 'D': return "110101101101110";
    case 'E': return "111100110100111";
    case 'F': return "111100110100100";
    case 'G': return "011100101101011";
    case 'H': return "101101111101101";
    case 'I': return "111010010010111";
    case 'J': return "001001001101010";
    case 'K': return "101101110101101";
    case 'L': return "100100100100111";
    case 'M': return "101111111101101";
    case 'N': return "110101101101101";
    case 'O': return "010101101101010";
    case 'P': return "110101110100100";
    case 'Q': return "010101101110011";
    case 'R': return "110101110101101";
    case 'S': return "011100010001110";
    case 'T': return "111010010010010";
    case 'U': return "101101101101111";
    case 'V': return "101101101101010";
    case 'W': return "101101111111101";
    case 'X': return "101101010101101";
    case 'Y': return "101101010010010";
    case 'Z': return "111001010100111";
    case '.': return "000000000000010";
    case ',': return "000000000010100";
    case '-': return "000000111000000";
    case '+': return "000010111010000";
    case ':': return "000010000010000";
    case '/': return "001001010100100";
    case '(': return "001010010010001";
    case ')': return "100010010010100";
    case '[': return "011010010010011";
    case ']': return "110010010010110";
    case '%': return "101001010100101";
    case '_': return "000000000000111";
    case '=': return "000111000111000";
    case '<': return "001010100010001";
    case '>': return "100010001010100";
    case '#': return "101111101111101";
    case ' ': return "000000000000000";
    default: return "111001011000010";
  }
}

inline void put(TensorView<std::uint8_t, 3> img, long x, long y, Rgb8 c) {
  if (x < 0 || y < 0 || y >= img.shape(0) || x >= img.shape(1)) return;
  for (index_t k = 0; k < 3; ++k) img(static_cast<index_t>(y), static_cast<index_t>(x), k) = c[static_cast<std::size_t>(k)];
}

inline void fill_rect(TensorView<std::uint8_t, 3> img, long x0, long y0, long x1, long y1, Rgb8 c) {
  for (long y = y0; y < y1; ++y)
    for (long x = x0; x < x1; ++x) put(img, x, y, c);
}

inline void line(TensorView<std::uint8_t, 3> img, double x0, double y0, double x1, double y1, Rgb8 c, int width) {
  const double len = std::max(std::abs(x1 - x0), std::abs(y1 - y0));
  const int steps = static_cast<int>(std::ceil(len)) + 1;
  for (int s = 0; s <= steps; ++s) {
    const double t = static_cast<double>(s) / steps;
    const long x = std::lround(x0 + t * (x1 - x0)), y = std::lround(y0 + t * (y1 - y0));
    for (int dy = 0; dy < width; ++dy)
      for (int dx = 0; dx < width; ++dx) put(img, x + dx - width / 2, y + dy - width / 2, c);
  }
}

// Tick positions at 1, 2 or 5 times a power of ten, about `target` of them across [lo, hi].
inline std::vector<double> nice_ticks(double lo, double hi, int target) {
  const double raw = (hi - lo) / std::max(target, 1);
  const double p = std::pow(10.0, std::floor(std::log10(raw)));
  double step = p;
  for (double m : {1.0, 2.0, 5.0, 10.0})
    if (m * p >= raw) {
      step = m * p;
      break;
    }
  std::vector<double> t;
  for (double v = std::ceil(lo / step) * step; v <= hi + 1e-9 * step; v += step) t.push_back(std::abs(v) < 1e-12 * step ? 0 : v);
  return t;
}

inline std::string tick_label(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3g", v);
  return buf;
}
}  // namespace detail

// Text in the built-in font: each font pixel becomes scale x scale pixels; glyphs advance 4 * scale.
inline void draw_text(TensorView<std::uint8_t, 3> img, long x, long y, std::string_view text, Rgb8 color, int scale = 2) {
  for (char ch : text) {
    const char* rows = detail::glyph_rows(ch);
    for (int r = 0; r < 5; ++r)
      for (int col = 0; col < 3; ++col)
        if (rows[3 * r + col] == '1') detail::fill_rect(img, x + col * scale, y + r * scale, x + (col + 1) * scale, y + (r + 1) * scale, color);
    x += 4 * scale;
  }
}

inline long text_width(std::string_view text, int scale = 2) { return static_cast<long>(text.size()) * 4 * scale - scale; }

struct PlotSeries {
  std::string name;
  std::vector<double> x, y;
  Rgb8 color{31, 119, 180};
};

struct PlotOptions {
  int width = 720, height = 400;
  std::string title, x_label, y_label;
  bool log_y = false;  // non-positive values are left out
};

// A line chart of the series, with axes, ticks, grid, title and legend.
inline Tensor<std::uint8_t, 3> plot_lines(std::span<const PlotSeries> series, const PlotOptions& o) {
  require(o.width >= 160 && o.height >= 120 && o.width <= 8192 && o.height <= 8192, "plot: size ", o.width, " x ",
          o.height, " outside [160, 8192] x [120, 8192]");
  Tensor<std::uint8_t, 3> img(Shape<3>{o.height, o.width, 3}, std::uint8_t(255));
  auto v = img.view();
  const Rgb8 ink{40, 40, 40}, grid{225, 225, 225};
  const long left = 70, right = o.width - 16, top = 34, bottom = o.height - 40;
  auto ty = [&](double y) { return o.log_y ? std::log10(y) : y; };
  auto usable = [&](double x, double y) { return std::isfinite(x) && std::isfinite(y) && (!o.log_y || y > 0); };
  double x0 = std::numeric_limits<double>::infinity(), x1 = -x0, y0 = x0, y1 = -x0;
  for (const auto& s : series) {
    require(s.x.size() == s.y.size(), "plot: series '", s.name, "' has ", s.x.size(), " x and ", s.y.size(), " y values");
    for (std::size_t i = 0; i < s.x.size(); ++i)
      if (usable(s.x[i], s.y[i])) {
        x0 = std::min(x0, s.x[i]), x1 = std::max(x1, s.x[i]);
        y0 = std::min(y0, ty(s.y[i])), y1 = std::max(y1, ty(s.y[i]));
      }
  }
  if (!std::isfinite(x0)) x0 = 0, x1 = 1, y0 = 0, y1 = 1;
  if (x1 <= x0) x1 = x0 + 1;
  if (y1 <= y0) y0 -= 0.5, y1 += 0.5;
  const double pad = 0.05 * (y1 - y0);
  y0 -= pad, y1 += pad;
  auto px = [&](double x) { return static_cast<double>(left) + (x - x0) / (x1 - x0) * static_cast<double>(right - left); };
  auto py = [&](double y) { return static_cast<double>(bottom) - (y - y0) / (y1 - y0) * static_cast<double>(bottom - top); };

  for (double t : detail::nice_ticks(y0, y1, 6)) {
    detail::line(v, static_cast<double>(left), py(t), static_cast<double>(right), py(t), grid, 1);
    const std::string label = detail::tick_label(o.log_y ? std::pow(10.0, t) : t);
    draw_text(v, left - 6 - text_width(label), std::lround(py(t)) - 5, label, ink);
  }
  for (double t : detail::nice_ticks(x0, x1, 8)) {
    detail::line(v, px(t), static_cast<double>(top), px(t), static_cast<double>(bottom), grid, 1);
    const std::string label = detail::tick_label(t);
    draw_text(v, std::lround(px(t)) - text_width(label) / 2, bottom + 6, label, ink);
  }
  detail::line(v, static_cast<double>(left), static_cast<double>(bottom), static_cast<double>(right), static_cast<double>(bottom), ink, 1);
  detail::line(v, static_cast<double>(left), static_cast<double>(top), static_cast<double>(left), static_cast<double>(bottom), ink, 1);
  for (const auto& s : series) {
    bool have = false;
    double lx = 0, ly = 0;
    for (std::size_t i = 0; i < s.x.size(); ++i) {
      if (!usable(s.x[i], s.y[i])) {
        have = false;
        continue;
      }
      const double cx = px(s.x[i]), cy = py(ty(s.y[i]));
      if (have) detail::line(v, lx, ly, cx, cy, s.color, 2);
      else detail::fill_rect(v, std::lround(cx) - 1, std::lround(cy) - 1, std::lround(cx) + 2, std::lround(cy) + 2, s.color);
      lx = cx, ly = cy, have = true;
    }
  }
  draw_text(v, left, 10, o.title + (o.log_y ? "  (log scale)" : ""), ink);
  draw_text(v, (left + right) / 2 - text_width(o.x_label) / 2, o.height - 16, o.x_label, ink);
  draw_text(v, 6, 10 + 16, o.y_label, ink);
  long ly = top + 6;
  for (const auto& s : series) {
    const long w = text_width(s.name) + 22;
    detail::fill_rect(v, right - w - 12, ly - 3, right - 1, ly + 13, {255, 255, 255});
    detail::fill_rect(v, right - w - 6, ly + 3, right - w + 8, ly + 7, s.color);
    draw_text(v, right - w + 12, ly, s.name, ink);
    ly += 16;
  }
  return img;
}

// One labelled cell of an image grid: an HWC float image in [0, 1] (1 or 3 channels; NaN is drawn magenta); an
// empty image leaves the cell blank.
struct GridCell {
  TensorView<const float, 3> image;
  std::string label;
};

// Cells row by row, `cols` per row, each scaled by an integer factor to about `cell` pixels, labels underneath.
inline Tensor<std::uint8_t, 3> image_grid(std::span<const GridCell> cells, int cols, int cell = 128) {
  require(!cells.empty() && cols >= 1, "image grid: ", cells.size(), " cells in ", cols, " columns");
  require(cell >= 8 && cell <= 4096, "image grid: cell size ", cell, " outside [8, 4096]");
  index_t ch = 0, cw = 0;
  for (const auto& c : cells) {
    if (c.image.empty()) continue;
    require(c.image.shape(2) == 1 || c.image.shape(2) == 3, "image grid: cell '", c.label, "' has ", c.image.shape(2),
            " channels, expected 1 or 3");
    ch = std::max(ch, c.image.shape(0)), cw = std::max(cw, c.image.shape(1));
  }
  require(ch > 0 && cw > 0, "image grid: every cell is empty");
  const index_t zoom = std::max<index_t>(1, cell / std::max(ch, cw));
  const long pad = 6, label_h = 16, cell_w = static_cast<long>(cw * zoom), cell_h = static_cast<long>(ch * zoom);
  const long rows = static_cast<long>((cells.size() + static_cast<std::size_t>(cols) - 1) / static_cast<std::size_t>(cols));
  const long W = cols * (cell_w + pad) + pad, H = rows * (cell_h + label_h + pad) + pad;
  Tensor<std::uint8_t, 3> img(Shape<3>{static_cast<index_t>(H), static_cast<index_t>(W), 3}, std::uint8_t(255));
  auto v = img.view();
  for (std::size_t i = 0; i < cells.size(); ++i) {
    const long gx = pad + static_cast<long>(i % static_cast<std::size_t>(cols)) * (cell_w + pad);
    const long gy = pad + static_cast<long>(i / static_cast<std::size_t>(cols)) * (cell_h + label_h + pad);
    const auto& im = cells[i].image;
    if (im.empty()) continue;
    const index_t C = im.shape(2);
    for (index_t y = 0; y < im.shape(0) * zoom; ++y)
      for (index_t x = 0; x < im.shape(1) * zoom; ++x) {
        Rgb8 c;
        for (index_t k = 0; k < 3; ++k) {
          const float f = im(y / zoom, x / zoom, C == 1 ? 0 : k);
          c[static_cast<std::size_t>(k)] = std::isnan(f) ? (k == 1 ? 0 : 255)
                                                        : static_cast<std::uint8_t>(std::lround(std::clamp(f, 0.f, 1.f) * 255.f));
        }
        detail::put(v, gx + static_cast<long>(x), gy + static_cast<long>(y), c);
      }
    std::string label = cells[i].label;
    const auto fits = static_cast<std::size_t>(std::max<long>(1, (cell_w + 2) / 8));
    if (label.size() > fits) label.resize(fits);
    draw_text(v, gx, gy + cell_h + 3, label, {40, 40, 40});
  }
  return img;
}

}  // namespace image
}  // namespace v0
}  // namespace flexsplat
