// The one cameras.json reader: the cameras it returns (sizes, K, R, t, names, orbit angles), one camera by index, and
// an error naming the source and the frame for each kind of bad input.
#include <catch2/catch.hpp>

#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "flexsplat/io/cameras_json.hpp"
#include "temp_dir.hpp"

using namespace flexsplat;

namespace cameras_json_test {

// Two orbit cameras of the shared renders' layout; frame 1 has its own size and no file name.
nlohmann::json two_cameras() {
  const Camera a = look_at({0, -3, 1}, {0, 0, 0}, 64, 48, intrinsics_from_fov(64, 48, 45.0));
  const Camera b = look_at({2, 2, 0.5}, {0, 0, 0}, 32, 32, intrinsics_from_fov(32, 32, 35.0));
  auto frame = [](const Camera& c) {
    double k[9], e[12];
    camera_arrays(c, k, e);
    nlohmann::json K = nlohmann::json::array(), w2c = nlohmann::json::array();
    for (int r = 0; r < 3; ++r) {
      K.push_back({k[3 * r], k[3 * r + 1], k[3 * r + 2]});
      w2c.push_back({e[4 * r], e[4 * r + 1], e[4 * r + 2], e[4 * r + 3]});
    }
    return nlohmann::json{{"K", K}, {"w2c", w2c}};
  };
  nlohmann::json doc = {{"width", 64}, {"height", 48}, {"frames", {frame(a), frame(b)}}};
  doc["frames"][0]["file"] = "images/000.png";
  doc["frames"][0]["elevation_deg"] = 20.0;
  doc["frames"][0]["azimuth_deg"] = 90.0;
  doc["frames"][1]["width"] = 32;
  doc["frames"][1]["height"] = 32;
  return doc;
}

}  // namespace cameras_json_test

using namespace cameras_json_test;

TEST_CASE("cameras.json gives one camera per frame with its size, name, orbit angles, K and w2c", "[io][cameras_json]") {
  const auto cams = io::parse_cameras_json(two_cameras(), "test");
  REQUIRE(cams.size() == 2);
  CHECK(cams[0].name == "images/000.png");
  CHECK(cams[1].name == "frame 1");
  CHECK((cams[0].width == 64 && cams[0].height == 48));
  CHECK((cams[1].width == 32 && cams[1].height == 32));
  CHECK(cams[0].elevation_deg == 20.0);
  CHECK(cams[0].azimuth_deg == 90.0);
  const Camera a = look_at({0, -3, 1}, {0, 0, 0}, 64, 48, intrinsics_from_fov(64, 48, 45.0));
  for (int c = 0; c < 3; ++c) {
    CHECK(cams[0].t[c] == a.t[c]);
    for (int r = 0; r < 3; ++r) {
      CHECK(cams[0].K[c][r] == a.K[c][r]);
      CHECK(cams[0].R[c][r] == a.R[c][r]);
    }
  }
  flexsplat_test::TempDir dir("cameras_json");
  const auto path = dir.path / "cameras.json";
  std::ofstream(path) << two_cameras().dump();
  CHECK(io::load_cameras_json(path).size() == 2);
  const auto one = io::load_camera_spec(path.string() + ":1");
  REQUIRE(one.size() == 1);
  CHECK(one[0].name == "frame 1");
  CHECK_THROWS_WITH(io::load_camera_spec(path.string() + ":2"), Catch::Contains("camera index 2 out of range (2 frames)"));
  CHECK_THROWS_WITH(io::load_camera_spec(path.string() + ":99999999999999999999"),
                    Catch::Contains("camera index 99999999999999999999 out of range"));
  CHECK_THROWS_WITH(io::load_cameras_json(dir.path / "absent.json"), Catch::Contains("absent.json") &&
                                                                         Catch::Contains("cannot open"));
}

TEST_CASE("cameras.json errors name the source, the frame and the field", "[io][cameras_json]") {
  auto fails = [](nlohmann::json doc, const std::string& what) {
    CHECK_THROWS_WITH(io::parse_cameras_json(doc, "cams.json"), Catch::Contains("'cams.json'") && Catch::Contains(what));
  };
  nlohmann::json d = two_cameras();
  d.erase("width");
  fails(d, "'width' must be an integer in [1, 65535]");
  d = two_cameras();
  d["frames"] = nlohmann::json::array();
  fails(d, "no non-empty 'frames' array");
  d = two_cameras();
  d["frames"][1] = 3;
  fails(d, "frame 1 is not an object");
  d = two_cameras();
  d["frames"][0]["K"][2][2] = 2.0;
  fails(d, "frame 0 'K' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]");
  d = two_cameras();
  d["frames"][1]["w2c"][0][0] = 2.0 * d["frames"][1]["w2c"][0][0].get<double>() + 1.0;
  fails(d, "frame 1 'w2c' rotation part is not a rotation");
  d = two_cameras();
  d["frames"][1]["w2c"][2] = {1, 2, 3};
  fails(d, "frame 1 'w2c' row 2 does not have 4 entries");
  d = two_cameras();
  d["frames"][0]["K"][0][1] = "0";
  fails(d, "frame 0 'K'[0][1] is not a number");
  d = two_cameras();
  d["frames"][1]["height"] = 0;
  fails(d, "frame 1 'height' must be an integer in [1, 65535]");
  fails(nlohmann::json::array(), "not a JSON object");
  // Text as Python's json module writes non-finite numbers, and text that is not JSON.
  std::string text = two_cameras().dump();
  text.replace(text.find("\"w2c\":[[") + 8, 1, "NaN,");
  CHECK_THROWS_WITH(io::parse_cameras_json_text(text, "py.json"),
                    Catch::Contains("'py.json'") && Catch::Contains("non-finite number ('NaN'"));
  CHECK_THROWS_WITH(io::parse_cameras_json_text("{\"width\": 3", "cut.json"),
                    Catch::Contains("'cut.json'") && Catch::Contains("not valid JSON"));
}
