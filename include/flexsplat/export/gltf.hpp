#pragma once
// glTF binary (.glb) writer and reader for KHR_gaussian_splatting (Khronos release candidate), through tinygltf 2.7.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <tiny_gltf.h>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/export/gaussian_set.hpp"

namespace flexsplat {
inline namespace v0 {
namespace gltf {

inline const std::string kExtension = "KHR_gaussian_splatting";
inline const std::string kAttributePrefix = "KHR_gaussian_splatting:";

// Rotation may be stored as float or as signed normalised integers (spec table); w x y z becomes x y z w in the file.
enum class RotationEncoding { Float, Int8Normalized, Int16Normalized };
// Scale and opacity: float or unsigned normalised integers (scale then needs every value <= 1).
enum class UnitEncoding { Float, UInt8Normalized, UInt16Normalized };

struct WriteOptions {
  RotationEncoding rotation = RotationEncoding::Float;
  UnitEncoding scale = UnitEncoding::Float;
  UnitEncoding opacity = UnitEncoding::Float;
  bool color_fallback = true;  // COLOR_0 for clients without the extension
  std::vector<Camera> cameras;  // written as glTF camera nodes
  std::string color_space = "srgb_rec709_display";
};

struct WriteReport {
  gaussians::ExportRepairs repairs;
  std::size_t bytes = 0;
};

namespace detail {

inline constexpr int kFloat = TINYGLTF_COMPONENT_TYPE_FLOAT;
inline constexpr int kI8 = TINYGLTF_COMPONENT_TYPE_BYTE;
inline constexpr int kU8 = TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE;
inline constexpr int kI16 = TINYGLTF_COMPONENT_TYPE_SHORT;
inline constexpr int kU16 = TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT;

inline int component_size(int component_type) {
  switch (component_type) {
    case kFloat: return 4;
    case kI8: case kU8: return 1;
    case kI16: case kU16: return 2;
    default: return 0;
  }
}

inline const char* component_name(int component_type) {
  switch (component_type) {
    case kFloat: return "float";
    case kI8: return "signed byte";
    case kU8: return "unsigned byte";
    case kI16: return "signed short";
    case kU16: return "unsigned short";
    case TINYGLTF_COMPONENT_TYPE_INT: return "signed int";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: return "unsigned int";
    default: return "unknown component type";
  }
}

// Normalised-integer decoding as the glTF spec defines it (signed values clamp at -1).
inline double dequantize(int component_type, double raw) {
  switch (component_type) {
    case kI8: return std::max(raw / 127.0, -1.0);
    case kU8: return raw / 255.0;
    case kI16: return std::max(raw / 32767.0, -1.0);
    case kU16: return raw / 65535.0;
    default: return raw;
  }
}

inline double quantize_max(int component_type) {
  switch (component_type) {
    case kI8: return 127.0;
    case kU8: return 255.0;
    case kI16: return 32767.0;
    case kU16: return 65535.0;
    default: return 1.0;
  }
}

// Appends one attribute as its own buffer view; elements padded to 4 bytes as glTF requires for vertex attributes.
struct AttributeWriter {
  tinygltf::Model& model;
  std::vector<unsigned char>& bin;

  int add(const std::vector<double>& values, int components, int component_type, bool normalized,
          const std::string& name, bool with_min_max = false) {
    const std::size_t count = components ? values.size() / static_cast<std::size_t>(components) : 0;
    const int csize = component_size(component_type);
    const int element = components * csize;
    const int stride = (element + 3) / 4 * 4;
    while (bin.size() % 4) bin.push_back(0);
    const std::size_t offset = bin.size();
    bin.resize(offset + count * static_cast<std::size_t>(stride), 0);
    const double qmax = quantize_max(component_type);
    for (std::size_t i = 0; i < count; ++i)
      for (int c = 0; c < components; ++c) {
        const double v = values[i * components + c];
        unsigned char* dst = bin.data() + offset + i * stride + c * csize;
        if (component_type == kFloat) {
          const float f = static_cast<float>(v);
          std::memcpy(dst, &f, 4);
        } else {
          const double q = std::round(std::clamp(v, component_type == kU8 || component_type == kU16 ? 0.0 : -1.0,
                                                 1.0) * qmax);
          if (component_type == kI8) { const auto x = static_cast<std::int8_t>(q); std::memcpy(dst, &x, 1); }
          if (component_type == kU8) { const auto x = static_cast<std::uint8_t>(q); std::memcpy(dst, &x, 1); }
          if (component_type == kI16) { const auto x = static_cast<std::int16_t>(q); std::memcpy(dst, &x, 2); }
          if (component_type == kU16) { const auto x = static_cast<std::uint16_t>(q); std::memcpy(dst, &x, 2); }
        }
      }
    tinygltf::BufferView view;
    view.buffer = 0;
    view.byteOffset = offset;
    view.byteLength = count * static_cast<std::size_t>(stride);
    view.byteStride = stride != element ? static_cast<std::size_t>(stride) : 0;
    view.target = TINYGLTF_TARGET_ARRAY_BUFFER;
    view.name = name;
    model.bufferViews.push_back(view);

    tinygltf::Accessor acc;
    acc.bufferView = static_cast<int>(model.bufferViews.size()) - 1;
    acc.byteOffset = 0;
    acc.componentType = component_type;
    acc.normalized = normalized;
    acc.count = count;
    acc.type = components == 1 ? TINYGLTF_TYPE_SCALAR : components == 3 ? TINYGLTF_TYPE_VEC3 : TINYGLTF_TYPE_VEC4;
    acc.name = name;
    if (with_min_max && count > 0) {
      acc.minValues.assign(components, std::numeric_limits<double>::infinity());
      acc.maxValues.assign(components, -std::numeric_limits<double>::infinity());
      for (std::size_t i = 0; i < count; ++i)
        for (int c = 0; c < components; ++c) {
          // Bounds of the stored float values, so the validator's exact comparison holds.
          const double v = static_cast<float>(values[i * components + c]);
          acc.minValues[c] = std::min(acc.minValues[c], v);
          acc.maxValues[c] = std::max(acc.maxValues[c], v);
        }
    }
    model.accessors.push_back(acc);
    return static_cast<int>(model.accessors.size()) - 1;
  }
};

inline int rotation_component(RotationEncoding e) {
  return e == RotationEncoding::Float ? kFloat : e == RotationEncoding::Int8Normalized ? kI8 : kI16;
}
inline int unit_component(UnitEncoding e) {
  return e == UnitEncoding::Float ? kFloat : e == UnitEncoding::UInt8Normalized ? kU8 : kU16;
}

inline double srgb_to_linear(double c) {
  return c <= 0.04045 ? c / 12.92 : std::pow((c + 0.055) / 1.055, 2.4);
}

inline std::string sh_attribute(int degree, int coefficient) {
  return kAttributePrefix + "SH_DEGREE_" + std::to_string(degree) + "_COEF_" + std::to_string(coefficient);
}

// OpenCV world-to-camera to a glTF camera node: glTF cameras look down -Z with +Y up (180 degrees about X).
inline void camera_to_node(const Camera& cam, tinygltf::Node& node) {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R(r, c) = cam.R[c][r];
    t(r) = cam.t[r];
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(R, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d Rn = svd.matrixU() * svd.matrixV().transpose();
  require(Rn.determinant() > 0 && (Rn - R).norm() < 1e-4, "camera '", cam.name,
          "': w2c rotation is not a proper rotation");
  const Eigen::Vector3d centre = -Rn.transpose() * t;
  const Eigen::Matrix3d c2w_gl = Rn.transpose() * Eigen::Vector3d(1, -1, -1).asDiagonal();
  Eigen::Quaterniond q(c2w_gl);
  q.normalize();
  node.translation = {centre.x(), centre.y(), centre.z()};
  node.rotation = {q.x(), q.y(), q.z(), q.w()};
}

inline Eigen::Matrix4d node_local_matrix(const tinygltf::Node& node) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  if (node.matrix.size() == 16) {
    for (int c = 0; c < 4; ++c)
      for (int r = 0; r < 4; ++r) m(r, c) = node.matrix[c * 4 + r];  // glTF matrices are column-major
    return m;
  }
  Eigen::Matrix3d rs = Eigen::Matrix3d::Identity();
  if (node.rotation.size() == 4)
    rs = Eigen::Quaterniond(node.rotation[3], node.rotation[0], node.rotation[1], node.rotation[2])
             .normalized()
             .toRotationMatrix();
  if (node.scale.size() == 3) rs = rs * Eigen::Vector3d(node.scale[0], node.scale[1], node.scale[2]).asDiagonal();
  m.topLeftCorner<3, 3>() = rs;
  if (node.translation.size() == 3) m.topRightCorner<3, 1>() << node.translation[0], node.translation[1], node.translation[2];
  return m;
}

inline std::vector<Eigen::Matrix4d> global_matrices(const tinygltf::Model& model, const std::string& source) {
  const std::size_t n = model.nodes.size();
  std::vector<int> parent(n, -1);
  for (std::size_t i = 0; i < n; ++i)
    for (int child : model.nodes[i].children) {
      require(child >= 0 && static_cast<std::size_t>(child) < n, source, ": node ", i, " has child index ", child,
              " out of range");
      require(parent[child] < 0, source, ": node ", child, " has two parents");
      parent[child] = static_cast<int>(i);
    }
  std::vector<Eigen::Matrix4d> global(n);
  for (std::size_t i = 0; i < n; ++i) {
    Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
    std::size_t hops = 0;
    for (int k = static_cast<int>(i); k >= 0; k = parent[k]) {
      require(++hops <= n, source, ": node hierarchy has a cycle through node ", i);
      m = node_local_matrix(model.nodes[k]) * m;
    }
    global[i] = m;
  }
  return global;
}

// Reads accessor `index` as doubles (normalised integers decoded), checking type, component type and bounds.
inline std::vector<double> read_accessor(const tinygltf::Model& model, int index, const std::string& semantic,
                                         int expected_type, const std::vector<int>& allowed_components,
                                         bool require_normalized_ints, std::size_t expected_count,
                                         const std::string& source, int* component_out = nullptr) {
  const std::string what = source + ": attribute '" + semantic + "'";
  require(index >= 0 && static_cast<std::size_t>(index) < model.accessors.size(), what, ": accessor index ", index,
          " out of range (", model.accessors.size(), " accessors)");
  const tinygltf::Accessor& acc = model.accessors[index];
  require(!acc.sparse.isSparse, what, ": sparse accessors are not supported");
  require(acc.type == expected_type, what, ": accessor type ", acc.type, " is not ",
          expected_type == TINYGLTF_TYPE_SCALAR ? "SCALAR" : expected_type == TINYGLTF_TYPE_VEC3 ? "VEC3" : "VEC4");
  require(std::find(allowed_components.begin(), allowed_components.end(), acc.componentType) !=
              allowed_components.end(),
          what, ": component type ", component_name(acc.componentType), " is not allowed here");
  if (acc.componentType != kFloat && require_normalized_ints)
    require(acc.normalized, what, ": integer component type ", component_name(acc.componentType),
            " must be normalized");
  require(acc.count == expected_count, what, ": accessor count ", acc.count, " differs from POSITION count ",
          expected_count);
  if (component_out) *component_out = acc.componentType;
  const int components = expected_type == TINYGLTF_TYPE_SCALAR ? 1 : expected_type == TINYGLTF_TYPE_VEC3 ? 3 : 4;
  std::vector<double> out(expected_count * components);
  if (expected_count == 0) return out;
  require(acc.bufferView >= 0 && static_cast<std::size_t>(acc.bufferView) < model.bufferViews.size(), what,
          ": buffer view index ", acc.bufferView, " out of range");
  const tinygltf::BufferView& view = model.bufferViews[acc.bufferView];
  require(view.buffer >= 0 && static_cast<std::size_t>(view.buffer) < model.buffers.size(), what,
          ": buffer index ", view.buffer, " out of range");
  const std::vector<unsigned char>& data = model.buffers[view.buffer].data;
  require(view.byteOffset <= data.size() && view.byteLength <= data.size() - view.byteOffset, what,
          ": buffer view [", view.byteOffset, ", +", view.byteLength, ") exceeds buffer of ", data.size(), " bytes");
  const std::size_t csize = static_cast<std::size_t>(component_size(acc.componentType));
  const std::size_t element = csize * components;
  const std::size_t stride = view.byteStride ? view.byteStride : element;
  require(stride >= element, what, ": byte stride ", stride, " is smaller than an element (", element, " bytes)");
  const std::size_t room = view.byteLength >= acc.byteOffset ? view.byteLength - acc.byteOffset : 0;
  require(acc.byteOffset <= view.byteLength && element <= room && (expected_count - 1) <= (room - element) / stride,
          what, ": ", expected_count, " elements of ", element, " bytes (stride ", stride, ") at offset ",
          acc.byteOffset, " do not fit in a buffer view of ", view.byteLength, " bytes");
  const unsigned char* base = data.data() + view.byteOffset + acc.byteOffset;
  for (std::size_t i = 0; i < expected_count; ++i)
    for (int c = 0; c < components; ++c) {
      const unsigned char* p = base + i * stride + c * csize;
      double v = 0;
      switch (acc.componentType) {
        case kFloat: { float f; std::memcpy(&f, p, 4); v = f; break; }
        case kI8: { std::int8_t x; std::memcpy(&x, p, 1); v = x; break; }
        case kU8: { std::uint8_t x; std::memcpy(&x, p, 1); v = x; break; }
        case kI16: { std::int16_t x; std::memcpy(&x, p, 2); v = x; break; }
        case kU16: { std::uint16_t x; std::memcpy(&x, p, 2); v = x; break; }
        default: break;
      }
      out[i * components + c] = acc.normalized ? dequantize(acc.componentType, v) : v;
    }
  return out;
}

}  // namespace detail

// Encodes a set as .glb bytes. Opacities outside [0, 1] are clamped and non-unit quaternions renormalised (counted
// in the report); NaN, negative scales and zero quaternions are errors.
template <class T>
std::vector<unsigned char> encode_glb(const GaussianSet<T>& input, const WriteOptions& options = {},
                                      WriteReport* report = nullptr) {
  using namespace detail;
  GaussianSet<double> set = convert_gaussian_set<double>(input);
  const gaussians::ExportRepairs repairs = gaussians::repair_for_export(set, "glb export");
  const std::size_t n = static_cast<std::size_t>(set.size());
  const int degree = set.sh_degree();
  if (options.scale != UnitEncoding::Float)
    for (index_t i = 0; i < set.scales.size(); ++i)
      require(set.scales.data()[i] <= 1.0, "glb export: scale ", set.scales.data()[i], " of Gaussian ", i / 3,
              " exceeds 1 and cannot be stored as a normalized integer; use float scales");

  tinygltf::Model model;
  std::vector<unsigned char> bin;
  AttributeWriter writer{model, bin};
  tinygltf::Primitive prim;
  prim.mode = TINYGLTF_MODE_POINTS;  // tinygltf's default of -1 would be written out as an invalid mode

  std::vector<double> values(n * 3);
  for (std::size_t i = 0; i < n; ++i)
    for (int c = 0; c < 3; ++c) values[i * 3 + c] = set.means(i, c);
  prim.attributes["POSITION"] = writer.add(values, 3, kFloat, false, "POSITION", true);

  if (options.color_fallback) {
    std::vector<double> color(n * 4);
    const bool srgb = options.color_space == "srgb_rec709_display";
    for (std::size_t i = 0; i < n; ++i) {
      for (int c = 0; c < 3; ++c) {
        const double display = std::clamp(sh_c0 * set.sh(i, 0, c) + sh_color_offset, 0.0, 1.0);
        color[i * 4 + c] = srgb ? srgb_to_linear(display) : display;  // COLOR_0 is linear by glTF's definition
      }
      color[i * 4 + 3] = set.opacities(i);
    }
    prim.attributes["COLOR_0"] = writer.add(color, 4, kU8, true, "COLOR_0");
  }

  std::vector<double> rot(n * 4);
  for (std::size_t i = 0; i < n; ++i) {
    // Integer encodings flip q to -q (same rotation) so that w >= 0; floats are stored untouched for exact reads.
    const double sign = options.rotation != RotationEncoding::Float && set.quats(i, 0) < 0 ? -1.0 : 1.0;
    for (int c = 0; c < 3; ++c) rot[i * 4 + c] = sign * set.quats(i, c + 1);
    rot[i * 4 + 3] = sign * set.quats(i, 0);
  }
  const int rot_type = rotation_component(options.rotation);
  prim.attributes[kAttributePrefix + "ROTATION"] = writer.add(rot, 4, rot_type, rot_type != kFloat, "ROTATION");

  for (std::size_t i = 0; i < n; ++i)
    for (int c = 0; c < 3; ++c) values[i * 3 + c] = set.scales(i, c);
  const int scale_type = unit_component(options.scale);
  prim.attributes[kAttributePrefix + "SCALE"] = writer.add(values, 3, scale_type, scale_type != kFloat, "SCALE");

  std::vector<double> opacity(set.opacities.data(), set.opacities.data() + n);
  const int opacity_type = unit_component(options.opacity);
  prim.attributes[kAttributePrefix + "OPACITY"] =
      writer.add(opacity, 1, opacity_type, opacity_type != kFloat, "OPACITY");

  for (int l = 0; l <= degree; ++l)
    for (int m = 0; m < 2 * l + 1; ++m) {
      const int k = l * l + m;
      for (std::size_t i = 0; i < n; ++i)
        for (int c = 0; c < 3; ++c) values[i * 3 + c] = set.sh(i, k, c);
      const std::string name = sh_attribute(l, m);
      prim.attributes[name] = writer.add(values, 3, kFloat, false, name.substr(kAttributePrefix.size()));
    }

  tinygltf::Value::Object ext;
  // std::string, not a literal: tinygltf::Value(const char*) would pick the bool constructor.
  ext["kernel"] = tinygltf::Value(std::string("ellipse"));
  ext["colorSpace"] = tinygltf::Value(std::string(options.color_space));
  ext["projection"] = tinygltf::Value(std::string("perspective"));
  ext["sortingMethod"] = tinygltf::Value(std::string("cameraDistance"));
  prim.extensions[kExtension] = tinygltf::Value(ext);

  tinygltf::Mesh mesh;
  mesh.name = "gaussians";
  mesh.primitives.push_back(prim);
  model.meshes.push_back(mesh);
  tinygltf::Node splat_node;
  splat_node.name = "gaussians";
  splat_node.mesh = 0;
  model.nodes.push_back(splat_node);
  tinygltf::Scene scene;
  scene.nodes.push_back(0);

  check_cameras(options.cameras, "glb export");
  for (const Camera& cam : options.cameras) {
    tinygltf::Camera gc;
    gc.type = "perspective";
    gc.name = cam.name;
    const double fx = cam.K[0][0], fy = cam.K[1][1];
    gc.perspective.yfov = 2.0 * std::atan(0.5 * cam.height / fy);
    gc.perspective.aspectRatio = (cam.width / fx) / (cam.height / fy);
    gc.perspective.znear = 0.01;
    gc.perspective.zfar = 1000.0;
    // Pixel intrinsics that glTF cannot express (principal point, fx != fy) travel in extras for a lossless read.
    tinygltf::Value::Object intrinsics;
    intrinsics["width"] = tinygltf::Value(cam.width);
    intrinsics["height"] = tinygltf::Value(cam.height);
    tinygltf::Value::Array k;
    double K[9];
    camera_arrays(cam, K, static_cast<double*>(nullptr));
    for (double v : K) k.emplace_back(v);
    intrinsics["K"] = tinygltf::Value(k);
    tinygltf::Value::Object extras;
    extras["flexsplat_opencv_intrinsics"] = tinygltf::Value(intrinsics);
    gc.extras = tinygltf::Value(extras);
    model.cameras.push_back(gc);
    tinygltf::Node node;
    node.name = cam.name.empty() ? "camera_" + std::to_string(model.cameras.size() - 1) : cam.name;
    node.camera = static_cast<int>(model.cameras.size()) - 1;
    camera_to_node(cam, node);
    model.nodes.push_back(node);
    scene.nodes.push_back(static_cast<int>(model.nodes.size()) - 1);
  }
  model.scenes.push_back(scene);
  model.defaultScene = 0;
  model.extensionsUsed.push_back(kExtension);
  model.asset.version = "2.0";
  model.asset.generator = "flexsplat";

  while (bin.size() % 4) bin.push_back(0);
  tinygltf::Buffer buffer;
  buffer.data = std::move(bin);
  model.buffers.push_back(std::move(buffer));

  tinygltf::TinyGLTF io;
  std::ostringstream stream(std::ios::binary);
  require(io.WriteGltfSceneToStream(&model, stream, false, true), "glb export: tinygltf failed to serialise");
  const std::string bytes = stream.str();
  if (report) {
    report->repairs = repairs;
    report->bytes = bytes.size();
  }
  return std::vector<unsigned char>(bytes.begin(), bytes.end());
}

template <class T>
WriteReport write_glb(const GaussianSet<T>& set, const std::filesystem::path& path,
                      const WriteOptions& options = {}) {
  WriteReport report;
  const std::vector<unsigned char> bytes = encode_glb(set, options, &report);
  write_file_atomic(path, "glb writer", std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
  return report;
}

// Decodes the single KHR_gaussian_splatting primitive of a .glb; float attributes come back bit-exact.
// Cameras stored as perspective camera nodes go to *cameras when it is given.
// Long (about 170 lines): the checks in the file's own order (header, chunks, JSON, accessors, attributes, cameras).
inline GaussianSet<float> decode_glb(const unsigned char* data, std::size_t size, const std::string& source,
                                     std::vector<Camera>* cameras = nullptr) {
  using namespace detail;
  require(size >= 12, source, ": ", size, " bytes is too short for a glb header");
  require(std::memcmp(data, "glTF", 4) == 0, source, ": not a binary glTF file (magic is not 'glTF')");
  std::uint32_t declared = 0;
  std::memcpy(&declared, data + 8, 4);
  require(declared == size, source, ": glb header declares ", declared, " bytes but the file has ", size,
          " (truncated or padded)");
  tinygltf::Model model;
  tinygltf::TinyGLTF io;
  // A .glb is self-contained: images (unused here) stay undecoded bytes rather than going through stb, and a uri
  // naming a file is refused rather than opened.
  io.SetImageLoader([](tinygltf::Image*, const int, std::string*, std::string*, int, int, const unsigned char*, int,
                       void*) { return true; },
                    nullptr);
  tinygltf::FsCallbacks no_files{};
  no_files.FileExists = [](const std::string&, void*) { return false; };
  no_files.ExpandFilePath = [](const std::string& path, void*) { return path; };
  no_files.ReadWholeFile = [](std::vector<unsigned char>*, std::string* err, const std::string& path, void*) {
    if (err) *err += "external file '" + path + "' is not read from a .glb\n";
    return false;
  };
  no_files.WriteWholeFile = [](std::string*, const std::string&, const std::vector<unsigned char>&, void*) {
    return false;
  };
  io.SetFsCallbacks(no_files);
  std::string err, warn;
  const bool ok = io.LoadBinaryFromMemory(&model, &err, &warn, data, static_cast<unsigned int>(size), "");
  require(ok, source, ": invalid glb: ", err.empty() ? warn : err);

  const tinygltf::Primitive* splats = nullptr;
  int splat_mesh = -1, found = 0;
  for (std::size_t m = 0; m < model.meshes.size(); ++m)
    for (const tinygltf::Primitive& p : model.meshes[m].primitives)
      if (p.extensions.count(kExtension)) {
        ++found;
        splats = &p;
        splat_mesh = static_cast<int>(m);
      }
  require(found == 1, source, ": expected exactly one primitive with ", kExtension, ", found ", found);
  require(splats->mode == TINYGLTF_MODE_POINTS, source, ": Gaussian primitive has mode ", splats->mode,
          ", the extension requires POINTS (0)");
  const tinygltf::Value& ext = splats->extensions.at(kExtension);
  require(ext.IsObject(), source, ": ", kExtension, " extension is not an object");
  const tinygltf::Value& kernel = ext.Get("kernel");
  require(kernel.IsString(), source, ": ", kExtension, " has no string 'kernel'");
  require(kernel.Get<std::string>() == "ellipse", source, ": unsupported kernel '", kernel.Get<std::string>(), "'");
  const tinygltf::Value& color_space = ext.Get("colorSpace");
  require(color_space.IsString(), source, ": ", kExtension, " has no string 'colorSpace'");
  if (ext.Has("projection"))
    require(ext.Get("projection").IsString() && ext.Get("projection").Get<std::string>() == "perspective", source,
            ": unsupported projection");

  const std::vector<Eigen::Matrix4d> global = global_matrices(model, source);
  for (std::size_t i = 0; i < model.nodes.size(); ++i)
    if (model.nodes[i].mesh == splat_mesh)
      require((global[i] - Eigen::Matrix4d::Identity()).cwiseAbs().maxCoeff() < 1e-9, source,
              ": node ", i, " places the Gaussians with a non-identity transform (not supported)");

  auto attribute = [&](const std::string& semantic) -> int {
    auto it = splats->attributes.find(semantic);
    require(it != splats->attributes.end(), source, ": required attribute '", semantic, "' is missing");
    return it->second;
  };
  const int pos_index = attribute("POSITION");
  require(pos_index >= 0 && static_cast<std::size_t>(pos_index) < model.accessors.size(), source,
          ": POSITION accessor index out of range");
  const std::size_t n = model.accessors[pos_index].count;
  const auto positions = read_accessor(model, pos_index, "POSITION", TINYGLTF_TYPE_VEC3, {kFloat}, false, n, source);
  int rot_type = kFloat;
  const auto rotations = read_accessor(model, attribute(kAttributePrefix + "ROTATION"), kAttributePrefix + "ROTATION",
                                       TINYGLTF_TYPE_VEC4, {kFloat, kI8, kI16}, true, n, source, &rot_type);
  const auto scales = read_accessor(model, attribute(kAttributePrefix + "SCALE"), kAttributePrefix + "SCALE",
                                    TINYGLTF_TYPE_VEC3, {kFloat, kU8, kU16}, false, n, source);
  const auto opacities = read_accessor(model, attribute(kAttributePrefix + "OPACITY"), kAttributePrefix + "OPACITY",
                                       TINYGLTF_TYPE_SCALAR, {kFloat, kU8, kU16}, true, n, source);
  int degree = -1;
  for (int l = 0; l <= max_sh_degree; ++l) {
    int present = 0;
    for (int m = 0; m < 2 * l + 1; ++m) present += splats->attributes.count(sh_attribute(l, m)) ? 1 : 0;
    if (present == 0) break;
    require(present == 2 * l + 1, source, ": SH degree ", l, " is partially defined (", present, " of ", 2 * l + 1,
            " coefficients)");
    degree = l;
  }
  require(degree >= 0, source, ": required attribute '", sh_attribute(0, 0), "' is missing");
  for (const auto& [semantic, index] : splats->attributes)
    if (semantic.rfind(kAttributePrefix + "SH_DEGREE_", 0) == 0) {
      bool known = false;
      for (int l = 0; l <= degree; ++l)
        for (int m = 0; m < 2 * l + 1; ++m) known = known || semantic == sh_attribute(l, m);
      require(known, source, ": attribute '", semantic, "' does not belong to a complete SH degree 0..", degree);
    }

  GaussianSet<float> set = make_gaussian_set<float>(static_cast<index_t>(n), degree);
  for (std::size_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) {
      set.means(i, c) = static_cast<float>(positions[i * 3 + c]);
      set.scales(i, c) = static_cast<float>(scales[i * 3 + c]);
    }
    set.opacities(i) = static_cast<float>(opacities[i]);
    set.quats(i, 0) = static_cast<float>(rotations[i * 4 + 3]);
    for (int c = 0; c < 3; ++c) set.quats(i, c + 1) = static_cast<float>(rotations[i * 4 + c]);
    if (rot_type != kFloat) {
      // Integer quaternions are unit only up to quantisation: check that bound, then renormalise.
      double norm = 0;
      for (int c = 0; c < 4; ++c) norm += rotations[i * 4 + c] * rotations[i * 4 + c];
      norm = std::sqrt(norm);
      const double tolerance = 2.0 / quantize_max(rot_type);
      require(std::abs(norm - 1.0) <= tolerance, source, ": rotation of Gaussian ", i,
              " is not a unit quaternion (norm ", norm, ")");
      for (int c = 0; c < 4; ++c) set.quats(i, c) = static_cast<float>(set.quats(i, c) / norm);
    }
  }
  for (int l = 0; l <= degree; ++l)
    for (int m = 0; m < 2 * l + 1; ++m) {
      const std::string name = sh_attribute(l, m);
      const auto coef = read_accessor(model, attribute(name), name, TINYGLTF_TYPE_VEC3, {kFloat}, false, n, source);
      for (std::size_t i = 0; i < n; ++i)
        for (int c = 0; c < 3; ++c) set.sh(i, l * l + m, c) = static_cast<float>(coef[i * 3 + c]);
    }

  std::vector<Camera> node_cameras;
  for (std::size_t i = 0; i < model.nodes.size(); ++i) {
    const int ci = model.nodes[i].camera;
    if (ci < 0) continue;
    require(static_cast<std::size_t>(ci) < model.cameras.size(), source, ": node ", i, " has camera index ", ci,
            " out of range");
    const tinygltf::Camera& gc = model.cameras[ci];
    if (gc.type != "perspective") continue;
    Camera cam;
    cam.name = model.nodes[i].name;
    // tinygltf's Value::Get asserts that it is called on an object; a number cast to int must fit.
    static const tinygltf::Value no_value;
    const tinygltf::Value& intr = gc.extras.IsObject() ? gc.extras.Get("flexsplat_opencv_intrinsics") : no_value;
    auto pixel_count = [&](const char* key) {
      const double v = intr.Get(key).GetNumberAsDouble();
      require(v >= 1 && v <= double(1 << 24), source, ": camera ", ci, " intrinsics '", key, "' = ", v,
              " is not a pixel count in [1, 2^24]");
      return static_cast<int>(v);
    };
    if (intr.IsObject() && intr.Get("K").IsArray() && intr.Get("K").ArrayLen() == 9) {
      cam.width = pixel_count("width");
      cam.height = pixel_count("height");
      for (int k = 0; k < 9; ++k) cam.K[k % 3][k / 3] = intr.Get("K").Get(k).GetNumberAsDouble();
    } else {
      // Without pixel intrinsics: a 1024-pixel-high image with the principal point at the centre.
      const double aspect = gc.perspective.aspectRatio > 0 ? gc.perspective.aspectRatio : 1.0;
      require(gc.perspective.yfov > 0, source, ": camera ", ci, " has yfov ", gc.perspective.yfov);
      cam.height = 1024;
      cam.width = static_cast<int>(std::lround(1024 * aspect));
      const double f = 0.5 * cam.height / std::tan(0.5 * gc.perspective.yfov);
      cam.K = glm::dmat3(1.0);
      cam.K[0][0] = cam.K[1][1] = f;
      cam.K[2][0] = 0.5 * cam.width, cam.K[2][1] = 0.5 * cam.height;
    }
    Eigen::Matrix3d c2w_gl = global[i].topLeftCorner<3, 3>();
    for (int c = 0; c < 3; ++c) c2w_gl.col(c).normalize();  // camera nodes ignore scale
    const Eigen::Matrix3d R = (c2w_gl * Eigen::Vector3d(1, -1, -1).asDiagonal()).transpose();
    const Eigen::Vector3d t = -R * global[i].topRightCorner<3, 1>();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) cam.R[c][r] = R(r, c);
      cam.t[r] = t(r);
    }
    node_cameras.push_back(cam);
  }
  gaussians::validate(set, source);
  check_cameras(node_cameras, source);
  if (cameras) *cameras = std::move(node_cameras);
  return set;
}

inline std::vector<unsigned char> read_file_bytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  require(in.good(), "cannot open '", path.string(), "'");
  return std::vector<unsigned char>(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

inline GaussianSet<float> read_glb(const std::filesystem::path& path,
                                   std::vector<Camera>* cameras = nullptr) {
  const std::vector<unsigned char> bytes = read_file_bytes(path);
  return decode_glb(bytes.data(), bytes.size(), path.string(), cameras);
}

}  // namespace gltf
}  // namespace v0
}  // namespace flexsplat
