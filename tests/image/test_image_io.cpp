#include <catch2/catch.hpp>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "flexsplat/image/image_io.hpp"

using namespace flexsplat;

namespace {
const std::filesystem::path spot = std::filesystem::path(FLEXSPLAT_SHARED_DIR) / "data/objects/spot";

std::filesystem::path temp_path(const std::string& name) {
  return std::filesystem::temp_directory_path() / ("flexsplat_test_img_" + std::to_string(::getpid()) + "_" + name);
}

// A JPEG written by libjpeg: `components` 1 (grey), 3 (YCbCr) or 4 (CMYK); progressive with `ac_bands` spectral
// bands per component, each sent at Al = 1 then refined (1 + 2 * ac_bands scans per component after the DC scan).
std::vector<unsigned char> libjpeg_encode(int w, int h, int components, int ac_bands = 0) {
  jpeg_compress_struct c{};
  jpeg_error_mgr err{};
  c.err = jpeg_std_error(&err);
  jpeg_create_compress(&c);
  unsigned char* out = nullptr;
  unsigned long size = 0;
  jpeg_mem_dest(&c, &out, &size);
  c.image_width = static_cast<JDIMENSION>(w);
  c.image_height = static_cast<JDIMENSION>(h);
  c.input_components = components;
  c.in_color_space = components == 1 ? JCS_GRAYSCALE : components == 3 ? JCS_RGB : JCS_CMYK;
  jpeg_set_defaults(&c);
  jpeg_set_quality(&c, 95, TRUE);
  std::vector<jpeg_scan_info> script;
  if (ac_bands > 0) {
    jpeg_scan_info dc{};
    dc.comps_in_scan = components;
    for (int k = 0; k < components; ++k) dc.component_index[k] = k;
    script.push_back(dc);
    for (int pass = 0; pass < 2; ++pass)
      for (int k = 0; k < components; ++k)
        for (int b = 0; b < ac_bands; ++b) {
          jpeg_scan_info ac{};
          ac.comps_in_scan = 1;
          ac.component_index[0] = k;
          ac.Ss = 1 + b * 63 / ac_bands;
          ac.Se = (b + 1) * 63 / ac_bands;
          ac.Ah = pass;
          ac.Al = 1 - pass;
          script.push_back(ac);
        }
    c.scan_info = script.data();
    c.num_scans = static_cast<int>(script.size());
  }
  jpeg_start_compress(&c, TRUE);
  std::vector<unsigned char> row(static_cast<std::size_t>(w) * components);
  while (c.next_scanline < c.image_height) {
    for (int x = 0; x < w; ++x)
      for (int k = 0; k < components; ++k)
        row[x * components + k] = static_cast<unsigned char>((x * 7 + k * 50 + c.next_scanline * 3) & 255);
    JSAMPROW r = row.data();
    jpeg_write_scanlines(&c, &r, 1);
  }
  jpeg_finish_compress(&c);
  jpeg_destroy_compress(&c);
  std::vector<unsigned char> bytes(out, out + size);
  std::free(out);
  return bytes;
}

std::filesystem::path write_temp(const std::string& name, const std::vector<unsigned char>& bytes) {
  const auto path = temp_path(name);
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  return path;
}
}  // namespace

// Expected pixel values come from an independent pure-Python PNG decoder (zlib + unfiltering) run on the same files.
TEST_CASE("reads the real RGBA render at 8 bits", "[image]") {
  const auto path = spot / "images/000.png";
  const auto info = image::probe(path);
  CHECK(info.width == 256);
  CHECK(info.height == 256);
  CHECK(info.channels == 4);
  CHECK(info.bit_depth == 8);
  const auto img = image::read_u8(path);
  REQUIRE(img.shape() == Shape<3>{256, 256, 4});
  // (row, column) = (y, x)
  CHECK(std::vector<int>{img(128, 128, 0), img(128, 128, 1), img(128, 128, 2), img(128, 128, 3)} ==
        std::vector<int>{228, 213, 206, 255});
  CHECK(std::vector<int>{img(150, 100, 0), img(150, 100, 3)} == std::vector<int>{68, 255});
  CHECK(std::vector<int>{img(60, 200, 0), img(60, 200, 1), img(60, 200, 2)} == std::vector<int>{64, 59, 56});
  CHECK(std::vector<int>{img(18, 185, 0), img(18, 185, 1), img(18, 185, 2), img(18, 185, 3)} ==
        std::vector<int>{164, 98, 64, 11});
  int opaque = 0, transparent = 0;
  for (index_t y = 0; y < 256; ++y)
    for (index_t x = 0; x < 256; ++x) {
      opaque += img(y, x, 3) == 255;
      transparent += img(y, x, 3) == 0;
    }
  CHECK(opaque == 21307);
  CHECK(transparent == 42707);
}

TEST_CASE("composites RGBA over a background colour in float", "[image]") {
  const auto path = spot / "images/000.png";
  const auto white = image::read_rgb<float>(path);
  REQUIRE(white.shape() == Shape<3>{256, 256, 3});
  CHECK(white(0, 0, 0) == 1.0f);  // fully transparent -> background
  CHECK(white(128, 128, 1) == Approx(213.0 / 255.0).epsilon(1e-6));  // opaque -> the pixel itself
  const double a = 11.0 / 255.0;
  CHECK(white(18, 185, 0) == Approx(164.0 / 255.0 * a + (1 - a)).epsilon(1e-6));
  const auto grey = image::read_rgb<double>(path, {0.5, 0.25, 0.0});
  CHECK(grey(0, 0, 1) == 0.25);
  CHECK(grey(18, 185, 2) == Approx(64.0 / 255.0 * a + 0.0 * (1 - a)).epsilon(1e-12));
  const auto f = image::read_float<float>(path);
  CHECK(f.shape() == Shape<3>{256, 256, 4});
  CHECK(f(18, 185, 3) == 11.0f / 255.0f);
  Tensor<float, 3> wrong({256, 256, 4});
  CHECK_THROWS_WITH(image::composite_over<float>(f.view(), {1, 1, 1}, wrong.view()), Catch::Contains("expected [256, 256, 3]"));
}

TEST_CASE("reads the 16-bit depth map without losing precision", "[image]") {
  const auto path = spot / "depth/000.png";
  const auto info = image::probe(path);
  CHECK(info.bit_depth == 16);
  CHECK(info.channels == 1);
  const auto raw = image::read_u16(path);
  REQUIRE(raw.shape() == Shape<3>{256, 256, 1});
  CHECK(raw(128, 128, 0) == 26373);
  CHECK(raw(150, 100, 0) == 25802);
  CHECK(raw(60, 200, 0) == 26837);
  CHECK(raw(0, 0, 0) == 0);
  int nonzero = 0, lo = 65536, hi = 0;
  for (index_t i = 0; i < raw.size(); ++i) {
    const int v = raw.data()[i];
    if (v == 0) continue;
    ++nonzero;
    lo = std::min(lo, v);
    hi = std::max(hi, v);
  }
  CHECK(nonzero == 22046);
  CHECK(lo == 24529);
  CHECK(hi == 32361);
  const auto depth = image::read_depth_png<double>(path, 1e-4);
  CHECK(depth(128, 128) == Approx(2.6373).epsilon(1e-12));
  CHECK(depth(0, 0) == 0.0);
  CHECK(image::read_float<double>(path)(128, 128, 0) == Approx(26373.0 / 65535.0).epsilon(1e-12));
  CHECK(image::read_u8(path)(128, 128, 0) == 26373 >> 8);
  CHECK_THROWS_WITH(image::read_depth_png<float>(spot / "images/000.png", 1e-4f),
                    Catch::Contains("images/000.png") && Catch::Contains("16-bit single-channel"));
}

TEST_CASE("PNG write/read round trip is exact for 1 to 4 channels", "[image]") {
  for (index_t c = 1; c <= 4; ++c) {
    Tensor<std::uint8_t, 3> img({7, 13, c});
    for (index_t i = 0; i < img.size(); ++i) img.data()[i] = static_cast<std::uint8_t>((i * 37 + c) % 256);
    const auto path = temp_path("roundtrip" + std::to_string(c) + ".png");
    image::write_png(path, img);
    const auto back = image::read_u8(path);
    REQUIRE(back.shape() == img.shape());
    CHECK(std::equal(back.data(), back.data() + back.size(), img.data()));
    CHECK(image::probe(path).channels == c);
    std::filesystem::remove(path);
  }
  // Float images are clamped and rounded to the nearest 8-bit step.
  Tensor<float, 3> f({1, 4, 1});
  f(0, 0, 0) = -0.5f;
  f(0, 1, 0) = 0.5f;
  f(0, 2, 0) = 2.0f;
  f(0, 3, 0) = 100.4f / 255.0f;
  const auto path = temp_path("float.png");
  image::write_png(path, f);
  const auto back = image::read_u8(path);
  CHECK(std::vector<int>{back(0, 0, 0), back(0, 1, 0), back(0, 2, 0), back(0, 3, 0)} == std::vector<int>{0, 128, 255, 100});
  std::filesystem::remove(path);
  f(0, 2, 0) = NAN;
  CHECK_THROWS_WITH(image::write_png(path, f), Catch::Contains("NaN at pixel (2, 0)"));
  CHECK_FALSE(std::filesystem::exists(path));
  CHECK_THROWS_WITH(image::write_png("/nonexistent_dir_flexsplat/x.png", Tensor<std::uint8_t, 3>({2, 2, 3})),
                    Catch::Contains("/nonexistent_dir_flexsplat/x.png"));
  CHECK_THROWS_WITH(image::write_png(path, Tensor<std::uint8_t, 3>({2, 2, 5})), Catch::Contains("5 channels"));
}

TEST_CASE("reads JPEG", "[image]") {
  // A smooth gradient written by stb's JPEG encoder at quality 100 decodes within a few levels.
  const int w = 32, h = 16;
  std::vector<unsigned char> rgb(w * h * 3);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      rgb[(y * w + x) * 3 + 0] = static_cast<unsigned char>(x * 8);
      rgb[(y * w + x) * 3 + 1] = static_cast<unsigned char>(y * 16);
      rgb[(y * w + x) * 3 + 2] = 128;
    }
  const auto path = temp_path("gradient.jpg");
  REQUIRE(stbi_write_jpg(path.c_str(), w, h, 3, rgb.data(), 100));
  const auto info = image::probe(path);
  CHECK(info.channels == 3);
  CHECK(info.bit_depth == 8);
  const auto img = image::read_u8(path);
  REQUIRE(img.shape() == Shape<3>{h, w, 3});
  int worst = 0;
  for (index_t i = 0; i < img.size(); ++i) worst = std::max(worst, std::abs(int(img.data()[i]) - int(rgb[i])));
  CHECK(worst <= 6);
  const auto with_alpha = image::read_u8(path, 4);
  CHECK(with_alpha(3, 5, 3) == 255);
  std::filesystem::remove(path);
}

TEST_CASE("JPEG channel conversions follow stb's rules for PNG", "[image]") {
  const auto grey = write_temp("grey.jpg", libjpeg_encode(24, 16, 1));
  const auto g = image::read_u8(grey);
  REQUIRE(g.shape() == Shape<3>{16, 24, 1});
  CHECK(image::probe(grey).channels == 1);
  const auto g4 = image::read_u8(grey, 4);
  const auto g16 = image::read_u16(grey, 2);
  for (index_t y = 0; y < 16; ++y)
    for (index_t x = 0; x < 24; ++x) {
      CHECK(g4(y, x, 0) == g(y, x, 0));
      CHECK(g4(y, x, 2) == g(y, x, 0));
      CHECK(g4(y, x, 3) == 255);
      CHECK(g16(y, x, 0) == 257 * g(y, x, 0));
      CHECK(g16(y, x, 1) == 65535);
    }
  const auto rgb_path = write_temp("rgb.jpg", libjpeg_encode(24, 16, 3));
  const auto rgb = image::read_u8(rgb_path);
  const auto luma = image::read_u8(rgb_path, 1);
  for (index_t y = 0; y < 16; ++y)
    for (index_t x = 0; x < 24; ++x)
      CHECK(int(luma(y, x, 0)) == (77 * rgb(y, x, 0) + 150 * rgb(y, x, 1) + 29 * rgb(y, x, 2)) >> 8);
  for (const auto& p : {grey, rgb_path}) std::filesystem::remove(p);
}

TEST_CASE("corrupt, CMYK and endlessly progressive JPEGs are refused by name", "[image]") {
  // 1 + 2 * 40 scans decode; 1 + 2 * 63 exceed image::detail::max_jpeg_scans.
  const auto ok = write_temp("scans81.jpg", libjpeg_encode(16, 16, 1, 40));
  const auto many = write_temp("scans127.jpg", libjpeg_encode(16, 16, 1, 63));
  CHECK(image::read_u8(ok).shape() == Shape<3>{16, 16, 1});
  CHECK_THROWS_WITH(image::read_u8(many),
                    Catch::Contains(many.string()) && Catch::Contains("more than 100 progressive scans"));
  const auto cmyk = write_temp("cmyk.jpg", libjpeg_encode(16, 16, 4));
  CHECK_THROWS_WITH(image::probe(cmyk), Catch::Contains(cmyk.string()) && Catch::Contains("CMYK"));
  // The entropy-coded data cut short: libjpeg would fill the rest with grey.
  auto bytes = libjpeg_encode(64, 64, 3);
  bytes.resize(bytes.size() * 2 / 3);
  const auto cut = write_temp("cut.jpg", bytes);
  CHECK_THROWS_WITH(image::read_u8(cut), Catch::Contains(cut.string()) && Catch::Contains("cannot decode JPEG"));
  for (const auto& p : {ok, many, cmyk, cut}) std::filesystem::remove(p);
}

TEST_CASE("missing and corrupt image files give errors naming the file", "[image]") {
  CHECK_THROWS_WITH(image::read_u8("/nonexistent_flexsplat.png"),
                    Catch::Contains("image file '/nonexistent_flexsplat.png'") && Catch::Contains("no such file"));
  CHECK_THROWS_WITH(image::probe(std::filesystem::temp_directory_path()), Catch::Contains("not a regular file"));
  const auto garbage = temp_path("garbage.png");
  { std::ofstream(garbage, std::ios::binary) << "this is not an image at all"; }
  CHECK_THROWS_WITH(image::read_float<float>(garbage), Catch::Contains(garbage.string()));
  CHECK_THROWS_WITH(image::read_u8(garbage), Catch::Contains(garbage.string()) && Catch::Contains("cannot decode"));
  const auto empty = temp_path("empty.png");
  { std::ofstream(empty, std::ios::binary); }
  CHECK_THROWS_WITH(image::read_u8(empty), Catch::Contains("file is empty"));
  // A real PNG cut in half.
  const auto src = spot / "images/000.png";
  std::ifstream in(src, std::ios::binary);
  std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto truncated = temp_path("truncated.png");
  {
    std::ofstream out(truncated, std::ios::binary);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size() / 2));
  }
  CHECK_THROWS_WITH(image::read_u8(truncated), Catch::Contains(truncated.string()));
  CHECK_THROWS_WITH(image::read_u8(src, 5), Catch::Contains("requested 5 channels"));
  for (const auto& p : {garbage, empty, truncated}) std::filesystem::remove(p);
}
