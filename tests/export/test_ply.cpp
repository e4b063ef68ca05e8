#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <string>

#include "export/random_set.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/export/ply.hpp"

using namespace flexsplat;
using flexsplat_test::random_set;

namespace {

GaussianSet<float> decode_ply(const std::string& bytes) {
  return ply::decode_ply(reinterpret_cast<const unsigned char*>(bytes.data()), bytes.size(), "test.ply");
}
GaussianSet<float> decode_ply(const std::vector<unsigned char>& bytes) {
  return ply::decode_ply(bytes.data(), bytes.size(), "test.ply");
}

std::string header_of(const std::vector<unsigned char>& ply) {
  const std::string text(ply.begin(), ply.end());
  return text.substr(0, text.find("end_header") + 11);
}

}  // namespace

TEST_CASE("PLY header lists the INRIA properties in order", "[ply]") {
  const auto bytes = ply::encode_ply(random_set(2, 1));
  const std::string header = header_of(bytes);
  std::string expected = "property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n"
                         "property float nz\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n";
  for (int i = 0; i < 9; ++i) expected += "property float f_rest_" + std::to_string(i) + "\n";
  expected += "property float opacity\nproperty float scale_0\nproperty float scale_1\nproperty float scale_2\n"
              "property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\nend_header\n";
  CHECK(header.find("format binary_little_endian 1.0\n") != std::string::npos);
  CHECK(header.find("element vertex 2\n") != std::string::npos);
  CHECK(header.substr(header.find("property float x")) == expected);
  CHECK(bytes.size() == header.size() + 2 * (17 + 9) * 4);
}

TEST_CASE("PLY stores logit opacity, log scale, w-first quaternion and channel-major f_rest", "[ply]") {
  auto set = random_set(1, 1);
  set.opacities(0) = 0.8f;
  set.scales(0, 1) = 0.05f;
  const float q[4] = {0.5f, -0.5f, 0.5f, 0.5f};
  for (int c = 0; c < 4; ++c) set.quats(0, c) = q[c];
  for (int k = 1; k < 4; ++k)
    for (int c = 0; c < 3; ++c) set.sh(0, k, c) = float(10 * c + k);  // channel c, coefficient k
  const auto bytes = ply::encode_ply(set);
  const std::size_t body = header_of(bytes).size();
  float row[26];
  std::memcpy(row, bytes.data() + body, sizeof(row));
  // f_rest_0..2 is red for coefficients 1..3, then green, then blue.
  for (int c = 0; c < 3; ++c)
    for (int k = 1; k < 4; ++k) CHECK(row[9 + c * 3 + (k - 1)] == float(10 * c + k));
  CHECK(row[18] == Approx(std::log(0.8 / 0.2)).epsilon(1e-6));
  CHECK(row[20] == Approx(std::log(0.05)).epsilon(1e-6));
  for (int c = 0; c < 4; ++c) CHECK(row[22 + c] == q[c]);
}

TEST_CASE("PLY round trip at every SH degree", "[ply]") {
  for (int degree = 0; degree <= 3; ++degree) {
    const auto set = random_set(25, degree, 100 + degree);
    const auto back = decode_ply(ply::encode_ply(set));
    REQUIRE(back.sh_degree() == degree);
    REQUIRE(back.size() == 25);
    CHECK(std::memcmp(back.means.data(), set.means.data(), 4 * set.means.size()) == 0);
    CHECK(std::memcmp(back.sh.data(), set.sh.data(), 4 * set.sh.size()) == 0);
    for (index_t i = 0; i < set.size(); ++i) {
      // logit/sigmoid and log/exp through float32 storage: a few ulps.
      CHECK(back.opacities(i) == Approx(set.opacities(i)).epsilon(1e-5).margin(1e-6));
      for (int c = 0; c < 3; ++c) CHECK(back.scales(i, c) == Approx(set.scales(i, c)).epsilon(1e-5));
      for (int c = 0; c < 4; ++c) CHECK(back.quats(i, c) == Approx(set.quats(i, c)).margin(1e-6));
    }
  }
}

TEST_CASE("PLY to glb to PLY keeps the set", "[ply][gltf]") {
  const auto dir = std::filesystem::temp_directory_path();
  const auto set = random_set(30, 3, 5);
  ply::write_ply(set, dir / "flexsplat_conv_a.ply");
  const auto from_ply = gaussians::read_gaussians(dir / "flexsplat_conv_a.ply");
  gaussians::write_gaussians(from_ply, dir / "flexsplat_conv_b.glb");
  const auto from_glb = gaussians::read_gaussians(dir / "flexsplat_conv_b.glb");
  // glb is exact, so the glb copy equals what the PLY reader produced.
  CHECK(std::memcmp(from_glb.opacities.data(), from_ply.opacities.data(), 4 * 30) == 0);
  CHECK(std::memcmp(from_glb.scales.data(), from_ply.scales.data(), 4 * 90) == 0);
  CHECK(std::memcmp(from_glb.sh.data(), from_ply.sh.data(), 4 * from_ply.sh.size()) == 0);
  gaussians::write_gaussians(from_glb, dir / "flexsplat_conv_c.ply");
  const auto again = gaussians::read_gaussians(dir / "flexsplat_conv_c.ply");
  for (index_t i = 0; i < 30; ++i) CHECK(again.opacities(i) == Approx(set.opacities(i)).epsilon(1e-5).margin(1e-6));
  for (const char* f : {"flexsplat_conv_a.ply", "flexsplat_conv_b.glb", "flexsplat_conv_c.ply"})
    std::filesystem::remove(dir / f);
  CHECK_THROWS_WITH(gaussians::read_gaussians(dir / "x.splat"), Catch::Contains("unknown Gaussian file extension"));
  gltf::WriteOptions with_cameras;
  with_cameras.cameras = {flexsplat_test::test_camera(0, "front")};
  CHECK_THROWS_WITH(gaussians::write_gaussians(set, dir / "flexsplat_conv_d.ply", with_cameras),
                    Catch::Contains("cannot store the 1 cameras"));
}

TEST_CASE("PLY reader normalises training quaternions and accepts ASCII", "[ply]") {
  const std::string ascii =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
      "property float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\nproperty float opacity\n"
      "property float scale_0\nproperty float scale_1\nproperty float scale_2\nproperty float rot_0\n"
      "property float rot_1\nproperty float rot_2\nproperty float rot_3\nend_header\n"
      "1 2 3 0.1 0.2 0.3 0 -1 -2 -3 2 0 0 0\n"
      "4 5 6 0 0 0 100 0 0 0 0 0 0 -3\n";
  const auto set = decode_ply(ascii);
  REQUIRE(set.size() == 2);
  CHECK(set.sh_degree() == 0);
  CHECK(set.means(1, 2) == 6.0f);
  CHECK(set.opacities(0) == 0.5f);
  CHECK(set.opacities(1) == 1.0f);
  CHECK(set.scales(0, 2) == Approx(std::exp(-3.0)));
  CHECK(set.quats(0, 0) == 1.0f);
  CHECK(set.quats(1, 3) == -1.0f);
}

TEST_CASE("PLY reader rejects bad input with a clear message", "[ply]") {
  const auto good = ply::encode_ply(random_set(4, 1));
  const std::size_t body = header_of(good).size();
  SECTION("truncated body") {
    std::vector<unsigned char> cut(good.begin(), good.end() - 5);
    CHECK_THROWS_WITH(decode_ply(cut), Catch::Contains("declares 4 vertices") && Catch::Contains("truncated"));
  }
  SECTION("truncated header") {
    std::vector<unsigned char> cut(good.begin(), good.begin() + 60);
    CHECK_THROWS_WITH(decode_ply(cut), Catch::Contains("no 'end_header'"));
  }
  SECTION("not a PLY") {
    CHECK_THROWS_WITH(decode_ply(std::string("glTF....")), Catch::Contains("not a PLY file"));
  }
  SECTION("wrong vertex count") {
    std::string text(good.begin(), good.end());
    text.replace(text.find("element vertex 4"), 16, "element vertex 9");
    CHECK_THROWS_WITH(decode_ply(text), Catch::Contains("declares 9 vertices"));
  }
  SECTION("missing attribute") {
    std::string text(good.begin(), good.end());
    text.replace(text.find("property float opacity"), 22, "property float opacitx");
    CHECK_THROWS_WITH(decode_ply(text), Catch::Contains("no property 'opacity'"));
  }
  SECTION("incomplete SH") {
    std::string text(good.begin(), good.end());
    text.replace(text.find("property float f_rest_8"), 23, "property float g_rest_8");
    CHECK_THROWS_WITH(decode_ply(text), Catch::Contains("8 f_rest_* properties is not a multiple of 3"));
  }
  SECTION("big-endian") {
    std::string text(good.begin(), good.end());
    text.replace(text.find("binary_little_endian"), 20, "binary_big_endian");
    CHECK_THROWS_WITH(decode_ply(text), Catch::Contains("'binary_big_endian' is not supported"));
  }
  SECTION("NaN value") {
    auto bad = good;
    const float nan = std::nanf("");
    std::memcpy(bad.data() + body + 26 * 4 * 2 + 4, &nan, 4);  // y of vertex 2
    CHECK_THROWS_WITH(decode_ply(bad), Catch::Contains("property 'y' of vertex 2 is not finite"));
  }
  SECTION("zero quaternion") {
    auto bad = good;
    const float zero[4] = {0, 0, 0, 0};
    std::memcpy(bad.data() + body + 26 * 4 * 1 + 22 * 4, zero, 16);
    CHECK_THROWS_WITH(decode_ply(bad), Catch::Contains("rotation of vertex 1 is a zero quaternion"));
  }
}

TEST_CASE("PLY export clamps opacity and reports it", "[ply]") {
  auto set = random_set(3, 0);
  set.opacities(0) = 3.0f;
  ply::WriteReport report;
  const auto back = decode_ply(ply::encode_ply(set, &report));
  CHECK(report.repairs.opacities_clamped == 1);
  CHECK(back.opacities(0) == 1.0f);
}
