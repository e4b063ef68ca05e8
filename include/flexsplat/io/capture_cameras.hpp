#pragma once
// The cameras a capture brings, in whichever format: a COLMAP sparse model folder (io/colmap.hpp), a nerfstudio /
// instant-ngp transforms.json (io/transforms_json.hpp) or the project's cameras.json (io/cameras_json.hpp), and the
// camera of each photo, matched by file name. Cameras of the capture that no photo names are allowed (a capture's
// held-out views); a photo without a camera, a name two cameras share, a photo given twice are errors naming the file.
//
//   std::vector<Camera> cams = io::load_capture_cameras("capture/sparse/0");
//   std::vector<Camera> mine = io::cameras_for_images(cams, {"a.png", "b.png"}, sizes, "capture/sparse/0");
#include <array>
#include <cmath>
#include <cstddef>
#include <filesystem>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/io/colmap.hpp"
#include "flexsplat/io/transforms_json.hpp"

namespace flexsplat {
inline namespace v0 {
namespace io {

enum class CameraFormat { colmap, transforms_json, cameras_json };

inline const char* camera_format_name(CameraFormat f) {
  switch (f) {
    case CameraFormat::colmap: return "COLMAP model";
    case CameraFormat::transforms_json: return "transforms.json";
    case CameraFormat::cameras_json: return "cameras.json";
  }
  return "?";
}

// A folder is a COLMAP model; a JSON file whose first frame has "transform_matrix" is a transforms.json, one whose
// first frame has "w2c" a cameras.json.
inline CameraFormat camera_format(const std::filesystem::path& path, const nlohmann::json* doc = nullptr) {
  if (std::filesystem::is_directory(path)) return CameraFormat::colmap;
  require(doc, "camera format of '", path.string(), "': not a folder and no document given");
  if (doc->is_object() && doc->contains("frames") && (*doc)["frames"].is_array() && !(*doc)["frames"].empty() &&
      (*doc)["frames"][0].is_object()) {
    const nlohmann::json& f = (*doc)["frames"][0];
    if (f.contains("transform_matrix")) return CameraFormat::transforms_json;
    if (f.contains("w2c")) return CameraFormat::cameras_json;
  }
  fail_in(path.string(), "is neither a transforms.json (frames with 'transform_matrix') nor a cameras.json (frames with "
          "'w2c')");
}

// Every camera of the capture at `path`; size_of gives image sizes a transforms.json leaves out.
inline std::vector<Camera> load_capture_cameras(const std::filesystem::path& path, const ImageSizeOf& size_of = {},
                                                CameraFormat* format = nullptr) {
  if (!std::filesystem::exists(path)) fail_in(path.string(), "does not exist (expected a COLMAP model folder, a "
                                              "transforms.json or a cameras.json)");
  if (std::filesystem::is_directory(path)) {
    if (format) *format = CameraFormat::colmap;
    return load_colmap(path);
  }
  const nlohmann::json doc = read_cameras_json(path);
  const CameraFormat f = camera_format(path, &doc);
  if (format) *format = f;
  if (f == CameraFormat::transforms_json) return parse_transforms_json(doc, path.string(), size_of);
  return parse_cameras_json(doc, path.string());
}

namespace capture_detail {
inline std::string file_name(const std::string& p) { return std::filesystem::path(p).filename().string(); }
inline std::string stem(const std::string& p) { return std::filesystem::path(p).stem().string(); }
}  // namespace capture_detail

// The camera of each image (by its file name; a capture name without extension, as the NeRF synthetic scenes write,
// matches on the stem), with K carried to the image's own size (width, height) when the camera was calibrated at
// another size of the same aspect ratio. `source` names the camera file in errors.
inline std::vector<Camera> cameras_for_images(const std::vector<Camera>& capture, const std::vector<std::string>& images,
                                              const std::vector<std::array<int, 2>>& sizes, const std::string& source) {
  using namespace capture_detail;
  require(sizes.size() == images.size(), "cameras for images: ", sizes.size(), " sizes for ", images.size(), " images");
  std::set<std::string> given;
  std::vector<Camera> out;
  for (std::size_t i = 0; i < images.size(); ++i) {
    const std::string name = file_name(images[i]);
    if (!given.insert(name).second) fail("'", images[i], "': an image of this name is given twice");
    std::vector<std::size_t> hits;
    for (std::size_t c = 0; c < capture.size(); ++c)
      if (file_name(capture[c].name) == name) hits.push_back(c);
    if (hits.empty())
      for (std::size_t c = 0; c < capture.size(); ++c)
        if (std::filesystem::path(capture[c].name).extension().empty() && file_name(capture[c].name) == stem(name))
          hits.push_back(c);
    if (hits.empty()) {
      std::string names;
      for (std::size_t c = 0; c < capture.size() && c < 8; ++c) names += (c ? ", " : "") + capture[c].name;
      if (capture.size() > 8) names += ", ...";
      fail_in(source, "has no camera for image '", images[i], "' (matched by file name '", name, "'; its ",
              capture.size(), " cameras are ", names, ")");
    }
    if (hits.size() > 1)
      fail_in(source, "image '", images[i], "' matches ", hits.size(), " cameras ('", capture[hits[0]].name, "' and '",
              capture[hits[1]].name, "'): the file name is ambiguous");
    Camera cam = capture[hits[0]];
    const int W = sizes[i][0], H = sizes[i][1];
    if (W != cam.width || H != cam.height) {
      const double sx = static_cast<double>(W) / cam.width, sy = static_cast<double>(H) / cam.height;
      if (!(std::abs(sx / sy - 1.0) <= 0.01))
        fail_in(source, "camera '", cam.name, "' is for a ", cam.width, " x ", cam.height, " image but '", images[i],
                "' is ", W, " x ", H, " (another aspect ratio)");
      cam.K[0][0] *= sx, cam.K[1][0] *= sx, cam.K[2][0] *= sx;  // column-major: fx, skew, cx
      cam.K[1][1] *= sy, cam.K[2][1] *= sy;
      cam.width = W, cam.height = H;
    }
    cam.name = name;
    out.push_back(std::move(cam));
  }
  check_cameras(out, source);
  return out;
}

// The capture's camera of each photo (file paths, their sizes (width, height) in the same order): the capture at
// `path` read with the photos' sizes for what a transforms.json leaves out, then matched as cameras_for_images does.
inline std::vector<Camera> cameras_for_photos(const std::filesystem::path& path, const std::vector<std::string>& photos,
                                              const std::vector<std::array<int, 2>>& sizes,
                                              CameraFormat* format = nullptr) {
  using namespace capture_detail;
  require(sizes.size() == photos.size(), "cameras for photos: ", sizes.size(), " sizes for ", photos.size(), " photos");
  const ImageSizeOf size_of = [&](const std::string& file) -> std::optional<std::array<int, 2>> {
    for (std::size_t i = 0; i < photos.size(); ++i)
      if (file_name(photos[i]) == file_name(file) || stem(photos[i]) == file_name(file)) return sizes[i];
    return std::nullopt;
  };
  return cameras_for_images(load_capture_cameras(path, size_of, format), photos, sizes, path.string());
}

}  // namespace io
}  // namespace v0
}  // namespace flexsplat
