#pragma once
// Forward-only inference of the whole FlexSplat model: images at the model's size -> VGGT (cameras, depth,
// confidence, depth features; no training cache) -> UNet, fusion and Gaussian decoder -> the last decoder layer's
// Gaussians, in the model's frame (first input camera = identity, the model's own scale). Also the input side: any
// RGBA/RGB picture turned into a model-size view the way the data module makes training views (premultiplied
// antialiased bicubic resize, composited on the background), with the intrinsics that follow the crop and resize.
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/gemm.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/model.hpp"
#include "flexsplat/solvers/orbit_search.hpp"
#include "flexsplat/geometry/pose_encoding.hpp"
#include "flexsplat/solvers/procrustes.hpp"
#include "flexsplat/image/layout.hpp"
#include "flexsplat/image/resample.hpp"
#include "flexsplat/model/geometry_result.hpp"
#include "flexsplat/model/geometry_stage.hpp"
#include "flexsplat/model/given_cameras.hpp"
#include "flexsplat/model/weights.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

template <class T>
struct Prediction {
  index_t views = 0, h = 0, w = 0;
  GeometryResult<T> geometry;   // w2c [V, 3, 4], K [V, 3, 3] (pixel centres at +0.5), depth, confidence, features
  std::vector<T> pose_enc;      // [V, 9] the camera head's last refinement iteration
  // Per view, the inlier matches of the view pair that placed its camera (match head); 0: the camera head's camera.
  std::vector<index_t> camera_matches;
  // With CameraSource::given: the capture's world in the model's frame (to_capture_world maps the result back).
  std::optional<GivenFrame> given;
  GaussianSet<T> gaussians;     // the last decoder layer
  // Wall time of the geometry network, the camera solvers after it (matches, orbit, turntable, given frame) and the
  // appearance side (UNet, fusion, decoder).
  double geometry_ms = 0, cameras_ms = 0, decoder_ms = 0;
  // The Gaussian budget and the queries of it the decoder ran (fewer with PredictWorkspace::auto_budget).
  index_t budget = 0, budget_queries = 0;
};

// The predicted input cameras (in the first view's frame, at the model's image size), named by `names` when given.
template <class T>
std::vector<Camera> input_cameras(const Prediction<T>& p, const std::vector<std::string>& names = {}) {
  require(names.empty() || names.size() == static_cast<std::size_t>(p.views), "input_cameras: ", names.size(),
          " names for ", p.views, " views");
  std::vector<Camera> cameras;
  for (index_t v = 0; v < p.views; ++v)
    cameras.push_back(camera_from_arrays(p.geometry.K.data() + 9 * v, p.geometry.extrinsics.data() + 12 * v,
                                         static_cast<int>(p.w), static_cast<int>(p.h),
                                         names.empty() ? std::string() : names[static_cast<std::size_t>(v)]));
  return cameras;
}

// Where the cameras the decoder sees come from. model: the camera head, or with a match head the cameras solved from
// its matches (solvers/procrustes.hpp); orbit_search: the views placed on an orbit around the object by their
// predicted silhouettes (the match head's object probability), depth and colour (solvers/orbit_search.hpp); given:
// the capture's own cameras (PredictWorkspace::given, model/given_cameras.hpp); turntable: photos in order at equal
// azimuth steps around the object, the elevation, direction and distance searched (geometry::cameras_from_turntable).
enum class CameraSource { model, orbit_search, given, turntable };

inline CameraSource parse_camera_source(const std::string& s) {
  if (s == "model") return CameraSource::model;
  if (s == "orbit") return CameraSource::orbit_search;
  if (s == "turntable") return CameraSource::turntable;
  fail("camera source '", s, "' is not one of: model, orbit, turntable");
}

// The orbit search on a model's predicted depth, whose shape is off by about 6 % (docs/evaluation.md): each point is
// placed within 10 % of its predicted depth, and the match head's descriptors weigh each placement.
inline geometry::OrbitSearchConfig predicted_depth_search() {
  geometry::OrbitSearchConfig c;
  c.depth_range = 0.1;
  c.descriptor_weight = 0.5;
  return c;
}

template <class T>
struct PredictWorkspace {
  CameraSource cameras = CameraSource::model;
  geometry::OrbitSearchConfig orbit = predicted_depth_search();  // with CameraSource::orbit_search
  GivenCameras<T> given;                                          // with CameraSource::given
  // [V, h, w] the photos' alpha at the model's size (model_photos), or empty: the object's outline for the given
  // and turntable cameras' searches and the automatic budget, in place of a match head's object probability.
  std::vector<T> silhouettes;
  // The automatic budget: of the Gaussian budget, only the queries whose anchors lie on the object's outline
  // (decoder::queries_on_outline) run; the others would place Gaussians on the background. Prediction::budget_queries
  // tells how many ran.
  bool auto_budget = false;
  double outline_margin = decoder::outline_margin_cells;  // anchor spacings around the outline the budget keeps
  geometry::TurntableResult turntable;                            // with CameraSource::turntable: what was found
  GeometryStage<T> geometry;
  decoder::ModelWorkspace<T> model;
  // Under GemmBackend::bf16: pack the weights to bf16 once (GemmWeightCache, 2 bytes per weight) and keep them for
  // later calls with the same weights object, which must then not change (packed_weights->clear() after changing
  // them). Pays when many predictions share fixed weights (eval): packing costs more than one call's reorders.
  bool keep_packed_weights = false;
  std::unique_ptr<GemmWeightCache> packed_weights;
  const void* packed_for = nullptr;
};

namespace detail {
template <class T>
void require_finite(const T* p, std::size_t n, const char* what) {
  for (std::size_t i = 0; i < n; ++i)
    require(std::isfinite(static_cast<double>(p[i])), "predict: the model produced a non-finite ", what, " (entry ",
            i, " = ", static_cast<double>(p[i]), "); the weights hold NaN/Inf or overflow");
}
}  // namespace detail

// Called between the geometry stage and the decoder with the predicted cameras and depth (in place): where
// experiments change the geometry the decoder sees (eval --rotation-noise); the Prediction holds the changed values.
template <class T>
using BeforeDecoder = std::function<void(GeometryResult<T>&)>;

// images [views, 3, h, w] in [0, 1] at the configuration's size (image_h x image_w). n_gaussians 0: the
// configuration's budget for the view count.
template <class T>
Prediction<T> predict(PredictWorkspace<T>& ws, const FlexSplatWeights<T>& w, const T* images, index_t views,
                      index_t n_gaussians = 0, const BeforeDecoder<T>& before_decoder = {}) {
  const FlexSplatConfig& c = w.config();
  require(images, "predict: null images");
  require(views >= 1 && views <= c.appearance.decoder.max_views, "predict: ", views,
          " input views; the model takes 1 to ", c.appearance.decoder.max_views, " (decoder max_views)");
  const index_t n = n_gaussians > 0 ? n_gaussians : c.gaussians_for(views);
  require(n_gaussians >= 0 && n <= c.appearance.decoder.max_queries, "predict: ", n,
          " Gaussians requested; the decoder has ", c.appearance.decoder.max_queries, " queries (max_queries)");
  const index_t h = c.image_h, wd = c.image_w, values = views * 3 * h * wd;
  for (index_t i = 0; i < values; ++i)
    require(images[i] >= T(0) && images[i] <= T(1), "predict: image value ", static_cast<double>(images[i]),
            " at flat index ", i, " of [", views, ", 3, ", h, ", ", wd, "] is outside [0, 1]");
  std::optional<UseGemmWeightCache> use_packed;
  if (!ws.keep_packed_weights) ws.packed_weights.reset();
  if constexpr (std::is_same_v<T, float>) {
    if (ws.keep_packed_weights && default_gemm_backend() == GemmBackend::bf16) {
      if (!ws.packed_weights) ws.packed_weights = std::make_unique<GemmWeightCache>();
      if (ws.packed_for != &w || ws.packed_weights->empty()) {
        ws.packed_weights->reset();
        ws.packed_weights->freeze(w.store().params(), static_cast<std::size_t>(w.store().size()));
        ws.packed_for = &w;
      }
      use_packed.emplace(*ws.packed_weights);
    }
  }
  using clock = std::chrono::steady_clock;
  const auto t0 = clock::now();
  {
    const profile::Stage stage("geometry");
    geometry_stage_forward(ws.geometry, w, images, views, /*train=*/false);
  }
  const auto t1 = clock::now();
  std::optional<profile::Stage> cameras_stage(std::in_place, "cameras");
  const GeometryResult<T>& g = ws.geometry.result;
  detail::require_finite(g.extrinsics.data(), g.extrinsics.size(), "camera extrinsic");
  detail::require_finite(g.K.data(), g.K.size(), "camera intrinsic");
  detail::require_finite(g.depth.data(), g.depth.size(), "depth");
  // With the match head each view's camera is solved from its matches with the first view where that fit is
  // determined; the camera head's camera stays for the others.
  std::vector<index_t> matched(static_cast<std::size_t>(views), 0);
  if (c.geometry.match_dim > 0 && views > 1 && ws.cameras == CameraSource::model) {
    const auto& o = ws.geometry.outputs;
    std::vector<T> solved(static_cast<std::size_t>(12 * views));
    std::unique_ptr<bool[]> ok(new bool[static_cast<std::size_t>(views)]);
    geometry::cameras_from_matches<T>(solved.data(), o.descriptors.data(), o.foreground.data(), o.depth.data(),
                                      o.intrinsics.data(), views, h, wd, c.geometry.match_dim, ok.get(), matched.data());
    for (index_t v = 1; v < views; ++v) {
      if (!ok[static_cast<std::size_t>(v)]) {
        matched[static_cast<std::size_t>(v)] = 0;
        continue;
      }
      std::copy(solved.begin() + 12 * v, solved.begin() + 12 * (v + 1), ws.geometry.result.extrinsics.begin() + 12 * v);
    }
  }
  if (ws.cameras == CameraSource::orbit_search && views > 1) {
    require(c.geometry.match_dim > 0, "predict: camera source 'orbit' needs the object probability of a match head; "
            "this model has none (geometry match_dim 0)");
    const auto& o = ws.geometry.outputs;
    std::vector<T> solved(static_cast<std::size_t>(12 * views));
    geometry::cameras_from_orbit_search<T>(solved.data(), images, o.foreground.data(), o.depth.data(), o.intrinsics.data(),
                                           views, h, wd, ws.orbit, nullptr, nullptr,
                                           {o.descriptors.data(), c.geometry.match_dim});
    std::copy(solved.begin(), solved.end(), ws.geometry.result.extrinsics.begin());
  }
  require(ws.silhouettes.empty() || ws.silhouettes.size() == static_cast<std::size_t>(views * h * wd), "predict: ",
          ws.silhouettes.size(), " silhouette values; ", views, " views of ", wd, " x ", h, " need ", views * h * wd);
  // The object's outline: the photos' alpha, else a match head's object probability (else null).
  const T* outline = !ws.silhouettes.empty()     ? ws.silhouettes.data()
                     : c.geometry.match_dim > 0 ? ws.geometry.outputs.foreground.data()
                                                : nullptr;
  // Without an outline: every pixel not the white background.
  std::vector<T> fg;
  const T* foreground = outline;
  if (!foreground && ((ws.cameras == CameraSource::turntable && views > 1) || ws.auto_budget)) {
    fg.resize(static_cast<std::size_t>(views * h * wd));
    for (index_t v = 0; v < views; ++v)
      for (index_t i = 0; i < h * wd; ++i) {
        T m = T(1);
        for (int ch = 0; ch < 3; ++ch) m = std::min(m, images[(v * 3 + ch) * h * wd + i]);
        fg[static_cast<std::size_t>(v * h * wd + i)] = m < T(0.98) ? T(1) : T(0);
      }
    foreground = fg.data();
  }
  if (ws.cameras == CameraSource::turntable && views > 1) {
    ws.turntable = geometry::cameras_from_turntable<T>(ws.geometry.result.extrinsics.data(), images, foreground,
                                                       g.depth.data(), ws.geometry.outputs.intrinsics.data(), views, h,
                                                       wd, ws.orbit);
  }
  std::optional<GivenFrame> given;
  if (ws.cameras == CameraSource::given) {
    require(ws.given.views() == views, "predict: ", ws.given.views(), " given cameras for ", views, " input views");
    given = given_frame(ws.given, images, g.depth.data(), outline, h, wd);
    place_given_cameras(ws.given, *given, ws.geometry.result.K.data(), ws.geometry.result.extrinsics.data());
  }
  if (before_decoder) before_decoder(ws.geometry.result);
  cameras_stage.reset();
  const auto t_decoder = clock::now();
  ws.model.keep_for_backward = false;  // no backward follows: the decoder's layers share one cache, no RGB head
  // An outline with no object on it tells nothing to skip: the whole budget runs.
  ws.model.decoder.subset.clear();
  if (ws.auto_budget)
    ws.model.decoder.subset = decoder::queries_on_outline(n, views, wd, h, foreground, ws.outline_margin);
  {
    const profile::Stage stage("appearance");
    decoder::model_forward(ws.model, n, w.appearance(), c.appearance, images, h, wd, g.features.data(), g.feature_h,
                           g.feature_w, g.view_geometry());
  }
  const index_t ran = ws.model.decoder.subset.empty() ? n : static_cast<index_t>(ws.model.decoder.subset.size());
  ws.model.decoder.subset.clear();
  const auto t2 = clock::now();
  Prediction<T> p;
  p.views = views, p.h = h, p.w = wd;
  p.gaussians = ws.model.gaussians().back();
  const GaussianSet<T>& s = p.gaussians;
  for (const auto* t : {&s.means, &s.quats, &s.scales}) detail::require_finite(t->data(), static_cast<std::size_t>(t->size()), "Gaussian parameter");
  detail::require_finite(s.opacities.data(), static_cast<std::size_t>(s.opacities.size()), "Gaussian opacity");
  detail::require_finite(s.sh.data(), static_cast<std::size_t>(s.sh.size()), "Gaussian colour");
  const std::size_t last = static_cast<std::size_t>((ws.geometry.iterations - 1) * views * geometry::pose_encoding_dim);
  p.pose_enc.assign(ws.geometry.pose_enc.begin() + static_cast<std::ptrdiff_t>(last), ws.geometry.pose_enc.end());
  p.camera_matches = std::move(matched);
  p.budget = n;
  p.budget_queries = ran;
  p.given = given;
  p.geometry = std::move(ws.geometry.result);  // the workspace refills it on the next call
  p.geometry_ms = std::chrono::duration<double, std::milli>(t1 - t0).count();
  p.cameras_ms = std::chrono::duration<double, std::milli>(t_decoder - t1).count();
  p.decoder_ms = std::chrono::duration<double, std::milli>(t2 - t_decoder).count();
  return p;
}

// The same from a tensor, whose shape is checked against the model.
template <class T>
Prediction<T> predict(PredictWorkspace<T>& ws, const FlexSplatWeights<T>& w, TensorView<const T, 4> images,
                      index_t n_gaussians = 0, const BeforeDecoder<T>& before_decoder = {}) {
  const FlexSplatConfig& c = w.config();
  require(images.shape(1) == 3 && images.shape(2) == c.image_h && images.shape(3) == c.image_w,
          "predict: images have shape ", shape_string(images.shape()), "; the model takes [V, 3, ", c.image_h, ", ",
          c.image_w, "] (prepare them with model::model_view)");
  require(images.is_contiguous(), "predict: images must be contiguous, got shape ", shape_string(images.shape()));
  return predict(ws, w, images.data(), images.shape(0), n_gaussians, before_decoder);
}

// How a source picture maps onto a model view: centre crop (x0, y0, width x height in source pixels), then resize by
// scale_x, scale_y. With pixel centres at +0.5, K follows as fx' = fx sx, cx' = (cx - x0) sx (and y alike).
struct ViewMapping {
  index_t x0 = 0, y0 = 0, width = 0, height = 0;
  double scale_x = 1, scale_y = 1;

  // Row-major K [3, 3] of the source camera -> the model view's (in place).
  void intrinsics(double* K) const {
    K[0] *= scale_x, K[1] *= scale_x, K[2] = (K[2] - static_cast<double>(x0)) * scale_x;
    K[4] *= scale_y, K[5] = (K[5] - static_cast<double>(y0)) * scale_y;
  }
  // The inverse: the model view's K -> the source camera's (in place).
  void to_source(double* K) const {
    K[0] /= scale_x, K[1] /= scale_x, K[2] = K[2] / scale_x + static_cast<double>(x0);
    K[4] /= scale_y, K[5] = K[5] / scale_y + static_cast<double>(y0);
  }
};

// The largest centred window of a W x H picture with the aspect ratio of h x w.
inline ViewMapping view_mapping(index_t W, index_t H, index_t h, index_t w) {
  require(W >= 1 && H >= 1, "model view: source image is ", W, " x ", H, " (empty)");
  require(h >= 1 && w >= 1, "model view: target size ", w, " x ", h, " is empty");
  ViewMapping m;
  // Compare W/H with w/h in integers: keep the full width when the picture is relatively taller.
  if (W * h <= H * w) {
    m.width = W;
    m.height = std::clamp<index_t>(static_cast<index_t>(std::llround(static_cast<double>(W) * h / w)), 1, H);
  } else {
    m.height = H;
    m.width = std::clamp<index_t>(static_cast<index_t>(std::llround(static_cast<double>(H) * w / h)), 1, W);
  }
  m.x0 = (W - m.width) / 2, m.y0 = (H - m.height) / 2;
  m.scale_x = static_cast<double>(w) / static_cast<double>(m.width);
  m.scale_y = static_cast<double>(h) / static_cast<double>(m.height);
  return m;
}

// rgba [H, W, 4] straight alpha in [0, 1] -> out [3, h, w] (CHW, the model's input layout) composited on
// `background`: the centred window of the model's aspect ratio, resized as data::sample_batch resizes training
// views (antialiased bicubic on premultiplied RGBA, colour clamped to [0, alpha]; a window of the model's size is
// copied). alpha_out [h, w] may be null.
template <class T>
ViewMapping model_view(T* out, TensorView<const float, 3> rgba, index_t h, index_t w,
                       const std::array<float, 3>& background = {1.0f, 1.0f, 1.0f}, T* alpha_out = nullptr) {
  require(rgba.shape(2) == 4, "model view: image has shape ", shape_string(rgba.shape()),
          "; expected [H, W, 4] RGBA (read it with image::read_float(path, 4))");
  const ViewMapping m = view_mapping(rgba.shape(1), rgba.shape(0), h, w);
  for (index_t i = 0; i < rgba.size(); ++i)
    require(rgba.data()[i] >= 0.0f && rgba.data()[i] <= 1.0f, "model view: pixel value ", rgba.data()[i],
            " outside [0, 1]");
  const index_t px = h * w;
  auto put = [&](index_t y, index_t x, const float rgb[3], float a) {
    for (int ch = 0; ch < 3; ++ch) out[ch * px + y * w + x] = static_cast<T>(rgb[ch]);
    if (alpha_out) alpha_out[y * w + x] = static_cast<T>(a);
  };
  if (m.width == w && m.height == h) {
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x) {
        const float a = rgba(m.y0 + y, m.x0 + x, 3);
        float c[3];
        for (int ch = 0; ch < 3; ++ch) c[ch] = rgba(m.y0 + y, m.x0 + x, ch) * a + background[static_cast<std::size_t>(ch)] * (1.0f - a);
        put(y, x, c, a);
      }
    return m;
  }
  Tensor<float, 3> planar(Shape<3>{4, m.height, m.width});
  for (index_t y = 0; y < m.height; ++y)
    for (index_t x = 0; x < m.width; ++x) {
      const float a = rgba(m.y0 + y, m.x0 + x, 3);
      for (int ch = 0; ch < 3; ++ch) planar(ch, y, x) = rgba(m.y0 + y, m.x0 + x, ch) * a;
      planar(3, y, x) = a;
    }
  const Tensor<float, 3> resized = interpolate_bicubic_antialias<float>(TensorView<const float, 3>(planar.view()), h, w);
  for (index_t y = 0; y < h; ++y)
    for (index_t x = 0; x < w; ++x) {
      const float a = std::clamp(resized(3, y, x), 0.0f, 1.0f);
      float c[3];
      for (int ch = 0; ch < 3; ++ch)
        c[ch] = std::clamp(resized(ch, y, x), 0.0f, a) + background[static_cast<std::size_t>(ch)] * (1.0f - a);
      put(y, x, c, a);
    }
  return m;
}

// Several pictures as the model's input tensor [V, 3, image_h, image_w]; mappings (may be null) receives one
// ViewMapping per picture.
template <class T>
Tensor<T, 4> model_input(const std::vector<Tensor<float, 3>>& rgba, const FlexSplatConfig& c,
                         std::vector<ViewMapping>* mappings = nullptr,
                         const std::array<float, 3>& background = {1.0f, 1.0f, 1.0f}, std::vector<T>* alpha = nullptr) {
  const index_t V = static_cast<index_t>(rgba.size());
  require(V >= 1, "model input: no images");
  Tensor<T, 4> out(Shape<4>{V, 3, c.image_h, c.image_w});
  if (mappings) mappings->clear();
  if (alpha) alpha->assign(static_cast<std::size_t>(V * c.image_h * c.image_w), T(1));
  for (index_t v = 0; v < V; ++v) {
    try {
      // A window smaller than one patch is less than one token of picture (a one-pixel "photo"): nothing to see.
      const auto& im = rgba[static_cast<std::size_t>(v)];
      const index_t p = c.geometry.aggregator.patch_size;
      const ViewMapping window = view_mapping(im.shape(1), im.shape(0), c.image_h, c.image_w);
      require(window.width >= p && window.height >= p, "its ", window.width, " x ", window.height,
              " pixel window (of ", im.shape(1), " x ", im.shape(0), ") is smaller than one ", p, " x ", p,
              " patch of the model");
      const ViewMapping m = model_view<T>(out.data() + v * 3 * c.image_h * c.image_w,
                                          TensorView<const float, 3>(rgba[static_cast<std::size_t>(v)].view()),
                                          c.image_h, c.image_w, background,
                                          alpha ? alpha->data() + v * c.image_h * c.image_w : nullptr);
      if (mappings) mappings->push_back(m);
    } catch (const Error& e) {
      fail("model input: image ", v, " of ", V, ": ", e.what());
    }
  }
  return out;
}

// The photos as the model sees them, resized once: the input tensor [V, 3, image_h, image_w] and their alpha at that
// size [V, h, w] (PredictWorkspace::silhouettes), empty when every pixel is opaque.
template <class T>
struct ModelPhotos {
  Tensor<T, 4> images;
  std::vector<T> silhouettes;
};

template <class T>
ModelPhotos<T> model_photos(const std::vector<Tensor<float, 3>>& rgba, const FlexSplatConfig& c) {
  ModelPhotos<T> m;
  m.images = model_input<T>(rgba, c, nullptr, {1.0f, 1.0f, 1.0f}, &m.silhouettes);
  if (std::all_of(m.silhouettes.begin(), m.silhouettes.end(), [](T a) { return a >= T(1); })) m.silhouettes.clear();
  return m;
}

// A capture's cameras of the photos (io::cameras_for_images: one per photo, in order, at the photo's own size) for
// the model: K through each photo's window to the model's size.
template <class T>
GivenCameras<T> given_cameras(const std::vector<Tensor<float, 3>>& rgba, const std::vector<Camera>& cameras,
                              const FlexSplatConfig& c) {
  require(cameras.size() == rgba.size(), "given cameras: ", cameras.size(), " cameras for ", rgba.size(), " photos");
  GivenCameras<T> g;
  g.K.resize(9 * rgba.size());
  g.w2c.resize(12 * rgba.size());
  std::vector<ViewMapping> maps;
  for (const auto& im : rgba) maps.push_back(view_mapping(im.shape(1), im.shape(0), c.image_h, c.image_w));
  for (std::size_t v = 0; v < rgba.size(); ++v) {
    const Camera& cam = cameras[v];
    require(cam.width == rgba[v].shape(1) && cam.height == rgba[v].shape(0), "given cameras: camera '", cam.name,
            "' is for a ", cam.width, " x ", cam.height, " image; photo ", v, " is ", rgba[v].shape(1), " x ",
            rgba[v].shape(0));
    camera_arrays(cam, g.K.data() + 9 * v, g.w2c.data() + 12 * v);
    maps[v].intrinsics(g.K.data() + 9 * v);
  }
  return g;
}

// Photos (RGBA [H, W, 4], any size) with their capture's cameras (io::cameras_for_images) -> the prediction in the
// model's frame with `given` set: the decoder sees the capture's cameras, refinement may follow (model::refine with the
// cameras fixed), then to_capture_world brings it to the capture's world.
template <class T>
Prediction<T> predict_posed(PredictWorkspace<T>& ws, const FlexSplatWeights<T>& w,
                            const std::vector<Tensor<float, 3>>& rgba, const std::vector<Camera>& cameras,
                            index_t n_gaussians = 0) {
  ModelPhotos<T> photos = model_photos<T>(rgba, w.config());
  ws.cameras = CameraSource::given;
  ws.given = given_cameras<T>(rgba, cameras, w.config());
  ws.silhouettes = std::move(photos.silhouettes);
  return predict(ws, w, TensorView<const T, 4>(photos.images.view()), n_gaussians);
}

// A prediction made with given cameras, brought to the capture's world: the Gaussians by the similarity of its frame
// and the cameras (geometry.extrinsics) back to the capture's world-to-camera (K stays at the model's size).
template <class T>
void to_capture_world(Prediction<T>& p) {
  require(p.given.has_value(), "to_capture_world: the prediction was not made with given cameras");
  gaussians_to_world(p.gaussians, p.given->frame);
  const Similarity s = model_to_world(p.given->frame);
  for (index_t v = 0; v < p.views; ++v) {
    double E[12];
    for (int i = 0; i < 12; ++i) E[i] = static_cast<double>(p.geometry.extrinsics[static_cast<std::size_t>(12 * v + i)]);
    transform_camera(E, s);
    for (int i = 0; i < 12; ++i) p.geometry.extrinsics[static_cast<std::size_t>(12 * v + i)] = static_cast<T>(E[i]);
  }
  p.given.reset();
}

// The size the photos are refined at: `longer` pixels on the model's longer side with its aspect ratio, or with
// longer 0 the largest of the photos' windows of that aspect ratio (the pictures' own resolution).
inline std::array<index_t, 2> refine_size(const std::vector<Tensor<float, 3>>& rgba, const FlexSplatConfig& c,
                                          index_t longer = 0) {
  require(!rgba.empty(), "refine size: no images");
  require(longer >= 0, "refine size: ", longer, " pixels");
  if (longer > 0) {
    const double aspect = static_cast<double>(c.image_w) / static_cast<double>(c.image_h);
    if (c.image_w >= c.image_h)
      return {std::max<index_t>(1, static_cast<index_t>(std::llround(static_cast<double>(longer) / aspect))), longer};
    return {longer, std::max<index_t>(1, static_cast<index_t>(std::llround(static_cast<double>(longer) * aspect)))};
  }
  std::array<index_t, 2> hw{1, 1};
  for (const auto& im : rgba) {
    const ViewMapping m = view_mapping(im.shape(1), im.shape(0), c.image_h, c.image_w);
    hw[0] = std::max(hw[0], m.height), hw[1] = std::max(hw[1], m.width);
  }
  return hw;
}

// Photos as fitting targets at h x w: each one's window resized as model_view does for the model (the pictures the
// model saw, at another size), [V, h, w, 3] on white, with its alpha [V, h, w]; and K [V, 3, 3], each photo's
// intrinsics K_photo (in its own pixels, row-major) carried to h x w through the same window.
template <class T>
struct PhotoTargets {
  index_t views = 0, h = 0, w = 0;
  std::vector<T> images, alpha, K;
};

template <class T>
PhotoTargets<T> photo_targets(const std::vector<Tensor<float, 3>>& rgba, const std::vector<double>& K_photo, index_t h,
                              index_t w) {
  require(h >= 1 && w >= 1, "photo targets: size ", w, " x ", h, " is empty");
  require(K_photo.size() == 9 * rgba.size(), "photo targets: ", K_photo.size(), " intrinsics values for ",
          rgba.size(), " photos (need 9 each)");
  PhotoTargets<T> t;
  t.views = static_cast<index_t>(rgba.size()), t.h = h, t.w = w;
  t.images.resize(static_cast<std::size_t>(t.views * h * w * 3));
  t.alpha.resize(static_cast<std::size_t>(t.views * h * w));
  std::vector<T> chw(static_cast<std::size_t>(3 * h * w));
  for (index_t v = 0; v < t.views; ++v) {
    const ViewMapping there = model_view<T>(chw.data(), TensorView<const float, 3>(rgba[static_cast<std::size_t>(v)].view()),
                                            h, w, {1.0f, 1.0f, 1.0f}, t.alpha.data() + v * h * w);
    image::chw_to_hwc(t.images.data() + v * h * w * 3, chw.data(), h, w);
    double K[9];
    std::copy_n(K_photo.data() + 9 * v, 9, K);
    there.intrinsics(K);
    for (int i = 0; i < 9; ++i) t.K.push_back(static_cast<T>(K[i]));
  }
  return t;
}

// The same with each photo's camera (at the photo's own size).
template <class T>
PhotoTargets<T> photo_targets(const std::vector<Tensor<float, 3>>& rgba, const std::vector<Camera>& cameras, index_t h,
                              index_t w) {
  std::vector<double> K(9 * cameras.size());
  for (std::size_t v = 0; v < cameras.size(); ++v) camera_arrays(cameras[v], K.data() + 9 * v, static_cast<double*>(nullptr));
  return photo_targets<T>(rgba, K, h, w);
}

// The same with the model's intrinsics K_model [V, 3, 3] (at its image_h x image_w), carried back to each photo first.
template <class T>
PhotoTargets<T> photo_targets(const std::vector<Tensor<float, 3>>& rgba, const FlexSplatConfig& c, const T* K_model,
                              index_t h, index_t w) {
  std::vector<double> K(9 * rgba.size());
  for (std::size_t v = 0; v < rgba.size(); ++v) {
    for (int i = 0; i < 9; ++i) K[9 * v + i] = static_cast<double>(K_model[9 * v + i]);
    view_mapping(rgba[v].shape(1), rgba[v].shape(0), c.image_h, c.image_w).to_source(K.data() + 9 * v);
  }
  return photo_targets<T>(rgba, K, h, w);
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
