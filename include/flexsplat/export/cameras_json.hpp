#pragma once
// Cameras from a cameras.json in the layout of the shared object renders (OpenCV K and 3x4 world-to-camera).
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gaussians {

inline std::vector<Camera> parse_cameras_json(const nlohmann::json& doc, const std::string& source) {
  require(doc.is_object(), source, ": cameras.json is not a JSON object");
  require(doc.contains("frames") && doc["frames"].is_array(), source, ": cameras.json has no 'frames' array");
  auto int_field = [&](const nlohmann::json& obj, const char* key, const std::string& where) {
    require(obj.contains(key) && obj[key].is_number_integer(), source, ": ", where, " has no integer '", key, "'");
    return obj[key].get<int>();
  };
  const int width = int_field(doc, "width", "cameras.json");
  const int height = int_field(doc, "height", "cameras.json");
  std::vector<Camera> cameras;
  for (std::size_t i = 0; i < doc["frames"].size(); ++i) {
    const nlohmann::json& frame = doc["frames"][i];
    const std::string where = "frame " + std::to_string(i);
    auto matrix = [&](const char* key, std::size_t rows, std::size_t cols, double* out) {
      require(frame.contains(key) && frame[key].is_array() && frame[key].size() == rows, source, ": ", where,
              " '", key, "' is not a ", rows, "x", cols, " matrix");
      for (std::size_t r = 0; r < rows; ++r) {
        const nlohmann::json& row = frame[key][r];
        require(row.is_array() && row.size() == cols, source, ": ", where, " '", key, "' row ", r, " does not have ",
                cols, " entries");
        for (std::size_t c = 0; c < cols; ++c) {
          require(row[c].is_number(), source, ": ", where, " '", key, "'[", r, "][", c, "] is not a number");
          out[r * cols + c] = row[c].get<double>();
        }
      }
    };
    double K[9], w2c[12];
    matrix("K", 3, 3, K);
    matrix("w2c", 3, 4, w2c);
    cameras.push_back(camera_from_arrays(
        K, w2c, frame.contains("width") ? int_field(frame, "width", where) : width,
        frame.contains("height") ? int_field(frame, "height", where) : height,
        frame.contains("file") && frame["file"].is_string() ? frame["file"].get<std::string>() : where));
  }
  return cameras;
}

inline std::vector<Camera> load_cameras_json(const std::filesystem::path& path) {
  std::ifstream in(path);
  require(in.good(), "cannot open '", path.string(), "'");
  nlohmann::json doc = nlohmann::json::parse(in, nullptr, false);
  require(!doc.is_discarded(), "'", path.string(), "' is not valid JSON");
  return parse_cameras_json(doc, path.string());
}

// "cameras.json" or "cameras.json:index" (one camera); an index out of range names the count.
inline std::vector<Camera> load_camera_spec(const std::string& spec) {
  const std::size_t colon = spec.rfind(':');
  if (colon != std::string::npos && colon + 1 < spec.size() &&
      spec.find_first_not_of("0123456789", colon + 1) == std::string::npos) {
    const std::vector<Camera> all = load_cameras_json(spec.substr(0, colon));
    const std::size_t index = std::stoul(spec.substr(colon + 1));
    require(index < all.size(), "'", spec, "': camera index ", index, " out of range (", all.size(), " frames)");
    return {all[index]};
  }
  return load_cameras_json(spec);
}

}  // namespace gaussians
}  // namespace v0
}  // namespace flexsplat
