// A capture's cameras in the formats users bring (COLMAP text and binary, transforms.json, cameras.json): each
// written and read back gives the same cameras; hand-written files in each tool's own layout read as that tool means
// them; photos are matched by file name; every kind of bad input is refused with the file and the entry named.
#include <catch2/catch.hpp>

#include <cmath>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/io/capture_cameras.hpp"
#include "temp_dir.hpp"

using namespace flexsplat;

namespace capture_cameras_test {

// Three cameras around the origin with unequal focal lengths and an off-centre principal point.
std::vector<Camera> capture() {
  std::vector<Camera> cams;
  const glm::dvec3 eyes[3] = {{0, -3, 1}, {2.5, 1.5, 0.2}, {-1, 2, 2.5}};
  for (int i = 0; i < 3; ++i) {
    glm::dmat3 K = intrinsics_from_fov(64, 48, 40.0 + 5 * i);
    K[1][1] *= 1.01;
    K[2][0] += 1.25 * i;
    Camera c = look_at(eyes[i], {0.1, 0, 0.2}, 64, 48, K);
    c.name = "img_" + std::to_string(i) + ".png";
    cams.push_back(c);
  }
  return cams;
}

double max_difference(const Camera& a, const Camera& b) {
  double d = std::abs(a.width - b.width) + std::abs(a.height - b.height);
  for (int c = 0; c < 3; ++c) {
    d = std::max(d, std::abs(a.t[c] - b.t[c]));
    for (int r = 0; r < 3; ++r) d = std::max({d, std::abs(a.K[c][r] - b.K[c][r]), std::abs(a.R[c][r] - b.R[c][r])});
  }
  return d;
}

void write_text(const std::filesystem::path& p, const std::string& text) {
  std::filesystem::create_directories(p.parent_path());
  std::ofstream(p, std::ios::binary) << text;
}

// The error message of `f`, or "" when it does not throw.
template <class F>
std::string error_of(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

}  // namespace capture_cameras_test

using namespace capture_cameras_test;

TEST_CASE("capture cameras: COLMAP text, COLMAP binary and transforms.json round-trip the cameras") {
  flexsplat_test::TempDir dir("capture_roundtrip");
  const std::vector<Camera> cams = capture();
  io::write_colmap_text(dir.path / "text", cams);
  io::write_colmap_binary(dir.path / "bin", cams);
  io::write_transforms_json(dir.path / "transforms.json", cams);
  for (const auto& [path, format] : {std::pair{dir.path / "text", io::CameraFormat::colmap},
                                     std::pair{dir.path / "bin", io::CameraFormat::colmap},
                                     std::pair{dir.path / "transforms.json", io::CameraFormat::transforms_json}}) {
    io::CameraFormat got{};
    const std::vector<Camera> back = io::load_capture_cameras(path, {}, &got);
    INFO(path.string());
    CHECK(got == format);
    REQUIRE(back.size() == cams.size());
    for (std::size_t i = 0; i < cams.size(); ++i) {
      CHECK(back[i].name == cams[i].name);
      CHECK(max_difference(back[i], cams[i]) < 1e-12);
    }
  }
  // A COLMAP workspace folder reads its sparse/0.
  io::write_colmap_text(dir.path / "ws" / "sparse" / "0", cams);
  CHECK(io::load_capture_cameras(dir.path / "ws").size() == 3);
}

TEST_CASE("capture cameras: hand-written files read as each tool means them") {
  flexsplat_test::TempDir dir("capture_handwritten");
  // COLMAP: camera 7 SIMPLE_RADIAL with zero distortion, a 90-degree turn about y (qw = qy = sqrt(1/2)), comments,
  // a name with a space and a points line.
  write_text(dir.path / "m" / "cameras.txt", "# comment\n7 SIMPLE_RADIAL 100 80 120 50 40 0\n");
  write_text(dir.path / "m" / "images.txt",
             "# IMAGE_ID ...\n3 0.70710678118654757 0 0.70710678118654757 0 1 2 3 7 my photo.png\n"
             "10.5 20.5 -1 11 12 4\n");
  const std::vector<Camera> c = io::load_capture_cameras(dir.path / "m");
  REQUIRE(c.size() == 1);
  CHECK(c[0].name == "my photo.png");
  CHECK(c[0].width == 100);
  CHECK(c[0].height == 80);
  CHECK(c[0].K[0][0] == 120);
  CHECK(c[0].K[1][1] == 120);
  CHECK(c[0].K[2][0] == 50);
  CHECK(c[0].K[2][1] == 40);
  // R maps world z to camera x: a world point on +z lands right of the image centre.
  CHECK(c[0].R[2][0] == Approx(1.0).margin(1e-12));  // column-major: R(row 0, col 2)
  CHECK(c[0].t[0] == 1);
  CHECK(c[0].t[2] == 3);
  // transforms.json in the NeRF synthetic layout: camera_angle_x only, file paths without extension, the size from
  // the image. The identity transform_matrix is an OpenGL camera at the origin looking down world -z.
  nlohmann::json doc = {{"camera_angle_x", 2 * std::atan(0.5)},
                        {"frames", {{{"file_path", "./train/r_0"},
                                     {"transform_matrix", {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 4}, {0, 0, 0, 1}}}}}}};
  write_text(dir.path / "t.json", doc.dump());
  const io::ImageSizeOf size_of = [](const std::string& f) -> std::optional<std::array<int, 2>> {
    if (f == "./train/r_0") return std::array<int, 2>{200, 100};
    return std::nullopt;
  };
  const std::vector<Camera> t = io::load_capture_cameras(dir.path / "t.json", size_of);
  REQUIRE(t.size() == 1);
  CHECK(t[0].K[0][0] == Approx(200.0));  // 0.5 w / tan(angle / 2)
  CHECK(t[0].K[1][1] == Approx(200.0));
  CHECK(t[0].K[2][0] == 100);
  CHECK(t[0].K[2][1] == 50);
  CHECK(t[0].centre().z == Approx(4.0));
  // OpenCV z (forward) is OpenGL -z: the camera looks down world -z, so the world origin is 4 in front of it.
  CHECK(t[0].to_camera({0, 0, 0}).z == Approx(4.0));
  CHECK(t[0].to_camera({0, 1, 0}).y == Approx(-1.0));  // OpenGL y up is OpenCV y down
  // Matched to photos by name; the extension-less capture name matches on the stem; a resized photo scales K.
  const std::vector<Camera> m =
      io::cameras_for_images(t, {"/data/photos/r_0.png"}, {{100, 50}}, "t.json");
  CHECK(m[0].name == "r_0.png");
  CHECK(m[0].K[0][0] == Approx(100.0));
  CHECK(m[0].K[2][1] == Approx(25.0));
  CHECK(m[0].width == 100);
}

TEST_CASE("capture cameras: bad files and bad matches are refused naming the file and the entry") {
  flexsplat_test::TempDir dir("capture_bad");
  const std::vector<Camera> cams = capture();
  auto colmap = [&](const std::string& cameras, const std::string& images) {
    write_text(dir.path / "c" / "cameras.txt", cameras);
    write_text(dir.path / "c" / "images.txt", images);
    return error_of([&] { io::load_capture_cameras(dir.path / "c"); });
  };
  const std::string cam1 = "1 PINHOLE 64 48 50 50 32 24\n";
  const std::string good_image = "1 1 0 0 0 0 0 0 1 a.png\n\n";
  CHECK(colmap(cam1, good_image).empty());
  CHECK_THAT(colmap("1 OPENCV 64 48 50 50 32 24 0.1 0 0 0\n", good_image),
             Catch::Contains("cameras.txt") && Catch::Contains("distortion parameter 0 = 0.1") &&
                 Catch::Contains("image_undistorter"));
  CHECK_THAT(colmap("1 OPENCV_FISHEYE 64 48 50 50 32 24 0 0 0 0\n", good_image),
             Catch::Contains("OPENCV_FISHEYE") && Catch::Contains("line 1"));
  CHECK_THAT(colmap("1 PINHOLE 64 48 0 50 32 24\n", good_image), Catch::Contains("focal length fx=0"));
  CHECK_THAT(colmap("1 PINHOLE 64 48 nan 50 32 24\n", good_image), Catch::Contains("parameter 0 is not finite"));
  CHECK_THAT(colmap("1 BROWN 64 48 50\n", good_image), Catch::Contains("unknown camera model 'BROWN'"));
  CHECK_THAT(colmap(cam1, "1 2 0 0 0 0 0 0 1 a.png\n\n"),
             Catch::Contains("images.txt") && Catch::Contains("line 1 (image 1 'a.png')") &&
                 Catch::Contains("has norm 2: not a rotation"));
  CHECK_THAT(colmap(cam1, "1 1 0 0 0 nan 0 0 1 a.png\n\n"), Catch::Contains("translation entry 0 is not finite"));
  CHECK_THAT(colmap(cam1, "1 1 0 0 0 0 0 0 5 a.png\n\n"), Catch::Contains("refers to camera 5"));
  CHECK_THAT(colmap(cam1, good_image + "2 1 0 0 0 0 0 0 1 a.png\n\n"),
             Catch::Contains("image name 'a.png' appears twice"));
  CHECK_THAT(colmap(cam1, "1 1 0 0 0 0 0\n"), Catch::Contains("fewer than 10 fields"));
  // Binary: truncated files name where they end.
  io::write_colmap_binary(dir.path / "b", cams);
  const std::string images = flexsplat_test::file_bytes(dir.path / "b" / "images.bin");
  write_text(dir.path / "b" / "images.bin", images.substr(0, images.size() - 5));
  CHECK_THAT(error_of([&] { io::load_capture_cameras(dir.path / "b"); }),
             Catch::Contains("images.bin") && Catch::Contains("truncated"));
  CHECK_THAT(error_of([&] { io::load_capture_cameras(dir.path / "none"); }), Catch::Contains("does not exist"));
  std::filesystem::create_directories(dir.path / "empty");
  CHECK_THAT(error_of([&] { io::load_capture_cameras(dir.path / "empty"); }),
             Catch::Contains("not a COLMAP model folder"));
  // transforms.json: a non-rotation, a NaN, a missing size, distortion, an unknown JSON layout.
  io::write_transforms_json(dir.path / "t.json", cams);
  nlohmann::json t = nlohmann::json::parse(flexsplat_test::file_bytes(dir.path / "t.json"));
  auto transforms = [&](const nlohmann::json& doc) {
    write_text(dir.path / "t2.json", doc.dump());
    return error_of([&] { io::load_capture_cameras(dir.path / "t2.json"); });
  };
  nlohmann::json bad = t;
  bad["frames"][1]["transform_matrix"][0][0] = 2.0;
  CHECK_THAT(transforms(bad), Catch::Contains("frame 1 ('img_1.png')") && Catch::Contains("not a rotation"));
  bad = t;
  bad["frames"][2]["fl_x"] = 0.0;
  CHECK_THAT(transforms(bad), Catch::Contains("frame 2") && Catch::Contains("fx=0"));
  bad = t;
  bad["frames"][0].erase("w");
  CHECK_THAT(transforms(bad), Catch::Contains("no 'w' / 'h'"));
  bad = t;
  bad["k1"] = 0.05;
  CHECK_THAT(transforms(bad), Catch::Contains("distortion k1 = 0.05"));
  write_text(dir.path / "t3.json", "{\"frames\": [{\"transform_matrix\": [[1, 0, 0, NaN]]}]}");
  CHECK_THAT(error_of([&] { io::load_capture_cameras(dir.path / "t3.json"); }),
             Catch::Contains("t3.json") && Catch::Contains("non-finite number"));
  CHECK_THAT(transforms({{"frames", {{{"name", "x"}}}}}), Catch::Contains("neither a transforms.json"));
  // Matching photos to cameras.
  CHECK_THAT(error_of([&] { io::cameras_for_images(cams, {"b/img_9.png"}, {{64, 48}}, "cams"); }),
             Catch::Contains("no camera for image 'b/img_9.png'") && Catch::Contains("img_0.png, img_1.png"));
  CHECK_THAT(error_of([&] { io::cameras_for_images(cams, {"img_0.png", "x/img_0.png"}, {{64, 48}, {64, 48}}, "cams"); }),
             Catch::Contains("'x/img_0.png': an image of this name is given twice"));
  std::vector<Camera> twice = cams;
  twice[1].name = "sub/img_0.png";
  CHECK_THAT(error_of([&] { io::cameras_for_images(twice, {"img_0.png"}, {{64, 48}}, "cams"); }),
             Catch::Contains("matches 2 cameras"));
  CHECK_THAT(error_of([&] { io::cameras_for_images(cams, {"img_0.png"}, {{64, 64}}, "cams"); }),
             Catch::Contains("another aspect ratio"));
  CHECK(io::cameras_for_images(cams, {"img_2.png", "img_0.png"}, {{64, 48}, {64, 48}}, "cams")[0].K[2][0] ==
        cams[2].K[2][0]);
}
