#pragma once
// COLMAP sparse models (cameras.txt + images.txt, or cameras.bin + images.bin): one Camera per registered image,
// named by the image's NAME. COLMAP's cameras are OpenCV axes with pixel centres at +0.5 and world-to-camera
// quaternions (w, x, y, z), the library's own convention, so the values pass through unchanged. Pinhole models only:
// SIMPLE_PINHOLE and PINHOLE, and SIMPLE_RADIAL, RADIAL and OPENCV when their distortion is zero; any other distortion
// is refused (undistort the images first: `colmap image_undistorter` writes a PINHOLE model). Every error names the
// file and the entry. The writers give other tools a capture's cameras (one PINHOLE camera per image).
//
//   std::vector<Camera> cams = io::load_colmap("capture/sparse/0");   // text or binary, whichever the folder holds
//   io::write_colmap_text("out/sparse/0", cams);                       // or write_colmap_binary
#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <glm/glm.hpp>
#include <glm/gtc/quaternion.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {
namespace io {

// A stored quaternion counts as a rotation when its norm is within this of 1 (COLMAP writes unit quaternions).
inline constexpr double kQuaternionNormTolerance = 1e-3;

namespace colmap_detail {

// COLMAP's camera models by id (src/colmap/sensor/models.h): name and parameter count.
struct ModelInfo {
  const char* name;
  int params;
};
inline constexpr std::array<ModelInfo, 11> models{{{"SIMPLE_PINHOLE", 3},
                                                   {"PINHOLE", 4},
                                                   {"SIMPLE_RADIAL", 4},
                                                   {"RADIAL", 5},
                                                   {"OPENCV", 8},
                                                   {"OPENCV_FISHEYE", 8},
                                                   {"FULL_OPENCV", 12},
                                                   {"FOV", 5},
                                                   {"SIMPLE_RADIAL_FISHEYE", 4},
                                                   {"RADIAL_FISHEYE", 5},
                                                   {"THIN_PRISM_FISHEYE", 12}}};

inline int model_id(const std::string& name) {
  for (std::size_t i = 0; i < models.size(); ++i)
    if (name == models[i].name) return static_cast<int>(i);
  return -1;
}

struct Intrinsics {
  int width = 0, height = 0;
  glm::dmat3 K{1.0};
};

// K from a model's parameters; distortion other than zero, fisheye and unknown models are refused.
inline Intrinsics intrinsics(int model, long long width, long long height, const std::vector<double>& p,
                             const std::string& source, const std::string& where) {
  if (model < 0 || model >= static_cast<int>(models.size())) fail_in(source, where, " has unknown camera model id ", model);
  const ModelInfo& m = models[static_cast<std::size_t>(model)];
  if (static_cast<int>(p.size()) != m.params)
    fail_in(source, where, " (", m.name, ") has ", p.size(), " parameters; the model has ", m.params);
  if (width < 1 || width > 65535 || height < 1 || height > 65535)
    fail_in(source, where, " has image size ", width, " x ", height, " (each side must be in [1, 65535])");
  for (std::size_t i = 0; i < p.size(); ++i)
    if (!std::isfinite(p[i])) fail_in(source, where, " (", m.name, ") parameter ", i, " is not finite");
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::size_t first_distortion = p.size();
  switch (model) {
    case 0: case 2: case 3: fx = fy = p[0], cx = p[1], cy = p[2], first_distortion = 3; break;
    case 1: case 4: fx = p[0], fy = p[1], cx = p[2], cy = p[3], first_distortion = 4; break;
    default:
      fail_in(source, where, " uses camera model ", m.name, ", which flexsplat does not read; undistort the images "
              "to a PINHOLE model first (colmap image_undistorter)");
  }
  for (std::size_t i = first_distortion; i < p.size(); ++i)
    if (p[i] != 0.0)
      fail_in(source, where, " (", m.name, ") has distortion parameter ", i - first_distortion, " = ", p[i],
              "; flexsplat takes pinhole cameras: undistort the images first (colmap image_undistorter writes a "
              "PINHOLE model)");
  if (!(fx > 0) || !(fy > 0)) fail_in(source, where, " (", m.name, ") has focal length fx=", fx, " fy=", fy, " (must be positive)");
  Intrinsics out;
  out.width = static_cast<int>(width), out.height = static_cast<int>(height);
  out.K[0][0] = fx, out.K[1][1] = fy, out.K[2][0] = cx, out.K[2][1] = cy;
  return out;
}

// World-to-camera from COLMAP's (qw, qx, qy, qz) and t; refuses a non-unit or non-finite quaternion.
inline void pose(Camera& cam, const double q[4], const double t[3], const std::string& source, const std::string& where) {
  for (int i = 0; i < 4; ++i)
    if (!std::isfinite(q[i])) fail_in(source, where, " quaternion entry ", i, " is not finite");
  for (int i = 0; i < 3; ++i)
    if (!std::isfinite(t[i])) fail_in(source, where, " translation entry ", i, " is not finite");
  const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(std::abs(norm - 1.0) <= kQuaternionNormTolerance))
    fail_in(source, where, " quaternion (", q[0], ", ", q[1], ", ", q[2], ", ", q[3], ") has norm ", norm,
            ": not a rotation");
  cam.R = glm::mat3_cast(glm::dquat(q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm));
  cam.t = glm::dvec3(t[0], t[1], t[2]);
}

inline Camera make_camera(const std::map<long long, Intrinsics>& intr, long long camera_id, const double q[4],
                          const double t[3], std::string name, const std::string& source, const std::string& where) {
  const auto it = intr.find(camera_id);
  if (it == intr.end()) fail_in(source, where, " refers to camera ", camera_id, ", which the cameras file does not define");
  if (name.empty()) fail_in(source, where, " has an empty image name");
  Camera cam;
  cam.name = std::move(name);
  cam.width = it->second.width, cam.height = it->second.height;
  cam.K = it->second.K;
  pose(cam, q, t, source, where);
  return cam;
}

inline void check_unique_names(const std::vector<Camera>& cams, const std::string& source) {
  std::map<std::string, std::size_t> seen;
  for (std::size_t i = 0; i < cams.size(); ++i) {
    const auto [it, fresh] = seen.emplace(cams[i].name, i);
    if (!fresh) fail_in(source, "image name '", cams[i].name, "' appears twice (entries ", it->second, " and ", i, ")");
  }
}

inline std::string read_all(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  if (!in) fail_in(file.string(), "cannot open");
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

// Lines without the comments ('#') and blank lines, with their 1-based numbers.
inline std::vector<std::pair<int, std::string>> content_lines(const std::string& text, bool keep_blank) {
  std::vector<std::pair<int, std::string>> out;
  std::istringstream in(text);
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    const std::size_t first = line.find_first_not_of(" \t");
    if (first != std::string::npos && line[first] == '#') continue;
    if (first == std::string::npos && !keep_blank) continue;
    out.emplace_back(number, line);
  }
  return out;
}

// Strict number parsing: the whole token, finite or not (the callers check finiteness where it matters).
inline double number(const std::string& token, const std::string& source, const std::string& where, const char* what) {
  char* end = nullptr;
  errno = 0;
  const double x = std::strtod(token.c_str(), &end);
  if (token.empty() || end != token.c_str() + token.size())
    fail_in(source, where, " ", what, " '", token, "' is not a number");
  return x;
}

inline long long integer(const std::string& token, const std::string& source, const std::string& where, const char* what) {
  char* end = nullptr;
  errno = 0;
  const long long x = std::strtoll(token.c_str(), &end, 10);
  if (token.empty() || end != token.c_str() + token.size() || errno == ERANGE)
    fail_in(source, where, " ", what, " '", token, "' is not an integer");
  return x;
}

// Bounds-checked little-endian reader of a binary model file.
struct Reader {
  const std::string& bytes;
  const std::string& source;
  std::size_t at = 0;
  template <class V>
  V get(const char* what) {
    if (bytes.size() - at < sizeof(V))
      fail_in(source, "ends at byte ", bytes.size(), " inside ", what, " (truncated file)");
    V v;
    std::memcpy(&v, bytes.data() + at, sizeof(V));
    at += sizeof(V);
    return v;
  }
  // A count of records of at least `record_bytes` each, refused if the rest of the file cannot hold them.
  std::uint64_t count(const char* what, std::size_t record_bytes) {
    const auto n = get<std::uint64_t>(what);
    if (n > (bytes.size() - at) / record_bytes)
      fail_in(source, what, " is ", n, " but the remaining ", bytes.size() - at, " bytes cannot hold that many");
    return n;
  }
};

}  // namespace colmap_detail

// cameras.txt and images.txt contents; the sources name them in errors.
inline std::vector<Camera> parse_colmap_text(const std::string& cameras_txt, const std::string& images_txt,
                                             const std::string& cameras_source, const std::string& images_source) {
  using namespace colmap_detail;
  std::map<long long, Intrinsics> intr;
  for (const auto& [line_no, line] : content_lines(cameras_txt, false)) {
    const std::string where = "line " + std::to_string(line_no);
    std::istringstream in(line);
    std::vector<std::string> tok{std::istream_iterator<std::string>(in), std::istream_iterator<std::string>()};
    if (tok.size() < 4) fail_in(cameras_source, where, " has ", tok.size(), " fields; expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]");
    const long long id = integer(tok[0], cameras_source, where, "CAMERA_ID");
    const int model = model_id(tok[1]);
    if (model < 0) fail_in(cameras_source, where, " has unknown camera model '", tok[1], "'");
    std::vector<double> p;
    for (std::size_t i = 4; i < tok.size(); ++i) p.push_back(number(tok[i], cameras_source, where, "parameter"));
    const Intrinsics k = intrinsics(model, integer(tok[2], cameras_source, where, "WIDTH"),
                                    integer(tok[3], cameras_source, where, "HEIGHT"), p, cameras_source,
                                    where + " (camera " + std::to_string(id) + ")");
    if (!intr.emplace(id, k).second) fail_in(cameras_source, where, " defines camera ", id, " a second time");
  }
  if (intr.empty()) fail_in(cameras_source, "defines no camera");
  std::vector<Camera> cams;
  // Each image is two lines: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its 2-D points (possibly blank).
  const auto lines = content_lines(images_txt, true);
  for (std::size_t i = 0; i < lines.size(); ++i) {
    const auto& [line_no, line] = lines[i];
    if (line.find_first_not_of(" \t") == std::string::npos) continue;
    const std::string where = "line " + std::to_string(line_no);
    std::istringstream in(line);
    std::string tok[9];
    for (auto& t : tok)
      if (!(in >> t)) fail_in(images_source, where, " has fewer than 10 fields; expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
    std::string name;
    std::getline(in >> std::ws, name);
    while (!name.empty() && (name.back() == ' ' || name.back() == '\t')) name.pop_back();
    const std::string entry = where + " (image " + tok[0] + (name.empty() ? "" : " '" + name + "'") + ")";
    (void)integer(tok[0], images_source, where, "IMAGE_ID");
    double q[4], t[3];
    for (int k = 0; k < 4; ++k) q[k] = number(tok[1 + k], images_source, where, "quaternion entry");
    for (int k = 0; k < 3; ++k) t[k] = number(tok[5 + k], images_source, where, "translation entry");
    cams.push_back(make_camera(intr, integer(tok[8], images_source, where, "CAMERA_ID"), q, t, name, images_source, entry));
    ++i;  // the points line
  }
  if (cams.empty()) fail_in(images_source, "has no registered image");
  check_unique_names(cams, images_source);
  return cams;
}

// cameras.bin and images.bin contents (COLMAP's little-endian binary model).
inline std::vector<Camera> parse_colmap_binary(const std::string& cameras_bin, const std::string& images_bin,
                                               const std::string& cameras_source, const std::string& images_source) {
  using namespace colmap_detail;
  std::map<long long, Intrinsics> intr;
  Reader rc{cameras_bin, cameras_source};
  const std::uint64_t n_cameras = rc.count("the camera count", 24);
  for (std::uint64_t i = 0; i < n_cameras; ++i) {
    const std::string where = "camera record " + std::to_string(i);
    const auto id = rc.get<std::int32_t>("a camera id");
    const auto model = rc.get<std::int32_t>("a camera model id");
    const auto width = rc.get<std::uint64_t>("a camera width");
    const auto height = rc.get<std::uint64_t>("a camera height");
    if (model < 0 || model >= static_cast<int>(models.size()))
      fail_in(cameras_source, where, " (camera ", id, ") has unknown camera model id ", model);
    std::vector<double> p(static_cast<std::size_t>(models[static_cast<std::size_t>(model)].params));
    for (double& x : p) x = rc.get<double>("camera parameters");
    const Intrinsics k = intrinsics(model, static_cast<long long>(std::min<std::uint64_t>(width, 1u << 30)),
                                    static_cast<long long>(std::min<std::uint64_t>(height, 1u << 30)), p,
                                    cameras_source, where + " (camera " + std::to_string(id) + ")");
    if (!intr.emplace(id, k).second) fail_in(cameras_source, where, " defines camera ", id, " a second time");
  }
  if (rc.at != cameras_bin.size())
    fail_in(cameras_source, cameras_bin.size() - rc.at, " bytes follow the last camera record");
  if (intr.empty()) fail_in(cameras_source, "defines no camera");
  std::vector<Camera> cams;
  Reader ri{images_bin, images_source};
  const std::uint64_t n_images = ri.count("the image count", 4 + 56 + 4 + 1 + 8);
  for (std::uint64_t i = 0; i < n_images; ++i) {
    const std::string where = "image record " + std::to_string(i);
    const auto id = ri.get<std::int32_t>("an image id");
    double q[4], t[3];
    for (double& x : q) x = ri.get<double>("a quaternion");
    for (double& x : t) x = ri.get<double>("a translation");
    const auto camera_id = ri.get<std::int32_t>("a camera id");
    const std::size_t end = images_bin.find('\0', ri.at);
    if (end == std::string::npos) fail_in(images_source, where, " (image ", id, ") has an unterminated name (truncated file)");
    std::string name = images_bin.substr(ri.at, end - ri.at);
    ri.at = end + 1;
    const std::uint64_t points = ri.count("a 2-D point count", 24);
    ri.at += static_cast<std::size_t>(points) * 24;
    cams.push_back(make_camera(intr, camera_id, q, t, std::move(name), images_source,
                               where + " (image " + std::to_string(id) + ")"));
  }
  if (ri.at != images_bin.size())
    fail_in(images_source, images_bin.size() - ri.at, " bytes follow the last image record");
  if (cams.empty()) fail_in(images_source, "has no registered image");
  check_unique_names(cams, images_source);
  return cams;
}

namespace colmap_detail {
// A camera as COLMAP's PINHOLE parameters and (qw, qx, qy, qz), t; a skewed K has no COLMAP model.
inline void pinhole(const Camera& c, double p[4], double q[4], double t[3]) {
  if (c.K[1][0] != 0.0) fail("COLMAP writer: camera '", c.name, "' has skew ", c.K[1][0], " (PINHOLE has none)");
  p[0] = c.K[0][0], p[1] = c.K[1][1], p[2] = c.K[2][0], p[3] = c.K[2][1];
  const glm::dquat r = glm::normalize(glm::quat_cast(c.R));
  q[0] = r.w, q[1] = r.x, q[2] = r.y, q[3] = r.z;
  for (int i = 0; i < 3; ++i) t[i] = c.t[i];
}
}  // namespace colmap_detail

// A COLMAP text model of `cameras` in `dir` (created): one PINHOLE camera per image, images named by Camera::name.
inline void write_colmap_text(const std::filesystem::path& dir, const std::vector<Camera>& cameras) {
  check_cameras(cameras, "COLMAP writer");
  std::filesystem::create_directories(dir);
  std::ostringstream cams, imgs;
  cams.precision(17), imgs.precision(17);
  cams << "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n";
  imgs << "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
          "#   POINTS2D[] as (X, Y, POINT3D_ID)\n";
  for (std::size_t i = 0; i < cameras.size(); ++i) {
    double p[4], q[4], t[3];
    colmap_detail::pinhole(cameras[i], p, q, t);
    cams << i + 1 << " PINHOLE " << cameras[i].width << " " << cameras[i].height << " " << p[0] << " " << p[1] << " "
         << p[2] << " " << p[3] << "\n";
    imgs << i + 1 << " " << q[0] << " " << q[1] << " " << q[2] << " " << q[3] << " " << t[0] << " " << t[1] << " "
         << t[2] << " " << i + 1 << " " << cameras[i].name << "\n\n";
  }
  write_file_atomic(dir / "cameras.txt", "COLMAP writer", cams.str());
  write_file_atomic(dir / "images.txt", "COLMAP writer", imgs.str());
}

// The same as COLMAP's binary model (cameras.bin, images.bin; no 2-D points).
inline void write_colmap_binary(const std::filesystem::path& dir, const std::vector<Camera>& cameras) {
  check_cameras(cameras, "COLMAP writer");
  std::filesystem::create_directories(dir);
  std::string cams, imgs;
  auto put = [](std::string& out, auto v) { out.append(reinterpret_cast<const char*>(&v), sizeof(v)); };
  put(cams, static_cast<std::uint64_t>(cameras.size()));
  put(imgs, static_cast<std::uint64_t>(cameras.size()));
  for (std::size_t i = 0; i < cameras.size(); ++i) {
    double p[4], q[4], t[3];
    colmap_detail::pinhole(cameras[i], p, q, t);
    put(cams, static_cast<std::int32_t>(i + 1));
    put(cams, static_cast<std::int32_t>(1));  // PINHOLE
    put(cams, static_cast<std::uint64_t>(cameras[i].width));
    put(cams, static_cast<std::uint64_t>(cameras[i].height));
    for (double x : p) put(cams, x);
    put(imgs, static_cast<std::int32_t>(i + 1));
    for (double x : q) put(imgs, x);
    for (double x : t) put(imgs, x);
    put(imgs, static_cast<std::int32_t>(i + 1));
    imgs.append(cameras[i].name);
    imgs.push_back('\0');
    put(imgs, static_cast<std::uint64_t>(0));
  }
  write_file_atomic(dir / "cameras.bin", "COLMAP writer", cams);
  write_file_atomic(dir / "images.bin", "COLMAP writer", imgs);
}

// True if `dir` holds a COLMAP model (the text or the binary pair).
inline bool is_colmap_model(const std::filesystem::path& dir) {
  namespace fs = std::filesystem;
  return (fs::is_regular_file(dir / "cameras.txt") && fs::is_regular_file(dir / "images.txt")) ||
         (fs::is_regular_file(dir / "cameras.bin") && fs::is_regular_file(dir / "images.bin"));
}

// A COLMAP model folder: the text pair if present, else the binary pair; a folder holding neither but a
// sparse/0 (COLMAP's workspace layout) reads that.
inline std::vector<Camera> load_colmap(const std::filesystem::path& dir) {
  using namespace colmap_detail;
  if (!is_colmap_model(dir) && is_colmap_model(dir / "sparse" / "0")) return load_colmap(dir / "sparse" / "0");
  if (std::filesystem::is_regular_file(dir / "cameras.txt") && std::filesystem::is_regular_file(dir / "images.txt"))
    return parse_colmap_text(read_all(dir / "cameras.txt"), read_all(dir / "images.txt"), (dir / "cameras.txt").string(),
                             (dir / "images.txt").string());
  if (std::filesystem::is_regular_file(dir / "cameras.bin") && std::filesystem::is_regular_file(dir / "images.bin"))
    return parse_colmap_binary(read_all(dir / "cameras.bin"), read_all(dir / "images.bin"), (dir / "cameras.bin").string(),
                               (dir / "images.bin").string());
  fail_in(dir.string(), "is not a COLMAP model folder (it holds neither cameras.txt + images.txt nor cameras.bin + "
          "images.bin, nor a sparse/0 that does)");
}

}  // namespace io
}  // namespace v0
}  // namespace flexsplat
