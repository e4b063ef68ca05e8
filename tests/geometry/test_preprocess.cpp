#include <catch2/catch.hpp>

#include <algorithm>
#include <array>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <unistd.h>

#include "flexsplat/geometry/preprocess.hpp"

using namespace flexsplat;

namespace {

std::vector<std::uint8_t> random_bytes(std::size_t n, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> d(0, 255);
  std::vector<std::uint8_t> v(n);
  for (auto& x : v) x = static_cast<std::uint8_t>(d(rng));
  return v;
}

// Minimal PNG writer (stored deflate blocks, filter 0) so tests can make any colour type / bit depth.
std::uint32_t crc32(const std::uint8_t* p, std::size_t n, std::uint32_t crc = 0xffffffffu) {
  for (std::size_t i = 0; i < n; ++i) {
    crc ^= p[i];
    for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xedb88320u & (0u - (crc & 1u)));
  }
  return crc;
}

void put32(std::vector<std::uint8_t>& out, std::uint32_t v) {
  for (int s = 24; s >= 0; s -= 8) out.push_back(static_cast<std::uint8_t>(v >> s));
}

void chunk(std::vector<std::uint8_t>& out, const char* type, const std::vector<std::uint8_t>& data) {
  put32(out, static_cast<std::uint32_t>(data.size()));
  std::vector<std::uint8_t> body(type, type + 4);
  body.insert(body.end(), data.begin(), data.end());
  out.insert(out.end(), body.begin(), body.end());
  put32(out, crc32(body.data(), body.size()) ^ 0xffffffffu);
}

// rows: raw scanline bytes (without filter byte), big-endian samples for 16-bit.
std::vector<std::uint8_t> make_png(std::uint32_t w, std::uint32_t h, int depth, int color_type,
                                   const std::vector<std::uint8_t>& raw, std::size_t row_bytes,
                                   const std::vector<std::uint8_t>& plte = {}, const std::vector<std::uint8_t>& trns = {}) {
  std::vector<std::uint8_t> out{0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  std::vector<std::uint8_t> ihdr;
  put32(ihdr, w);
  put32(ihdr, h);
  ihdr.insert(ihdr.end(), {static_cast<std::uint8_t>(depth), static_cast<std::uint8_t>(color_type), 0, 0, 0});
  chunk(out, "IHDR", ihdr);
  if (!plte.empty()) chunk(out, "PLTE", plte);
  if (!trns.empty()) chunk(out, "tRNS", trns);
  std::vector<std::uint8_t> filtered;
  for (std::uint32_t y = 0; y < h; ++y) {
    filtered.push_back(0);
    filtered.insert(filtered.end(), raw.begin() + y * row_bytes, raw.begin() + (y + 1) * row_bytes);
  }
  std::vector<std::uint8_t> z{0x78, 0x01};
  std::size_t pos = 0;
  do {
    const std::size_t len = std::min<std::size_t>(65535, filtered.size() - pos);
    const bool last = pos + len == filtered.size();
    z.push_back(last ? 1 : 0);
    z.push_back(static_cast<std::uint8_t>(len & 0xff));
    z.push_back(static_cast<std::uint8_t>(len >> 8));
    z.push_back(static_cast<std::uint8_t>(~len & 0xff));
    z.push_back(static_cast<std::uint8_t>((~len >> 8) & 0xff));
    z.insert(z.end(), filtered.begin() + pos, filtered.begin() + pos + len);
    pos += len;
  } while (pos < filtered.size());
  std::uint32_t a = 1, b = 0;
  for (auto v : filtered) {
    a = (a + v) % 65521;
    b = (b + a) % 65521;
  }
  put32(z, (b << 16) | a);
  chunk(out, "IDAT", z);
  chunk(out, "IEND", {});
  return out;
}

std::string write_temp(const std::string& name, const std::vector<std::uint8_t>& bytes) {
  const auto dir = std::filesystem::temp_directory_path() / ("flexsplat_test_preprocess_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const auto path = dir / name;
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(bytes.data()),
                                               static_cast<std::streamsize>(bytes.size()));
  return path.string();
}

InterleavedImage make_image(index_t w, index_t h, int channels, std::uint32_t seed) {
  InterleavedImage im;
  im.width = w;
  im.height = h;
  im.channels = channels;
  im.pixels = random_bytes(static_cast<std::size_t>(w * h * channels), seed);
  return im;
}

}  // namespace

TEST_CASE("python round: nearest, ties to even", "[preprocess]") {
  CHECK(python_round(0.5) == 0.0);
  CHECK(python_round(1.5) == 2.0);
  CHECK(python_round(2.5) == 2.0);
  CHECK(python_round(36.5) == 36.0);
  CHECK(python_round(37.5) == 38.0);
  CHECK(python_round(23.125) == 23.0);
  CHECK(python_round(22.9) == 23.0);
  CHECK(python_round(-0.5) == -0.0);
}

TEST_CASE("resize targets follow load_fn.py", "[preprocess]") {
  using M = VggtPreprocessMode;
  auto t = vggt_resize_target(320, 200, M::crop);  // 200 * 518 / 320 / 14 = 23.125 -> 322
  CHECK(t.width == 518);
  CHECK(t.height == 322);
  t = vggt_resize_target(150, 260, M::crop);  // 64.13 -> 896, cropped later
  CHECK(t.width == 518);
  CHECK(t.height == 896);
  t = vggt_resize_target(150, 260, M::pad);  // width = round(150 * 518 / 260 / 14) * 14 = 21 * 14
  CHECK(t.width == 294);
  CHECK(t.height == 518);
  t = vggt_resize_target(256, 256, M::pad);
  CHECK((t.width == 518 && t.height == 518));
  // 5 * (518 / 74) / 14 = 2.5 exactly: Python rounds to 2 (half-up would give 42).
  t = vggt_resize_target(74, 5, M::crop);
  CHECK(t.height == 28);
  t = vggt_resize_target(74, 7, M::crop);  // 3.5 -> 4
  CHECK(t.height == 56);
  // 1 * 7 / 14 = 0.5 -> 0: Pillow would refuse the size; so do we, naming it.
  CHECK_THROWS_WITH(vggt_resize_target(74, 1, M::crop), Catch::Contains("74x1") && Catch::Contains("518x0"));
  CHECK_THROWS_WITH(parse_vggt_preprocess_mode("square"), Catch::Contains("'crop' or 'pad'"));
  CHECK(parse_vggt_preprocess_mode("pad") == M::pad);
}

TEST_CASE("RGBA is composited on white with Pillow's integer arithmetic", "[preprocess]") {
  std::uint8_t rgb[3];
  const auto composite = [&](std::uint8_t r, std::uint8_t g, std::uint8_t b, std::uint8_t a) {
    const std::uint8_t px[4] = {r, g, b, a};
    pillow_composite_on_white(px, rgb);
    return std::array<int, 3>{rgb[0], rgb[1], rgb[2]};
  };
  CHECK(composite(10, 20, 30, 0) == std::array<int, 3>{255, 255, 255});
  CHECK(composite(10, 20, 30, 255) == std::array<int, 3>{10, 20, 30});
  // Worked by hand: coef1 = 128 * 128, coef2 = 127 * 128; value 0 -> 4161664 -> 127; value 255 -> 255.
  CHECK(composite(0, 255, 0, 128) == std::array<int, 3>{127, 255, 127});
  // 100 at alpha 200: 100 * 200/255 + 255 * 55/255 = 133.43 -> 133.
  CHECK(composite(100, 100, 100, 200)[0] == 133);
  // Exhaustive check against the rounded real-valued blend: never more than one unit away.
  int worst = 0;
  for (int a = 0; a < 256; ++a)
    for (int v = 0; v < 256; ++v) {
      const int got = composite(std::uint8_t(v), 0, 0, std::uint8_t(a))[0];
      const double exact = (v * a + 255.0 * (255 - a)) / 255.0;
      worst = std::max(worst, int(std::abs(got - exact) + 0.5));
    }
  CHECK(worst <= 1);
}

TEST_CASE("conversion to RGB per Pillow mode", "[preprocess]") {
  std::vector<std::uint8_t> rgb;
  const std::vector<std::uint8_t> la{10, 0, 200, 128};
  vggt_convert_to_rgb({la.data(), 2, 1, 2}, rgb);  // "LA": alpha dropped, not composited
  CHECK(rgb == std::vector<std::uint8_t>{10, 10, 10, 200, 200, 200});
  const std::vector<std::uint8_t> l{7, 9};
  vggt_convert_to_rgb({l.data(), 1, 2, 1}, rgb);
  CHECK(rgb == std::vector<std::uint8_t>{7, 7, 7, 9, 9, 9});
  const std::vector<std::uint8_t> rgba{1, 2, 3, 0, 4, 5, 6, 255};
  vggt_convert_to_rgb({rgba.data(), 2, 1, 4}, rgb);
  CHECK(rgb == std::vector<std::uint8_t>{255, 255, 255, 4, 5, 6});
  CHECK_THROWS_WITH(vggt_convert_to_rgb({rgba.data(), 2, 1, 5}, rgb), Catch::Contains("5 channels"));
  CHECK_THROWS_WITH(vggt_convert_to_rgb({nullptr, 2, 1, 3}, rgb), Catch::Contains("null"));
  CHECK_THROWS_WITH(vggt_convert_to_rgb({rgba.data(), 0, 1, 3}, rgb), Catch::Contains("empty image"));
}

TEST_CASE("crop mode: resize to width 518, centre-crop tall images", "[preprocess]") {
  const auto tall = make_image(60, 100, 3, 1);  // 100 * 518 / 60 / 14 = 61.67 -> 868 rows, crop 175..693
  const std::vector<InterleavedImage> one{tall};
  const auto out = vggt_preprocess_images(one, VggtPreprocessMode::crop);
  REQUIRE(out.shape() == Shape<4>{1, 3, 518, 518});
  const auto resized = resize_pillow_bicubic(tall.pixels, 60, 100, 3, 518, 868);
  const index_t start = (868 - 518) / 2;
  std::size_t mismatches = 0;
  for (index_t c = 0; c < 3; ++c)
    for (index_t y = 0; y < 518; ++y)
      for (index_t x = 0; x < 518; ++x)
        mismatches += out(0, c, y, x) != float(resized[((y + start) * 518 + x) * 3 + c]) / 255.0f;
  CHECK(mismatches == 0);

  const auto wide = make_image(90, 40, 3, 2);  // 40 * 518 / 90 / 14 = 16.44 -> 224 rows, no crop
  const auto out2 = vggt_preprocess_images(std::vector<InterleavedImage>{wide}, VggtPreprocessMode::crop);
  CHECK(out2.shape() == Shape<4>{1, 3, 224, 518});
}

TEST_CASE("pad mode: longer side 518, centred white padding", "[preprocess]") {
  const auto wide = make_image(90, 40, 3, 3);  // 224 x 518, padded by 147 above and 147 below
  const auto out = vggt_preprocess_images(std::vector<InterleavedImage>{wide}, VggtPreprocessMode::pad);
  REQUIRE(out.shape() == Shape<4>{1, 3, 518, 518});
  const auto resized = resize_pillow_bicubic(wide.pixels, 90, 40, 3, 518, 224);
  std::size_t mismatches = 0;
  for (index_t c = 0; c < 3; ++c)
    for (index_t y = 0; y < 518; ++y)
      for (index_t x = 0; x < 518; ++x) {
        const bool inside = y >= 147 && y < 147 + 224;
        const float expected = inside ? float(resized[((y - 147) * 518 + x) * 3 + c]) / 255.0f : 1.0f;
        mismatches += out(0, c, y, x) != expected;
      }
  CHECK(mismatches == 0);

  const auto tall = make_image(41, 100, 3, 4);  // width round(41 * 5.18 / 14) * 14 = 15 * 14 = 210; pad 154 / 154
  const auto out2 = vggt_preprocess_images(std::vector<InterleavedImage>{tall}, VggtPreprocessMode::pad);
  REQUIRE(out2.shape() == Shape<4>{1, 3, 518, 518});
  CHECK(out2(0, 1, 100, 153) == 1.0f);
  CHECK(out2(0, 1, 100, 154 + 210) == 1.0f);
  const auto resized2 = resize_pillow_bicubic(tall.pixels, 41, 100, 3, 210, 518);
  CHECK(out2(0, 2, 100, 154) == float(resized2[(100 * 210 + 0) * 3 + 2]) / 255.0f);
  CHECK(out2(0, 2, 517, 154 + 209) == float(resized2[(517 * 210 + 209) * 3 + 2]) / 255.0f);
}

TEST_CASE("batches of different shapes are padded with white to the largest", "[preprocess]") {
  const std::vector<InterleavedImage> images{make_image(90, 40, 3, 5), make_image(50, 50, 4, 6)};
  const auto out = vggt_preprocess_images(images, VggtPreprocessMode::crop);
  REQUIRE(out.shape() == Shape<4>{2, 3, 518, 518});
  const auto first = vggt_preprocess_images(std::vector<InterleavedImage>{images[0]}, VggtPreprocessMode::crop);
  REQUIRE(first.shape() == Shape<4>{1, 3, 224, 518});
  const auto second = vggt_preprocess_images(std::vector<InterleavedImage>{images[1]}, VggtPreprocessMode::crop);
  std::size_t mismatches = 0;
  for (index_t c = 0; c < 3; ++c)
    for (index_t y = 0; y < 518; ++y)
      for (index_t x = 0; x < 518; ++x) {
        const bool inside = y >= 147 && y < 147 + 224;
        mismatches += out(0, c, y, x) != (inside ? first(0, c, y - 147, x) : 1.0f);
        mismatches += out(1, c, y, x) != second(0, c, y, x);
      }
  CHECK(mismatches == 0);
  // Same shapes: no padding at all.
  const std::vector<InterleavedImage> same{make_image(90, 40, 3, 7), make_image(90, 40, 3, 8)};
  CHECK(vggt_preprocess_images(same, VggtPreprocessMode::crop).shape() == Shape<4>{2, 3, 224, 518});
  // Values stay in [0, 1].
  CHECK(std::all_of(out.span().begin(), out.span().end(), [](float v) { return v >= 0.0f && v <= 1.0f; }));
}

TEST_CASE("preprocess errors name the problem", "[preprocess][errors]") {
  CHECK_THROWS_WITH(vggt_preprocess_images(std::vector<InterleavedImage>{}, VggtPreprocessMode::crop),
                    Catch::Contains("At least 1 image"));
  InterleavedImage bad = make_image(74, 1, 3, 9);
  CHECK_THROWS_WITH(vggt_preprocess_images(std::vector<InterleavedImage>{make_image(8, 8, 3, 1), bad},
                                           VggtPreprocessMode::crop),
                    Catch::Contains("image 1 of 2") && Catch::Contains("height and width must be > 0"));
  CHECK_THROWS_WITH(vggt_load_and_preprocess_images({"/nonexistent/flexsplat.png"}, VggtPreprocessMode::pad),
                    Catch::Contains("/nonexistent/flexsplat.png"));
  const auto junk = write_temp("junk.png", {1, 2, 3, 4, 5});
  CHECK_THROWS_WITH(decode_image_like_pillow(junk), Catch::Contains("junk.png") && Catch::Contains("cannot decode"));
  const auto empty = write_temp("empty.png", {});
  CHECK_THROWS_WITH(decode_image_like_pillow(empty), Catch::Contains("empty"));
}

TEST_CASE("PNG decoding gives what Pillow 9.4's PNG plugin gives", "[preprocess][decode]") {
  SECTION("8-bit RGBA and RGB round-trip") {
    const auto px = random_bytes(5 * 3 * 4, 10);
    const auto im = decode_image_like_pillow(write_temp("rgba.png", make_png(5, 3, 8, 6, px, 5 * 4)));
    CHECK((im.width == 5 && im.height == 3 && im.channels == 4));
    CHECK(im.pixels == px);
    const auto px3 = random_bytes(4 * 2 * 3, 11);
    const auto im3 = decode_image_like_pillow(write_temp("rgb.png", make_png(4, 2, 8, 2, px3, 4 * 3)));
    CHECK(im3.channels == 3);
    CHECK(im3.pixels == px3);
  }
  SECTION("16-bit greyscale is mode I: clipped at 255") {
    const std::vector<std::uint8_t> raw{0x00, 0x00, 0x00, 0x64, 0x00, 0xff, 0x01, 0x00, 0xff, 0xff};
    const auto im = decode_image_like_pillow(write_temp("g16.png", make_png(5, 1, 16, 0, raw, 10)));
    CHECK(im.channels == 1);
    CHECK(im.pixels == std::vector<std::uint8_t>{0, 100, 255, 255, 255});
  }
  SECTION("16-bit RGB keeps the high byte") {
    const std::vector<std::uint8_t> raw{0x12, 0x34, 0xab, 0xcd, 0x00, 0xff};
    const auto im = decode_image_like_pillow(write_temp("rgb16.png", make_png(1, 1, 16, 2, raw, 6)));
    CHECK(im.pixels == std::vector<std::uint8_t>{0x12, 0xab, 0x00});
  }
  SECTION("8-bit grey+alpha is LA (alpha later dropped), 16-bit grey+alpha is RGBA") {
    const std::vector<std::uint8_t> raw8{50, 0, 60, 255};
    const auto la = decode_image_like_pillow(write_temp("la8.png", make_png(2, 1, 8, 4, raw8, 4)));
    CHECK(la.channels == 2);
    CHECK(la.pixels == raw8);
    const std::vector<std::uint8_t> raw16{0x50, 0x11, 0x00, 0x00};
    const auto la16 = decode_image_like_pillow(write_temp("la16.png", make_png(1, 1, 16, 4, raw16, 4)));
    CHECK(la16.channels == 4);
    CHECK(la16.pixels == std::vector<std::uint8_t>{0x50, 0x50, 0x50, 0x00});
  }
  SECTION("palette with tRNS converts to RGB without alpha") {
    const std::vector<std::uint8_t> plte{255, 0, 0, 0, 0, 255};
    const std::vector<std::uint8_t> trns{0, 255};
    const std::vector<std::uint8_t> idx{0, 1, 1};
    const auto im = decode_image_like_pillow(write_temp("p.png", make_png(3, 1, 8, 3, idx, 3, plte, trns)));
    CHECK(im.channels == 3);
    CHECK(im.pixels == std::vector<std::uint8_t>{255, 0, 0, 0, 0, 255, 0, 0, 255});
  }
  SECTION("file overload equals the buffer overload") {
    const auto px = random_bytes(30 * 20 * 4, 12);
    const auto path = write_temp("f.png", make_png(30, 20, 8, 6, px, 30 * 4));
    const auto a = vggt_load_and_preprocess_images({path, path}, VggtPreprocessMode::pad);
    InterleavedImage im{30, 20, 4, px};
    const auto b = vggt_preprocess_images(std::vector<InterleavedImage>{im, im}, VggtPreprocessMode::pad);
    REQUIRE(a.shape() == b.shape());
    CHECK(std::equal(a.span().begin(), a.span().end(), b.span().begin()));
  }
}
