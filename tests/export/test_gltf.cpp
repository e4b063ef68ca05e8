#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>

#include <nlohmann/json.hpp>

#include "export/random_set.hpp"
#include "flexsplat/export/gltf.hpp"

using namespace flexsplat;
using flexsplat_test::random_set;

namespace {

// The JSON chunk of a glb, parsed.
nlohmann::json glb_json(const std::vector<unsigned char>& glb) {
  std::uint32_t length = 0;
  std::memcpy(&length, glb.data() + 12, 4);
  return nlohmann::json::parse(glb.begin() + 20, glb.begin() + 20 + length);
}

std::vector<unsigned char> with_json(const std::vector<unsigned char>& glb, const nlohmann::json& json) {
  std::uint32_t old_length = 0;
  std::memcpy(&old_length, glb.data() + 12, 4);
  std::string text = json.dump();
  while (text.size() % 4) text += ' ';
  std::vector<unsigned char> out(glb.begin(), glb.begin() + 12);
  const std::uint32_t length = static_cast<std::uint32_t>(text.size());
  out.resize(20);
  std::memcpy(out.data() + 12, &length, 4);
  std::memcpy(out.data() + 16, glb.data() + 16, 4);
  out.insert(out.end(), text.begin(), text.end());
  out.insert(out.end(), glb.begin() + 20 + old_length, glb.end());
  const std::uint32_t total = static_cast<std::uint32_t>(out.size());
  std::memcpy(out.data() + 8, &total, 4);
  return out;
}

GaussianSet<float> decode(const std::vector<unsigned char>& glb) {
  return gltf::decode_glb(glb.data(), glb.size(), "test.glb");
}

}  // namespace

TEST_CASE("glb round trip is bit-exact for float attributes at every SH degree", "[gltf]") {
  for (int degree = 0; degree <= 3; ++degree) {
    auto set = random_set(37, degree, 11 + degree);
    const auto glb = gltf::encode_glb(set);
    const auto back = decode(glb);
    REQUIRE(back.size() == set.size());
    REQUIRE(back.sh_degree() == degree);
    CHECK(std::memcmp(back.means.data(), set.means.data(), 4 * set.means.size()) == 0);
    CHECK(std::memcmp(back.quats.data(), set.quats.data(), 4 * set.quats.size()) == 0);
    CHECK(std::memcmp(back.scales.data(), set.scales.data(), 4 * set.scales.size()) == 0);
    CHECK(std::memcmp(back.opacities.data(), set.opacities.data(), 4 * set.opacities.size()) == 0);
    CHECK(std::memcmp(back.sh.data(), set.sh.data(), 4 * set.sh.size()) == 0);
  }
}

TEST_CASE("glb JSON follows KHR_gaussian_splatting", "[gltf]") {
  auto set = random_set(20, 1);
  const auto json = glb_json(gltf::encode_glb(set));
  CHECK(json["extensionsUsed"] == nlohmann::json::array({"KHR_gaussian_splatting"}));
  CHECK(!json.contains("extensionsRequired"));
  const auto& prim = json["meshes"][0]["primitives"][0];
  CHECK(prim["mode"] == 0);
  const auto& ext = prim["extensions"]["KHR_gaussian_splatting"];
  CHECK(ext["kernel"] == "ellipse");  // a string, not the bool tinygltf makes of Value("ellipse")
  CHECK(ext["colorSpace"] == "srgb_rec709_display");
  const auto& attrs = prim["attributes"];
  for (const char* name : {"POSITION", "COLOR_0", "KHR_gaussian_splatting:ROTATION", "KHR_gaussian_splatting:SCALE",
                           "KHR_gaussian_splatting:OPACITY", "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0",
                           "KHR_gaussian_splatting:SH_DEGREE_1_COEF_0", "KHR_gaussian_splatting:SH_DEGREE_1_COEF_2"})
    CHECK(attrs.contains(name));
  CHECK(!attrs.contains("KHR_gaussian_splatting:SH_DEGREE_2_COEF_0"));
  const auto& pos = json["accessors"][attrs["POSITION"].get<int>()];
  CHECK(pos["type"] == "VEC3");
  CHECK(pos["min"].size() == 3);
  CHECK(pos["max"].size() == 3);
  const auto& rot = json["accessors"][attrs["KHR_gaussian_splatting:ROTATION"].get<int>()];
  CHECK(rot["type"] == "VEC4");
  CHECK(rot["componentType"] == 5126);
  const auto& op = json["accessors"][attrs["KHR_gaussian_splatting:OPACITY"].get<int>()];
  CHECK(op["type"] == "SCALAR");
}

TEST_CASE("glb stores quaternions x y z w", "[gltf]") {
  auto set = random_set(1, 0);
  const float q[4] = {0.5f, 0.5f, -0.5f, 0.5f};  // w x y z
  for (int c = 0; c < 4; ++c) set.quats(0, c) = q[c];
  const auto glb = gltf::encode_glb(set);
  const auto json = glb_json(glb);
  const int acc = json["meshes"][0]["primitives"][0]["attributes"]["KHR_gaussian_splatting:ROTATION"];
  const int view = json["accessors"][acc]["bufferView"];
  const std::size_t offset = json["bufferViews"][view]["byteOffset"].get<std::size_t>();
  std::uint32_t json_length = 0;
  std::memcpy(&json_length, glb.data() + 12, 4);
  float stored[4];
  std::memcpy(stored, glb.data() + 20 + json_length + 8 + offset, 16);
  CHECK(stored[0] == 0.5f);   // x
  CHECK(stored[1] == -0.5f);  // y
  CHECK(stored[2] == 0.5f);   // z
  CHECK(stored[3] == 0.5f);   // w
}

TEST_CASE("COLOR_0 fallback is SH_C0 * dc + 0.5, clamped, sRGB-decoded to linear, alpha = opacity", "[gltf]") {
  auto set = random_set(3, 0);
  set.sh(0, 0, 0) = 0.0f;                                       // 0.5 display
  set.sh(0, 0, 1) = float(0.5 / sh_c0);              // 1.0 display
  set.sh(0, 0, 2) = -5.0f;                                      // clamps to 0
  set.opacities(0) = 0.6f;
  const auto glb = gltf::encode_glb(set);
  const auto json = glb_json(glb);
  const int acc = json["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"];
  CHECK(json["accessors"][acc]["componentType"] == 5121);
  CHECK(json["accessors"][acc]["normalized"] == true);
  const int view = json["accessors"][acc]["bufferView"];
  const std::size_t offset = json["bufferViews"][view]["byteOffset"].get<std::size_t>();
  std::uint32_t json_length = 0;
  std::memcpy(&json_length, glb.data() + 12, 4);
  const unsigned char* rgba = glb.data() + 20 + json_length + 8 + offset;
  CHECK(int(rgba[0]) == 55);  // round(255 * ((0.5 + 0.055) / 1.055)^2.4) = round(54.6)
  CHECK(int(rgba[1]) == 255);
  CHECK(int(rgba[2]) == 0);
  CHECK(int(rgba[3]) == 153);
}

TEST_CASE("cameras become glTF camera nodes looking down -Z and come back exactly", "[gltf]") {
  auto set = random_set(10, 0);
  gltf::WriteOptions options;
  options.cameras = {flexsplat_test::test_camera(0, "front"), flexsplat_test::test_camera(135, "side")};
  const auto glb = gltf::encode_glb(set, options);
  const auto json = glb_json(glb);
  REQUIRE(json["cameras"].size() == 2);
  CHECK(json["cameras"][0]["type"] == "perspective");
  CHECK(json["cameras"][0]["perspective"]["yfov"].get<double>() == Approx(2 * std::atan(120.0 / 290.0)));
  CHECK(json["cameras"][0]["perspective"]["aspectRatio"].get<double>() == Approx((320.0 / 300) / (240.0 / 290)));
  // Camera 0 sits at (3, 0, 0.6) looking at the origin: glTF -Z axis of its node must point back to the origin.
  const auto& node = json["nodes"][1];
  CHECK(node["camera"] == 0);
  CHECK(node["translation"][0].get<double>() == Approx(3.0));
  CHECK(node["translation"][2].get<double>() == Approx(0.6));
  const double x = node["rotation"][0], y = node["rotation"][1], z = node["rotation"][2], w = node["rotation"][3];
  // Third column of the rotation matrix is the node's +Z; -Z must be along -(position).
  const double zx = 2 * (x * z + w * y), zy = 2 * (y * z - w * x), zz = 1 - 2 * (x * x + y * y);
  const double n = std::sqrt(9 + 0.36);
  CHECK(-zx == Approx(-3 / n));
  CHECK(-zy == Approx(0).margin(1e-12));
  CHECK(-zz == Approx(-0.6 / n));
  // Node +Y (camera up) has a positive world-z component.
  CHECK(2 * (y * z + w * x) > 0);
  std::vector<Camera> back;
  gltf::decode_glb(glb.data(), glb.size(), "test.glb", &back);
  REQUIRE(back.size() == 2);
  for (int k = 0; k < 2; ++k) {
    CHECK(back[k].name == options.cameras[k].name);
    CHECK(back[k].width == 320);
    CHECK(back[k].height == 240);
    double K0[9], E0[12], K1[9], E1[12];
    camera_arrays(options.cameras[k], K0, E0);
    camera_arrays(back[k], K1, E1);
    for (int i = 0; i < 9; ++i) CHECK(K1[i] == K0[i]);
    for (int i = 0; i < 12; ++i) CHECK(E1[i] == Approx(E0[i]).margin(1e-12));
  }
}

TEST_CASE("quantised attributes shrink the file with bounded error", "[gltf]") {
  auto set = random_set(400, 0, 3);
  gltf::WriteReport plain_report, small_report;
  const auto plain = gltf::encode_glb(set, {}, &plain_report);
  gltf::WriteOptions options;
  options.rotation = gltf::RotationEncoding::Int8Normalized;
  options.scale = gltf::UnitEncoding::UInt16Normalized;
  options.opacity = gltf::UnitEncoding::UInt8Normalized;
  const auto small = gltf::encode_glb(set, options, &small_report);
  CHECK(small_report.bytes == small.size());
  // Rotation 16 -> 4 bytes, scale 12 -> 8 bytes; an 8-bit scalar is padded to 4 bytes, so opacity saves nothing.
  // The JSON grows a little (normalized flags, byte strides), by far less than one Gaussian's saving per 10.
  CHECK(plain.size() - small.size() <= 400 * (12 + 4));
  CHECK(plain.size() - small.size() >= 400 * (12 + 4) - 200);
  const auto back = decode(small);
  double max_angle = 0, max_scale = 0, max_opacity = 0;
  for (index_t i = 0; i < set.size(); ++i) {
    double dot = 0;
    for (int c = 0; c < 4; ++c) dot += double(set.quats(i, c)) * back.quats(i, c);
    max_angle = std::max(max_angle, 2 * std::acos(std::min(1.0, std::abs(dot))));
    for (int c = 0; c < 3; ++c) max_scale = std::max(max_scale, double(std::abs(set.scales(i, c) - back.scales(i, c))));
    max_opacity = std::max(max_opacity, double(std::abs(set.opacities(i) - back.opacities(i))));
  }
  CHECK(max_scale <= 0.5 / 65535 + 1e-7);
  CHECK(max_opacity <= 0.5 / 255 + 1e-7);
  CHECK(max_angle < 0.03);  // radians; int8 components carry 1/254 of error each
  CHECK(max_angle > 1e-4);  // the encoding really was lossy
}

TEST_CASE("glb export clamps opacities and reports the count", "[gltf]") {
  auto set = random_set(5, 0);
  set.opacities(1) = 1.2f;
  set.opacities(2) = -0.1f;
  gltf::WriteReport report;
  const auto glb = gltf::encode_glb(set, {}, &report);
  CHECK(report.repairs.opacities_clamped == 2);
  const auto back = decode(glb);
  CHECK(back.opacities(1) == 1.0f);
  CHECK(back.opacities(2) == 0.0f);
}

TEST_CASE("glb export refuses NaN and scales a normalized encoding cannot hold", "[gltf]") {
  auto set = random_set(5, 0);
  SECTION("NaN") {
    set.sh(3, 0, 1) = std::numeric_limits<float>::quiet_NaN();
    CHECK_THROWS_WITH(gltf::encode_glb(set), Catch::Contains("'sh' has a non-finite value") && Catch::Contains("Gaussian 3"));
  }
  SECTION("scale above one") {
    set.scales(4, 0) = 2.0f;
    gltf::WriteOptions options;
    options.scale = gltf::UnitEncoding::UInt8Normalized;
    CHECK_THROWS_WITH(gltf::encode_glb(set, options), Catch::Contains("exceeds 1"));
  }
}

TEST_CASE("glb reader rejects malformed files with a clear message", "[gltf]") {
  auto set = random_set(6, 1);
  const auto glb = gltf::encode_glb(set);
  SECTION("truncated") {
    std::vector<unsigned char> cut(glb.begin(), glb.end() - 40);
    CHECK_THROWS_WITH(decode(cut), Catch::Contains("truncated"));
  }
  SECTION("too short") {
    std::vector<unsigned char> cut(glb.begin(), glb.begin() + 7);
    CHECK_THROWS_WITH(decode(cut), Catch::Contains("too short"));
  }
  SECTION("not glTF") {
    auto bad = glb;
    bad[0] = 'X';
    CHECK_THROWS_WITH(decode(bad), Catch::Contains("magic"));
  }
  SECTION("JSON garbage") {
    auto bad = glb;
    bad[20] = '#';
    CHECK_THROWS_WITH(decode(bad), Catch::Contains("invalid glb"));
  }
  auto json = glb_json(glb);
  auto& prim = json["meshes"][0]["primitives"][0];
  SECTION("missing attribute") {
    prim["attributes"].erase("KHR_gaussian_splatting:SCALE");
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("'KHR_gaussian_splatting:SCALE' is missing"));
  }
  SECTION("partial SH degree") {
    prim["attributes"].erase("KHR_gaussian_splatting:SH_DEGREE_1_COEF_1");
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("partially defined"));
  }
  SECTION("wrong element count") {
    json["accessors"][prim["attributes"]["KHR_gaussian_splatting:OPACITY"].get<int>()]["count"] = 5;
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("count 5 differs from POSITION count 6"));
  }
  SECTION("count larger than the data") {
    for (auto& acc : json["accessors"]) acc["count"] = 1000;
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("do not fit"));
  }
  SECTION("wrong mode") {
    prim["mode"] = 4;
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("requires POINTS"));
  }
  SECTION("missing extension object") {
    prim.erase("extensions");
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("found 0"));
  }
  SECTION("kernel that is not a string") {
    prim["extensions"]["KHR_gaussian_splatting"]["kernel"] = true;
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("no string 'kernel'"));
  }
  SECTION("node transform on the splats") {
    json["nodes"][0]["translation"] = {1.0, 0.0, 0.0};
    CHECK_THROWS_WITH(decode(with_json(glb, json)), Catch::Contains("non-identity transform"));
  }
}

TEST_CASE("glb reader rejects invalid values", "[gltf]") {
  auto set = random_set(6, 0);
  SECTION("non-unit quaternion") {
    const auto glb = gltf::encode_glb(set);
    // Scale the stored x y z w of Gaussian 2 in place by 1.5.
    const auto json = glb_json(glb);
    const int acc = json["meshes"][0]["primitives"][0]["attributes"]["KHR_gaussian_splatting:ROTATION"];
    const std::size_t offset = json["bufferViews"][json["accessors"][acc]["bufferView"].get<int>()]["byteOffset"];
    std::uint32_t json_length = 0;
    std::memcpy(&json_length, glb.data() + 12, 4);
    auto patched = glb;
    float* q = reinterpret_cast<float*>(patched.data() + 20 + json_length + 8 + offset) + 2 * 4;
    for (int c = 0; c < 4; ++c) q[c] *= 1.5f;
    CHECK_THROWS_WITH(decode(patched), Catch::Contains("rotation of Gaussian 2 is not a unit quaternion"));
  }
  SECTION("opacity outside [0, 1] and NaN") {
    const auto glb = gltf::encode_glb(set);
    const auto json = glb_json(glb);
    const int acc = json["meshes"][0]["primitives"][0]["attributes"]["KHR_gaussian_splatting:OPACITY"];
    const std::size_t offset = json["bufferViews"][json["accessors"][acc]["bufferView"].get<int>()]["byteOffset"];
    std::uint32_t json_length = 0;
    std::memcpy(&json_length, glb.data() + 12, 4);
    auto patched = glb;
    float* o = reinterpret_cast<float*>(patched.data() + 20 + json_length + 8 + offset);
    o[4] = 1.25f;
    CHECK_THROWS_WITH(decode(patched), Catch::Contains("opacity of Gaussian 4 is 1.25"));
    o[4] = std::numeric_limits<float>::quiet_NaN();
    CHECK_THROWS_WITH(decode(patched), Catch::Contains("'opacities' has a non-finite value"));
  }
}

TEST_CASE("glb files on disk", "[gltf]") {
  auto set = random_set(9, 2);
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_test_export.glb";
  const auto report = gltf::write_glb(set, path);
  CHECK(report.bytes == std::filesystem::file_size(path));
  const auto back = gltf::read_glb(path);
  CHECK(back.size() == 9);
  std::filesystem::remove(path);
  CHECK_THROWS_WITH(gltf::read_glb(path), Catch::Contains("cannot open"));
}
