#pragma once
// The one cameras.json reader (the layout of the shared object renders: top-level width and height, "frames" each
// with an OpenCV "K" and a 3x4 world-to-camera "w2c"), used by the object folders of data/ and by the export and
// render commands. Every error names the source and the frame.
//
//   std::vector<Camera> cams = io::load_cameras_json("spot/cameras.json");
//   std::vector<Camera> one = io::load_camera_spec("spot/cameras.json:3");  // frame 3 only
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <utility>
#include <vector>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {
namespace io {

// A stored w2c rotation counts as a rotation when R^T R and det R are within this of I and 1 (float storage).
inline constexpr double kRotationTolerance = 1e-4;

namespace detail {

inline void read_camera_matrix(const nlohmann::json& frame, const char* key, int rows, int cols, double* out,
                               const std::string& source, std::size_t index) {
  if (!frame.contains(key) || !frame[key].is_array() || frame[key].size() != static_cast<std::size_t>(rows))
    fail_in(source, "frame ", index, " '", key, "' is not a ", rows, "x", cols, " matrix");
  for (int r = 0; r < rows; ++r) {
    const nlohmann::json& row = frame[key][static_cast<std::size_t>(r)];
    if (!row.is_array() || row.size() != static_cast<std::size_t>(cols))
      fail_in(source, "frame ", index, " '", key, "' row ", r, " does not have ", cols, " entries");
    for (int c = 0; c < cols; ++c) {
      const nlohmann::json& v = row[static_cast<std::size_t>(c)];
      if (!v.is_number()) fail_in(source, "frame ", index, " '", key, "'[", r, "][", c, "] is not a number");
      const double x = v.get<double>();
      if (!std::isfinite(x)) fail_in(source, "frame ", index, " '", key, "'[", r, "][", c, "] is not finite");
      out[r * cols + c] = x;
    }
  }
}

inline int image_size_field(const nlohmann::json& obj, const char* key, const std::string& source,
                            const std::string& where) {
  if (!obj.contains(key) || !obj[key].is_number_integer() || obj[key].get<long long>() < 1 ||
      obj[key].get<long long>() > 65535)
    fail_in(source, where, "'", key, "' must be an integer in [1, 65535]");
  return obj[key].get<int>();
}

}  // namespace detail

// Parses cameras.json text; `source` names it in errors. Python's json module writes NaN / Infinity, which JSON cannot
// hold: the error says so instead of reporting a bare syntax error.
inline nlohmann::json parse_cameras_json_text(const std::string& text, const std::string& source) {
  nlohmann::json doc;
  try {
    doc = nlohmann::json::parse(text);
  } catch (const nlohmann::json::parse_error& e) {
    const std::size_t at = e.byte > 0 ? std::min<std::size_t>(e.byte - 1, text.size()) : 0;
    const std::size_t start = text.find_last_of(",[:{ \n", at);
    const std::string token = text.substr(start == std::string::npos ? 0 : start + 1, 9);
    if (token.rfind("NaN", 0) == 0 || token.rfind("Infinity", 0) == 0 || token.rfind("-Infinity", 0) == 0)
      fail_in(source, "contains a non-finite number ('",
                                 token.substr(0, token.find_first_of(",]} \n")), "' near byte ", e.byte,
                                 "); every K and w2c entry must be finite");
    fail_in(source, "not valid JSON (", e.what(), ")");
  } catch (const nlohmann::json::exception& e) {
    if (e.id == 406) fail_in(source, "contains a non-finite number (", e.what(), ")");
    fail_in(source, "not valid JSON (", e.what(), ")");
  }
  if (!doc.is_object()) fail_in(source, "not a JSON object");
  return doc;
}

inline nlohmann::json read_cameras_json(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  if (!in) fail_in(file.string(), "cannot open");
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return parse_cameras_json_text(text, file.string());
}

// One camera per frame: the document's width and height (a frame's own "width"/"height" override them), K of the form
// [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, w2c's left 3x3 a rotation, every entry finite; the name is
// the frame's "file" (else "frame i"), the orbit angles its "elevation_deg" / "azimuth_deg" when present.
inline std::vector<Camera> parse_cameras_json(const nlohmann::json& doc, const std::string& source) {
  if (!doc.is_object()) fail_in(source, "not a JSON object");
  const int width = detail::image_size_field(doc, "width", source, "");
  const int height = detail::image_size_field(doc, "height", source, "");
  if (!doc.contains("frames") || !doc["frames"].is_array() || doc["frames"].empty())
    fail_in(source, "has no non-empty 'frames' array");
  std::vector<Camera> cameras;
  for (std::size_t i = 0; i < doc["frames"].size(); ++i) {
    const nlohmann::json& frame = doc["frames"][i];
    const std::string where = "frame " + std::to_string(i);
    if (!frame.is_object()) fail_in(source, where, " is not an object");
    double K[9], w2c[12];
    detail::read_camera_matrix(frame, "K", 3, 3, K, source, i);
    detail::read_camera_matrix(frame, "w2c", 3, 4, w2c, source, i);
    if (!(K[0] > 0 && K[4] > 0 && K[3] == 0 && K[6] == 0 && K[7] == 0 && K[8] == 1))
      fail_in(source, where, " 'K' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0");
    const int w = frame.contains("width") ? detail::image_size_field(frame, "width", source, where + " ") : width;
    const int h = frame.contains("height") ? detail::image_size_field(frame, "height", source, where + " ") : height;
    Camera cam = camera_from_arrays(K, w2c, w, h,
                                    frame.contains("file") && frame["file"].is_string() ? frame["file"].get<std::string>()
                                                                                        : where);
    const double err = rotation_defect(cam.R);
    if (!(err <= kRotationTolerance))
      fail_in(source, where, " 'w2c' rotation part is not a rotation (|R^T R - I|, |det R - 1| up to ",
                                 err, ")");
    if (frame.contains("elevation_deg") && frame["elevation_deg"].is_number())
      cam.elevation_deg = frame["elevation_deg"].get<double>();
    if (frame.contains("azimuth_deg") && frame["azimuth_deg"].is_number())
      cam.azimuth_deg = frame["azimuth_deg"].get<double>();
    cameras.push_back(std::move(cam));
  }
  return cameras;
}

inline std::vector<Camera> load_cameras_json(const std::filesystem::path& path) {
  return parse_cameras_json(read_cameras_json(path), path.string());
}

// "cameras.json" or "cameras.json:index" (one camera); an index out of range names the count.
inline std::vector<Camera> load_camera_spec(const std::string& spec) {
  const std::size_t colon = spec.rfind(':');
  if (colon != std::string::npos && colon + 1 < spec.size() &&
      spec.find_first_not_of("0123456789", colon + 1) == std::string::npos) {
    const std::vector<Camera> all = load_cameras_json(spec.substr(0, colon));
    const std::string digits = spec.substr(colon + 1);
    const std::size_t index = digits.size() > 9 ? all.size() : std::stoul(digits);
    require(index < all.size(), "'", spec, "': camera index ", digits, " out of range (", all.size(), " frames)");
    return {all[index]};
  }
  return load_cameras_json(spec);
}

}  // namespace io
}  // namespace v0
}  // namespace flexsplat
