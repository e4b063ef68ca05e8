#pragma once
// Object folders in the layout of the shared renders (images/NNN.png RGBA, depth/NNN.png 16-bit, cameras.json with
// K, w2c, depth_png_scale_m and input_views): the generator that renders procedural objects, the atomic writer,
// the validating reader, and training batches of N input + M target views per scene, sampled from folders or
// straight from the generator in memory.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <limits>
#include <numeric>
#include <string>
#include <system_error>
#include <vector>

#include <unistd.h>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/data/cameras.hpp"
#include "flexsplat/data/mesh_render.hpp"
#include "flexsplat/data/procedural.hpp"
#include "flexsplat/data/random.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/resample.hpp"
#include "flexsplat/io/cameras_json.hpp"

namespace flexsplat {
inline namespace v0 {
namespace data {

// Depth PNG quantum of the shared renders: 0.1 mm per step, so 16 bits reach 6.5535 units.
inline constexpr double kDepthPngScale = 1e-4;

// ---------------------------------------------------------------------------------------------------------------
// Generator
// ---------------------------------------------------------------------------------------------------------------

struct GeneratorConfig {
  ObjectConfig object;
  OrbitRanges orbit;
  int size = 256;          // square images
  int views = 32;          // per object
  bool structured = true;  // views 0-3 are the structured evaluation set (when views >= 4); they are input_views
  int supersample = 2;
};

struct GeneratedObject {
  ProceduralObject object;
  std::vector<Camera> cameras;
  std::vector<RenderOutput> views;
  std::vector<int> input_views;
};

inline void check_generator(const GeneratorConfig& cfg) {
  require(cfg.size >= 8 && cfg.size <= 4096, "generator: size ", cfg.size, " outside [8, 4096]");
  require(cfg.views >= 1 && cfg.views <= 1000, "generator: views ", cfg.views, " outside [1, 1000]");
  check_ranges(cfg.orbit);
  check_object_config(cfg.object);
}

// Seed of object `index` of the dataset with seed `seed`.
inline std::uint64_t object_seed(std::uint64_t seed, std::uint64_t index) { return child_seed(seed, index); }

// Cameras of an object: the structured set first (if enabled and views >= 4), then random orbit views.
inline std::vector<Camera> object_cameras(std::uint64_t obj_seed, const GeneratorConfig& cfg) {
  std::vector<Camera> cams;
  if (cfg.structured && cfg.views >= 4) cams = structured_cameras(cfg.size, cfg.size);
  Rng rng(stream_seed(obj_seed, Stream::cameras));
  while (static_cast<int>(cams.size()) < cfg.views) cams.push_back(sample_orbit_camera(rng, cfg.orbit, cfg.size, cfg.size));
  return cams;
}

inline RenderOptions object_render_options(const ProceduralObject& object, int supersample, bool normals = false) {
  RenderOptions opt;
  opt.supersample = supersample;
  opt.normals = normals;
  opt.light_direction = object.light_direction;
  opt.ambient = object.ambient;
  return opt;
}

// Object `index` of dataset `seed` with all its views, rendered in parallel over views.
inline GeneratedObject generate_object(std::uint64_t seed, std::uint64_t index, const GeneratorConfig& cfg,
                                       ThreadPool& pool = global_pool()) {
  check_generator(cfg);
  GeneratedObject g;
  g.object = make_object(object_seed(seed, index), cfg.object);
  g.cameras = object_cameras(g.object.seed, cfg);
  if (cfg.structured && cfg.views >= 4) g.input_views = {0, 1, 2, 3};
  g.views.resize(g.cameras.size());
  const RenderOptions opt = object_render_options(g.object, cfg.supersample);
  parallel_for(static_cast<index_t>(g.cameras.size()), [&](index_t begin, index_t end, int) {
    RenderWorkspace ws;
    for (index_t v = begin; v < end; ++v) render_mesh(g.object.mesh, g.cameras[v], opt, g.views[v], ws, pool);
  }, pool);
  return g;
}

// ---------------------------------------------------------------------------------------------------------------
// Writer
// ---------------------------------------------------------------------------------------------------------------

namespace detail {

inline nlohmann::json matrix_json(const glm::dmat3& m) {
  nlohmann::json rows = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({m[0][r], m[1][r], m[2][r]});
  return rows;
}

inline nlohmann::json w2c_json(const Camera& cam) {
  nlohmann::json rows = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({cam.R[0][r], cam.R[1][r], cam.R[2][r], cam.t[r]});
  return rows;
}

inline std::string view_name(std::size_t i) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%03zu.png", i);
  return buf;
}

inline void write_text_atomic(const std::filesystem::path& path, const std::string& text) {
  write_file_atomic(path, "make-data", text);
}

}  // namespace detail

// 16-bit depth PNG: round(z / scale); 0 stays 0 (no surface); depths beyond 65535 steps are an error.
inline void write_depth_png(const std::filesystem::path& path, TensorView<const float, 2> depth, double scale) {
  Tensor<std::uint16_t, 3> q(Shape<3>{depth.shape(0), depth.shape(1), 1});
  for (index_t y = 0; y < depth.shape(0); ++y)
    for (index_t x = 0; x < depth.shape(1); ++x) {
      const double z = depth(y, x);
      const double steps = std::round(z / scale);
      if (!(steps >= 0 && steps <= 65535))
        fail("write_depth_png '", path.string(), "': depth ", z, " at (", x, ", ", y, ") not representable with scale ",
             scale);
      q(y, x, 0) = static_cast<std::uint16_t>(steps);
    }
  image::write_png_u16(path, TensorView<const std::uint16_t, 3>(q.view()));
}

inline nlohmann::json cameras_document(const std::vector<Camera>& cams, const std::vector<int>& input_views) {
  require(!cams.empty(), "cameras_document: no cameras");
  nlohmann::json doc;
  doc["width"] = cams[0].width;
  doc["height"] = cams[0].height;
  doc["camera_model"] = "pinhole";
  doc["convention"] = "OpenCV: x right, y down, z forward; w2c maps world to camera; pixel centres at +0.5";
  doc["depth_png_scale_m"] = kDepthPngScale;
  doc["background"] = "transparent (composite over white)";
  doc["input_views"] = input_views;
  doc["frames"] = nlohmann::json::array();
  for (std::size_t i = 0; i < cams.size(); ++i) {
    require(cams[i].width == cams[0].width && cams[i].height == cams[0].height, "cameras_document: camera ", i,
            " is ", cams[i].width, "x", cams[i].height, ", camera 0 is ", cams[0].width, "x", cams[0].height);
    doc["frames"].push_back({{"file", "images/" + detail::view_name(i)},
                             {"depth", "depth/" + detail::view_name(i)},
                             {"elevation_deg", cams[i].elevation_deg},
                             {"azimuth_deg", cams[i].azimuth_deg},
                             {"K", detail::matrix_json(cams[i].K)},
                             {"w2c", detail::w2c_json(cams[i])}});
  }
  return doc;
}

// Writes `g` as folder `dir` (which must not exist): everything goes to a temporary sibling that is renamed into
// place at the end, so a folder that exists is complete. PNGs are encoded in parallel over views.
inline void write_object(const std::filesystem::path& dir, const GeneratedObject& g, ThreadPool& pool = global_pool()) {
  namespace fs = std::filesystem;
  require(!fs::exists(dir), "write_object: '", dir.string(), "' already exists");
  require(g.views.size() == g.cameras.size() && !g.views.empty(), "write_object '", dir.string(), "': ",
          g.views.size(), " renders for ", g.cameras.size(), " cameras");
  const fs::path tmp = dir.parent_path() / (".tmp_" + dir.filename().string() + "_" + std::to_string(::getpid()));
  std::error_code ec;
  fs::remove_all(tmp, ec);
  fs::create_directories(tmp / "images", ec);
  require(!ec, "write_object: cannot create '", (tmp / "images").string(), "': ", ec.message());
  fs::create_directories(tmp / "depth", ec);
  require(!ec, "write_object: cannot create '", (tmp / "depth").string(), "': ", ec.message());
  try {
    parallel_for(static_cast<index_t>(g.views.size()), [&](index_t begin, index_t end, int) {
      for (index_t v = begin; v < end; ++v) {
        image::write_png(tmp / "images" / detail::view_name(v), TensorView<const float, 3>(g.views[v].rgba.view()));
        write_depth_png(tmp / "depth" / detail::view_name(v), TensorView<const float, 2>(g.views[v].depth.view()),
                        kDepthPngScale);
      }
    }, pool);
    nlohmann::json doc = cameras_document(g.cameras, g.input_views);
    nlohmann::json prims = nlohmann::json::array();
    for (const Primitive& p : g.object.primitives)
      prims.push_back({{"kind", primitive_name(p.kind)}, {"texture", texture_name(p.material.kind)}});
    doc["generator"] = {{"name", "flexsplat procedural"}, {"object_seed", g.object.seed}, {"primitives", prims}};
    detail::write_text_atomic(tmp / "cameras.json", doc.dump(1) + "\n");
    fs::rename(tmp, dir, ec);
    require(!ec, "write_object: cannot rename '", tmp.string(), "' to '", dir.string(), "': ", ec.message());
  } catch (...) {
    std::error_code ignored;
    fs::remove_all(tmp, ignored);
    throw;
  }
}

struct MakeDataOptions {
  int count = 1;
  std::uint64_t seed = 0;
  GeneratorConfig generator;
};

struct MakeDataReport {
  int written = 0, skipped = 0;
};

inline std::string object_folder_name(std::uint64_t index) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "obj_%06llu", static_cast<unsigned long long>(index));
  return buf;
}

// Generates objects 0..count-1 of dataset `seed` into out/obj_NNNNNN/. Resumable: existing object folders are
// complete (atomic rename) and skipped; out/make_data.json records the settings and a rerun with different ones is
// refused. progress(done, total) is called after each object.
inline MakeDataReport make_dataset(const std::filesystem::path& out, const MakeDataOptions& options,
                                   const std::function<void(int, int)>& progress = {},
                                   ThreadPool& pool = global_pool()) {
  namespace fs = std::filesystem;
  check_generator(options.generator);
  require(options.count >= 1, "make-data: count ", options.count, " must be at least 1");
  std::error_code ec;
  fs::create_directories(out, ec);
  require(!ec, "make-data: cannot create '", out.string(), "': ", ec.message());
  const GeneratorConfig& g = options.generator;
  nlohmann::json settings = {{"seed", options.seed}, {"views", g.views}, {"size", g.size},
                             {"structured", g.structured}, {"supersample", g.supersample},
                             {"segments", g.object.segments}, {"format", 1}};
  // Recorded only when set, so that folders made before these options existed still match.
  if (g.object.blob_fraction > 0) settings["blob_fraction"] = g.object.blob_fraction;
  if (g.object.attached) settings["attached"] = true;
  if (g.object.soft_textures) settings["soft_textures"] = true;
  const fs::path manifest = out / "make_data.json";
  if (fs::exists(manifest)) {
    std::ifstream in(manifest);
    const nlohmann::json old = nlohmann::json::parse(in, nullptr, false);
    require(!old.is_discarded() && old == settings, "make-data: '", manifest.string(), "' records different settings (",
            old.is_discarded() ? std::string("unreadable") : old.dump(), ") than this run (", settings.dump(),
            "); use another --out");
  } else {
    detail::write_text_atomic(manifest, settings.dump(1) + "\n");
  }
  // Leftovers of interrupted runs: their objects are regenerated below.
  for (const auto& entry : fs::directory_iterator(out))
    if (entry.is_directory() && entry.path().filename().string().rfind(".tmp_obj_", 0) == 0) fs::remove_all(entry.path(), ec);
  MakeDataReport report;
  for (int i = 0; i < options.count; ++i) {
    const fs::path dir = out / object_folder_name(static_cast<std::uint64_t>(i));
    if (fs::is_directory(dir)) {
      ++report.skipped;
    } else {
      write_object(dir, generate_object(options.seed, static_cast<std::uint64_t>(i), g, pool), pool);
      ++report.written;
    }
    if (progress) progress(i + 1, options.count);
  }
  return report;
}

// ---------------------------------------------------------------------------------------------------------------
// Reader
// ---------------------------------------------------------------------------------------------------------------

struct FrameRecord {
  std::filesystem::path image, depth;
  Camera camera;
};

struct ObjectRecord {
  std::string name;
  std::filesystem::path dir;
  int width = 0, height = 0;
  double depth_scale = 0;
  std::vector<FrameRecord> frames;
  std::vector<int> input_views;
};

namespace detail {

// True if p is a regular file, false if it or a parent is missing; any other failure (a name longer than the file
// system allows, no permission, a symlink loop) is an error naming p, not a std::filesystem exception.
inline bool is_file(const std::filesystem::path& p) {
  std::error_code ec;
  const std::filesystem::file_status st = std::filesystem::status(p, ec);
  if (ec && ec != std::errc::no_such_file_or_directory && ec != std::errc::not_a_directory)
    fail_in(p.string(), "cannot be read: ", ec.message());
  return std::filesystem::is_regular_file(st);
}

inline std::filesystem::path frame_file(const nlohmann::json& frame, const char* key, const std::filesystem::path& dir,
                                        const std::filesystem::path& file, std::size_t index) {
  if (!frame.contains(key) || !frame[key].is_string())
    fail_in(file.string(), "frame ", index, " has no string '", key, "'");
  const std::filesystem::path rel = frame[key].get<std::string>();
  if (rel.is_absolute() || rel.empty()) fail_in(file.string(), "frame ", index, " '", key, "' must be a relative path");
  return dir / rel;
}

}  // namespace detail

// Loads and checks one object folder: cameras.json parses and has sane width/height, depth scale, intrinsics,
// rotations and input_views; every image is an RGBA (or RGB) PNG and every depth a 16-bit single-channel PNG of the
// stated size. Pixels are not decoded. Errors name the offending file.
inline ObjectRecord load_object(const std::filesystem::path& dir) {
  namespace fs = std::filesystem;
  const fs::path file = dir / "cameras.json";
  if (!detail::is_file(file)) fail_in(file.string(), "missing (not an object folder)");
  const nlohmann::json doc = io::read_cameras_json(file);
  const std::vector<Camera> cameras = io::parse_cameras_json(doc, file.string());
  ObjectRecord rec;
  rec.dir = dir;
  rec.name = dir.filename().string();
  if (rec.name.empty()) rec.name = dir.parent_path().filename().string();
  rec.width = doc["width"].get<int>();  // parse_cameras_json checked both
  rec.height = doc["height"].get<int>();
  if (!doc.contains("depth_png_scale_m") || !doc["depth_png_scale_m"].is_number())
    fail_in(file.string(), "has no numeric 'depth_png_scale_m'");
  rec.depth_scale = doc["depth_png_scale_m"].get<double>();
  if (!(std::isfinite(rec.depth_scale) && rec.depth_scale > 0 && rec.depth_scale <= 1))
    fail_in(file.string(), "'depth_png_scale_m' = ", rec.depth_scale, " must be finite and in (0, 1]");
  const nlohmann::json& frames = doc["frames"];
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const nlohmann::json& frame = frames[i];
    FrameRecord fr;
    fr.image = detail::frame_file(frame, "file", dir, file, i);
    fr.depth = detail::frame_file(frame, "depth", dir, file, i);
    fr.camera = cameras[i];
    for (const fs::path* p : {&fr.image, &fr.depth})
      if (!detail::is_file(*p)) fail_in(p->string(), "missing (frame ", i, " of '", file.string(), "')");
    const image::ImageInfo im = image::probe(fr.image);
    if (im.width != fr.camera.width || im.height != fr.camera.height || im.channels < 3)
      fail_in(fr.image.string(), "is ", im.width, "x", im.height, " with ", im.channels, " channels; '",
                            file.string(), "' says ", fr.camera.width, "x", fr.camera.height, " RGB(A)");
    const image::ImageInfo dp = image::probe(fr.depth);
    if (dp.width != fr.camera.width || dp.height != fr.camera.height || dp.channels != 1 || dp.bit_depth != 16)
      fail_in(fr.depth.string(), "is ", dp.width, "x", dp.height, ", ", dp.bit_depth, "-bit with ", dp.channels,
                            " channels; '", file.string(), "' says ", fr.camera.width, "x", fr.camera.height,
                            " 16-bit single-channel depth");
    rec.frames.push_back(std::move(fr));
  }
  if (doc.contains("input_views")) {
    const nlohmann::json& iv = doc["input_views"];
    if (!iv.is_array()) fail_in(file.string(), "'input_views' is not an array");
    for (const nlohmann::json& v : iv) {
      if (!v.is_number_integer() || v.get<long long>() < 0 || v.get<long long>() >= static_cast<long long>(frames.size()))
        fail_in(file.string(), "'input_views' entry ", v.dump(), " is not a frame index in [0, ", frames.size(), ")");
      const int index = v.get<int>();
      if (std::find(rec.input_views.begin(), rec.input_views.end(), index) != rec.input_views.end())
        fail_in(file.string(), "'input_views' lists frame ", index, " twice");
      rec.input_views.push_back(index);
    }
  }
  return rec;
}

// Each path is an object folder (has cameras.json) or a folder of object folders (sorted by name).
inline std::vector<ObjectRecord> load_objects(const std::vector<std::filesystem::path>& paths) {
  namespace fs = std::filesystem;
  std::vector<ObjectRecord> out;
  for (const fs::path& p : paths) {
    std::error_code ec;
    const bool folder = fs::is_directory(p, ec);
    require(folder, "dataset: '", p.string(), "' is not a folder", ec ? " (" + ec.message() + ")" : "");
    if (fs::exists(p / "cameras.json", ec) || ec) {  // load_object names an unreadable one
      out.push_back(load_object(p));
      continue;
    }
    std::vector<fs::path> children;
    for (fs::directory_iterator it(p, ec), end; !ec && it != end; it.increment(ec))
      if (it->is_directory(ec) && it->path().filename().string().rfind(".tmp_", 0) != 0) children.push_back(it->path());
    require(!ec, "dataset: cannot list '", p.string(), "': ", ec.message());
    std::sort(children.begin(), children.end());
    const std::size_t before = out.size();
    for (const fs::path& c : children) out.push_back(load_object(c));
    require(out.size() > before, "dataset: '", p.string(), "' holds no object folders");
  }
  return out;
}

// ---------------------------------------------------------------------------------------------------------------
// Training batches
// ---------------------------------------------------------------------------------------------------------------

enum class BackgroundMode { white, black, random, fixed };

struct BatchOptions {
  int inputs = 4, targets = 4;
  bool structured_inputs = true;  // use the scene's input_views when there are exactly `inputs` of them
  int crop = 0;                   // output side; 0 keeps the full image (then scale jitter needs scale >= 1)
  double scale_min = 1.0, scale_max = 1.0;  // zoom: a window of side crop / scale is resampled to crop
  BackgroundMode background = BackgroundMode::white;
  glm::vec3 background_color{1.0f};  // for BackgroundMode::fixed
};

struct Views {
  Tensor<float, 4> rgb;    // [V, H, W, 3] composited over the scene's background
  Tensor<float, 3> alpha;  // [V, H, W]
  Tensor<float, 3> depth;  // [V, H, W] camera z, 0 for background
  std::vector<Camera> cameras;
};

struct SceneSample {
  std::string name;
  glm::vec3 background{1.0f};
  Views inputs, targets;
};

namespace detail {

inline void check_batch_options(const BatchOptions& o) {
  require(o.inputs >= 1 && o.targets >= 0, "BatchOptions: inputs ", o.inputs, " must be >= 1 and targets ",
          o.targets, " >= 0");
  require(o.crop >= 0, "BatchOptions: crop ", o.crop, " must be >= 0");
  require(o.scale_min > 0 && o.scale_min <= o.scale_max && std::isfinite(o.scale_max), "BatchOptions: scale range [",
          o.scale_min, ", ", o.scale_max, "] must be positive and ordered");
}

// Picks `inputs` and `targets` view indices of a scene with `frames` views.
inline void choose_views(Rng& rng, int frames, const std::vector<int>& input_views, const BatchOptions& o,
                         std::vector<int>& in, std::vector<int>& tg, const std::string& name) {
  require(o.inputs <= frames, "batch: scene '", name, "' has ", frames, " views, fewer than ", o.inputs, " inputs");
  std::vector<int> order(static_cast<std::size_t>(frames));
  std::iota(order.begin(), order.end(), 0);
  for (int i = frames - 1; i > 0; --i) std::swap(order[static_cast<std::size_t>(i)], order[static_cast<std::size_t>(rng.integer(0, i))]);
  if (o.structured_inputs && static_cast<int>(input_views.size()) == o.inputs) in = input_views;
  else in.assign(order.begin(), order.begin() + o.inputs);
  std::vector<int> rest;
  for (int v : order)
    if (std::find(in.begin(), in.end(), v) == in.end()) rest.push_back(v);
  tg.clear();
  for (int i = 0; i < o.targets; ++i)  // distinct from the inputs while the scene has enough views
    tg.push_back(static_cast<int>(rest.size()) >= o.targets ? rest[static_cast<std::size_t>(i)]
                                                            : order[static_cast<std::size_t>(rng.integer(0, frames - 1))]);
}

inline glm::vec3 scene_background(Rng& rng, const BatchOptions& o) {
  switch (o.background) {
    case BackgroundMode::white: return glm::vec3(1.0f);
    case BackgroundMode::black: return glm::vec3(0.0f);
    case BackgroundMode::fixed: return o.background_color;
    case BackgroundMode::random: {
      const float r = static_cast<float>(rng.uniform()), g = static_cast<float>(rng.uniform());
      return {r, g, static_cast<float>(rng.uniform())};
    }
  }
  return glm::vec3(1.0f);
}

// Crop / zoom one view into slot `slot` of `views`: a random window of side round(out / scale) is resampled to
// out x out (antialiased bicubic on premultiplied RGBA, nearest for depth) and K follows the window.
inline void augment_view(TensorView<const float, 3> rgba, TensorView<const float, 2> depth, const Camera& cam,
                         int out, std::uint64_t seed, const BatchOptions& o, glm::vec3 background, Views& views,
                         index_t slot) {
  const int W = static_cast<int>(rgba.shape(1)), H = static_cast<int>(rgba.shape(0));
  Rng rng(seed);
  const double scale = o.scale_min == o.scale_max ? o.scale_min : rng.uniform(o.scale_min, o.scale_max);
  const int window = std::max(1, static_cast<int>(std::lround(out / scale)));
  require(window <= W && window <= H, "batch: a window of ", window, " pixels (output ", out, ", scale ", scale,
          ") does not fit the ", W, "x", H, " image");
  const int x0 = rng.integer(0, W - window), y0 = rng.integer(0, H - window);
  const double k = static_cast<double>(out) / window;
  Camera c = cam;
  c.width = c.height = out;
  c.K[0][0] *= k;
  c.K[1][0] *= k;
  c.K[1][1] *= k;
  c.K[2][0] = (c.K[2][0] - x0) * k;
  c.K[2][1] = (c.K[2][1] - y0) * k;
  views.cameras[static_cast<std::size_t>(slot)] = c;
  if (window == out) {
    for (int y = 0; y < out; ++y)
      for (int x = 0; x < out; ++x) {
        const float a = rgba(y0 + y, x0 + x, 3);
        for (int ch = 0; ch < 3; ++ch)
          views.rgb(slot, y, x, ch) = rgba(y0 + y, x0 + x, ch) * a + background[ch] * (1.0f - a);
        views.alpha(slot, y, x) = a;
        views.depth(slot, y, x) = depth(y0 + y, x0 + x);
      }
    return;
  }
  Tensor<float, 3> planar(Shape<3>{4, window, window});
  for (int y = 0; y < window; ++y)
    for (int x = 0; x < window; ++x) {
      const float a = rgba(y0 + y, x0 + x, 3);
      for (int ch = 0; ch < 3; ++ch) planar(ch, y, x) = rgba(y0 + y, x0 + x, ch) * a;
      planar(3, y, x) = a;
    }
  const Tensor<float, 3> resized = interpolate_bicubic_antialias<float>(TensorView<const float, 3>(planar.view()), out, out);
  for (int y = 0; y < out; ++y)
    for (int x = 0; x < out; ++x) {
      const float a = std::clamp(resized(3, y, x), 0.0f, 1.0f);
      for (int ch = 0; ch < 3; ++ch)  // premultiplied colour lies in [0, alpha]; this also removes bicubic ringing
        views.rgb(slot, y, x, ch) = std::clamp(resized(ch, y, x), 0.0f, a) + background[ch] * (1.0f - a);
      views.alpha(slot, y, x) = a;
      const int sx = std::min(window - 1, static_cast<int>((x + 0.5) / k)), sy = std::min(window - 1, static_cast<int>((y + 0.5) / k));
      views.depth(slot, y, x) = depth(y0 + sy, x0 + sx);
    }
}

inline Views make_views(int count, int side) {
  Views v;
  v.rgb = Tensor<float, 4>(Shape<4>{count, side, side, 3});
  v.alpha = Tensor<float, 3>(Shape<3>{count, side, side});
  v.depth = Tensor<float, 3>(Shape<3>{count, side, side});
  v.cameras.resize(static_cast<std::size_t>(count));
  return v;
}

struct ViewJob {
  std::size_t scene;
  bool target;
  int slot, view;
};

inline std::vector<ViewJob> view_jobs(const std::vector<std::vector<int>>& in, const std::vector<std::vector<int>>& tg) {
  std::vector<ViewJob> jobs;
  for (std::size_t s = 0; s < in.size(); ++s) {
    for (std::size_t i = 0; i < in[s].size(); ++i) jobs.push_back({s, false, static_cast<int>(i), in[s][i]});
    for (std::size_t i = 0; i < tg[s].size(); ++i) jobs.push_back({s, true, static_cast<int>(i), tg[s][i]});
  }
  return jobs;
}

inline std::uint64_t view_seed(std::uint64_t seed, std::uint64_t step, std::size_t job) {
  return child_seed(child_seed(stream_seed(seed, Stream::augment), step), job);
}

}  // namespace detail

// Batch `step` of a run with `seed`: batch_size scenes drawn uniformly from `objects` (with replacement), each with
// N input and M target views loaded from disk and augmented. Deterministic in (seed, step), any thread count.
inline std::vector<SceneSample> sample_batch(const std::vector<ObjectRecord>& objects, int batch_size,
                                             std::uint64_t seed, std::uint64_t step, const BatchOptions& o,
                                             ThreadPool& pool = global_pool()) {
  detail::check_batch_options(o);
  require(!objects.empty(), "sample_batch: no objects");
  require(batch_size >= 1, "sample_batch: batch size ", batch_size, " must be >= 1");
  Rng rng(child_seed(stream_seed(seed, Stream::batch), step));
  std::vector<SceneSample> batch(static_cast<std::size_t>(batch_size));
  std::vector<const ObjectRecord*> scene(batch.size());
  std::vector<std::vector<int>> in(batch.size()), tg(batch.size());
  for (std::size_t s = 0; s < batch.size(); ++s) {
    scene[s] = &objects[static_cast<std::size_t>(rng.integer(0, static_cast<int>(objects.size()) - 1))];
    detail::choose_views(rng, static_cast<int>(scene[s]->frames.size()), scene[s]->input_views, o, in[s], tg[s],
                         scene[s]->name);
    batch[s].name = scene[s]->name;
    batch[s].background = detail::scene_background(rng, o);
    const int side = o.crop > 0 ? o.crop : scene[s]->width;
    require(o.crop > 0 || scene[s]->width == scene[s]->height, "sample_batch: scene '", scene[s]->name, "' is ",
            scene[s]->width, "x", scene[s]->height, "; non-square images need a crop");
    batch[s].inputs = detail::make_views(o.inputs, side);
    batch[s].targets = detail::make_views(o.targets, side);
  }
  const auto jobs = detail::view_jobs(in, tg);
  parallel_for(static_cast<index_t>(jobs.size()), [&](index_t begin, index_t end, int) {
    for (index_t j = begin; j < end; ++j) {
      const detail::ViewJob& job = jobs[static_cast<std::size_t>(j)];
      const ObjectRecord& rec = *scene[job.scene];
      const FrameRecord& fr = rec.frames[static_cast<std::size_t>(job.view)];
      const Tensor<float, 3> rgba = image::read_float<float>(fr.image, 4);
      const Tensor<float, 2> depth = image::read_depth_png<float>(fr.depth, static_cast<float>(rec.depth_scale));
      require(rgba.shape(0) == rec.height && rgba.shape(1) == rec.width && depth.shape() == Shape<2>{rec.height, rec.width},
              "sample_batch: '", fr.image.string(), "' or its depth changed size since the folder was loaded");
      SceneSample& out = batch[job.scene];
      detail::augment_view(TensorView<const float, 3>(rgba.view()), TensorView<const float, 2>(depth.view()), fr.camera,
                           o.crop > 0 ? o.crop : rec.width, detail::view_seed(seed, step, static_cast<std::size_t>(j)), o,
                           out.background, job.target ? out.targets : out.inputs, job.slot);
    }
  }, pool);
  return batch;
}

// The same batch structure straight from the generator, no files: scene b of batch `step` is object
// step * batch_size + b of dataset `seed`; inputs are the structured set when structured_inputs and inputs == 4,
// otherwise random orbit views; targets are random orbit views.
inline std::vector<SceneSample> generate_batch(const GeneratorConfig& cfg, int batch_size, std::uint64_t seed,
                                               std::uint64_t step, const BatchOptions& o,
                                               ThreadPool& pool = global_pool()) {
  detail::check_batch_options(o);
  check_generator(cfg);
  require(batch_size >= 1, "generate_batch: batch size ", batch_size, " must be >= 1");
  std::vector<SceneSample> batch(static_cast<std::size_t>(batch_size));
  std::vector<ProceduralObject> objects(batch.size());
  std::vector<std::vector<Camera>> cams(batch.size());
  std::vector<std::vector<int>> in(batch.size()), tg(batch.size());
  parallel_for(batch_size, [&](index_t begin, index_t end, int) {
    for (index_t s = begin; s < end; ++s)
      objects[static_cast<std::size_t>(s)] =
          make_object(object_seed(seed, step * static_cast<std::uint64_t>(batch_size) + static_cast<std::uint64_t>(s)),
                      cfg.object);
  }, pool);
  for (std::size_t s = 0; s < batch.size(); ++s) {
    const bool structured = o.structured_inputs && o.inputs == 4;
    std::vector<Camera>& c = cams[s];
    if (structured) c = structured_cameras(cfg.size, cfg.size);
    Rng rng(stream_seed(objects[s].seed, Stream::cameras));
    while (static_cast<int>(c.size()) < o.inputs + o.targets) {
      const Camera* first = c.empty() || structured ? nullptr : &c.front();
      c.push_back(sample_orbit_camera(rng, cfg.orbit, cfg.size, cfg.size, first));
    }
    for (int i = 0; i < o.inputs; ++i) in[s].push_back(i);
    for (int i = 0; i < o.targets; ++i) tg[s].push_back(o.inputs + i);
    Rng bg(child_seed(stream_seed(seed, Stream::batch), objects[s].seed));
    batch[s].name = object_folder_name(step * static_cast<std::uint64_t>(batch_size) + s);
    batch[s].background = detail::scene_background(bg, o);
    const int side = o.crop > 0 ? o.crop : cfg.size;
    batch[s].inputs = detail::make_views(o.inputs, side);
    batch[s].targets = detail::make_views(o.targets, side);
  }
  const auto jobs = detail::view_jobs(in, tg);
  parallel_for(static_cast<index_t>(jobs.size()), [&](index_t begin, index_t end, int) {
    RenderWorkspace ws;
    RenderOutput r;
    for (index_t j = begin; j < end; ++j) {
      const detail::ViewJob& job = jobs[static_cast<std::size_t>(j)];
      const ProceduralObject& obj = objects[job.scene];
      const Camera& cam = cams[job.scene][static_cast<std::size_t>(job.view)];
      render_mesh(obj.mesh, cam, object_render_options(obj, cfg.supersample), r, ws, pool);
      SceneSample& out = batch[job.scene];
      detail::augment_view(TensorView<const float, 3>(r.rgba.view()), TensorView<const float, 2>(r.depth.view()), cam,
                           o.crop > 0 ? o.crop : cfg.size, detail::view_seed(seed, step, static_cast<std::size_t>(j)), o,
                           out.background, job.target ? out.targets : out.inputs, job.slot);
    }
  }, pool);
  return batch;
}

}  // namespace data
}  // namespace v0
}  // namespace flexsplat
