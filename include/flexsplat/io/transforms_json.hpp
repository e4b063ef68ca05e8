#pragma once
// nerfstudio / instant-ngp transforms.json: one Camera per frame, named by its "file_path". Each frame's
// "transform_matrix" is camera-to-world in OpenGL axes (x right, y up, z backwards), turned here into the library's
// OpenCV world-to-camera; intrinsics "fl_x", "fl_y", "cx", "cy", "w", "h" (or the field of view "camera_angle_x" /
// "camera_angle_y") are read at the top level and may be overridden per frame, pixel centres at +0.5 as nerfstudio's
// rays. Distortion ("k1".."k4", "p1", "p2") other than zero and fisheye models are refused. Where "w" / "h" are absent
// (the NeRF synthetic scenes) `size_of` gives the image's size from its file.
//
//   std::vector<Camera> cams = io::load_transforms_json("capture/transforms.json", size_of);
//   io::write_transforms_json("out/transforms.json", cams);
#include <array>
#include <cmath>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/io/cameras_json.hpp"

namespace flexsplat {
inline namespace v0 {
namespace io {

// The size (width, height) of the image a frame's file_path names, if it can be had.
using ImageSizeOf = std::function<std::optional<std::array<int, 2>>(const std::string& file_path)>;

namespace transforms_detail {

// A numeric field of the frame, else of the document; nullopt where neither has it.
inline std::optional<double> field(const nlohmann::json& frame, const nlohmann::json& doc, const char* key,
                                   const std::string& source, const std::string& where) {
  for (const nlohmann::json* obj : {&frame, &doc}) {
    if (!obj->contains(key)) continue;
    const nlohmann::json& v = (*obj)[key];
    if (!v.is_number()) fail_in(source, where, " '", key, "' is not a number");
    const double x = v.get<double>();
    if (!std::isfinite(x)) fail_in(source, where, " '", key, "' is not finite");
    return x;
  }
  return std::nullopt;
}

}  // namespace transforms_detail

// The document (parsed by parse_cameras_json_text, which also names non-finite numbers); `source` names it in errors.
inline std::vector<Camera> parse_transforms_json(const nlohmann::json& doc, const std::string& source,
                                                 const ImageSizeOf& size_of = {}) {
  using transforms_detail::field;
  if (!doc.is_object()) fail_in(source, "not a JSON object");
  if (doc.contains("camera_model") && doc["camera_model"].is_string()) {
    const std::string model = doc["camera_model"].get<std::string>();
    if (model != "OPENCV" && model != "PINHOLE")
      fail_in(source, "camera_model '", model, "' is not a pinhole model (OPENCV or PINHOLE without distortion)");
  }
  if (!doc.contains("frames") || !doc["frames"].is_array() || doc["frames"].empty())
    fail_in(source, "has no non-empty 'frames' array");
  std::vector<Camera> cameras;
  for (std::size_t i = 0; i < doc["frames"].size(); ++i) {
    const nlohmann::json& frame = doc["frames"][i];
    std::string where = "frame " + std::to_string(i);
    if (!frame.is_object()) fail_in(source, where, " is not an object");
    if (!frame.contains("file_path") || !frame["file_path"].is_string() || frame["file_path"].get<std::string>().empty())
      fail_in(source, where, " has no 'file_path' string");
    const std::string file = frame["file_path"].get<std::string>();
    where += " ('" + file + "')";
    for (const char* k : {"k1", "k2", "k3", "k4", "p1", "p2"}) {
      const auto d = field(frame, doc, k, source, where);
      if (d && *d != 0.0)
        fail_in(source, where, " has distortion ", k, " = ", *d, "; flexsplat takes pinhole cameras: undistort the "
                "images first");
    }
    // Image size: the fields, else the image file.
    std::optional<double> w = field(frame, doc, "w", source, where), h = field(frame, doc, "h", source, where);
    if (!w || !h) {
      const auto size = size_of ? size_of(file) : std::nullopt;
      if (!size) fail_in(source, where, " has no 'w' / 'h' and its image's size is not known");
      if (!w) w = (*size)[0];
      if (!h) h = (*size)[1];
    }
    if (!(*w >= 1 && *w <= 65535 && *h >= 1 && *h <= 65535 && *w == std::floor(*w) && *h == std::floor(*h)))
      fail_in(source, where, " has image size ", *w, " x ", *h, " (integers in [1, 65535] needed)");
    // Focal lengths: fl_x / fl_y, else from the fields of view; a missing one takes the other's value.
    std::optional<double> fx = field(frame, doc, "fl_x", source, where), fy = field(frame, doc, "fl_y", source, where);
    const auto ax = field(frame, doc, "camera_angle_x", source, where), ay = field(frame, doc, "camera_angle_y", source, where);
    if (!fx && ax) fx = 0.5 * *w / std::tan(0.5 * *ax);
    if (!fy && ay) fy = 0.5 * *h / std::tan(0.5 * *ay);
    if (!fx && fy) fx = fy;
    if (!fy && fx) fy = fx;
    if (!fx) fail_in(source, where, " has no focal length ('fl_x', 'fl_y', 'camera_angle_x' or 'camera_angle_y')");
    if (!(*fx > 0 && *fy > 0 && std::isfinite(*fx) && std::isfinite(*fy)))
      fail_in(source, where, " has focal length fx=", *fx, " fy=", *fy, " (must be positive)");
    const double cx = field(frame, doc, "cx", source, where).value_or(0.5 * *w);
    const double cy = field(frame, doc, "cy", source, where).value_or(0.5 * *h);
    // transform_matrix: 4 x 4 (last row 0 0 0 1) or 3 x 4 camera-to-world.
    if (!frame.contains("transform_matrix") || !frame["transform_matrix"].is_array() ||
        (frame["transform_matrix"].size() != 4 && frame["transform_matrix"].size() != 3))
      fail_in(source, where, " 'transform_matrix' is not a 4x4 (or 3x4) matrix");
    double m[16] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1};
    const int rows = static_cast<int>(frame["transform_matrix"].size());
    detail::read_camera_matrix(frame, "transform_matrix", rows, 4, m, source, i);
    if (rows == 4 && !(m[12] == 0 && m[13] == 0 && m[14] == 0 && m[15] == 1))
      fail_in(source, where, " 'transform_matrix' last row is not [0, 0, 0, 1]");
    glm::dmat3 c2w;  // OpenGL camera axes -> OpenCV: y and z flip
    glm::dvec3 centre(m[3], m[7], m[11]);
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) c2w[c][r] = m[4 * r + c] * (c == 0 ? 1.0 : -1.0);
    const double err = rotation_defect(c2w);
    if (!(err <= kRotationTolerance))
      fail_in(source, where, " 'transform_matrix' rotation part is not a rotation (|R^T R - I|, |det R - 1| up to ",
              err, ")");
    Camera cam;
    cam.name = file;
    cam.width = static_cast<int>(*w), cam.height = static_cast<int>(*h);
    cam.K[0][0] = *fx, cam.K[1][1] = *fy, cam.K[2][0] = cx, cam.K[2][1] = cy;
    cam.R = glm::transpose(c2w);
    cam.t = -(cam.R * centre);
    cameras.push_back(std::move(cam));
  }
  return cameras;
}

inline std::vector<Camera> load_transforms_json(const std::filesystem::path& path, const ImageSizeOf& size_of = {}) {
  return parse_transforms_json(read_cameras_json(path), path.string(), size_of);
}

// A transforms.json of `cameras` (per-frame intrinsics; file_path is Camera::name, relative to the file's folder).
inline void write_transforms_json(const std::filesystem::path& path, const std::vector<Camera>& cameras) {
  check_cameras(cameras, "transforms.json writer");
  nlohmann::json doc;
  doc["camera_model"] = "PINHOLE";
  doc["frames"] = nlohmann::json::array();
  for (const Camera& c : cameras) {
    if (c.K[1][0] != 0.0) fail("transforms.json writer: camera '", c.name, "' has skew ", c.K[1][0], " (none allowed)");
    const glm::dmat3 c2w = glm::transpose(c.R);
    const glm::dvec3 centre = c.centre();
    nlohmann::json m = nlohmann::json::array();
    for (int r = 0; r < 3; ++r)  // OpenCV camera axes -> OpenGL: y and z flip
      m.push_back({c2w[0][r], -c2w[1][r], -c2w[2][r], centre[r]});
    m.push_back({0.0, 0.0, 0.0, 1.0});
    doc["frames"].push_back({{"file_path", c.name}, {"transform_matrix", m}, {"fl_x", c.K[0][0]}, {"fl_y", c.K[1][1]},
                             {"cx", c.K[2][0]}, {"cy", c.K[2][1]}, {"w", c.width}, {"h", c.height}});
  }
  write_file_atomic(path, "transforms.json writer", doc.dump(1));
}

}  // namespace io
}  // namespace v0
}  // namespace flexsplat
