#pragma once
// The evaluation protocol of a pose-free model on object folders (the layout of ../shared/data/objects, read by
// data::load_objects): input views, held-out targets, the predicted input cameras aligned to the ground truth by a
// similarity (align_cameras: Umeyama's least-squares estimator with scale over the camera centres), the camera
// errors, and every target rendered from its ground-truth camera mapped into the model's frame, on white, at the
// model's size, scored against the ground truth resized the same way (PSNR, SSIM, optionally LPIPS). Also the
// experiments' pieces: rotation noise on predicted cameras, the input views for test-time refinement and the
// posed-fit baseline (a per-scene fit from the input views with their ground-truth cameras). docs/app.md.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/layout.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/loss/ssim.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/frames.hpp"
#include "flexsplat/train/objective.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/eval/refine.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

struct EvalOptions {
  int view_count = 0;             // 0: the folder's input_views; N: those when it lists N, else N evenly spaced frames
  std::vector<int> view_list;     // explicit input frames (overrides view_count)
  int max_targets = 0;            // 0: every other frame
  bool white_baseline = false;    // also score a white image against each target
  int grid_targets = 0;           // keep this many (ground truth, render) pairs for a picture
  const loss::LpipsWeights<float>* lpips = nullptr;  // null: no LPIPS (NaN)
};

// "4" (a view count) or "9,26,3" (the input frames, in that order; "9," one frame) into o.view_count / o.view_list.
inline void set_views(EvalOptions& o, const std::string& text) {
  std::vector<int> values;
  std::istringstream in(text);
  for (std::string item; std::getline(in, item, ',');) {  // "9," yields one item
    std::size_t used = 0;
    int v = -1;
    try {
      v = std::stoi(item, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    require(used == item.size() && !item.empty() && v >= 0, "views '", text,
            "': expected a view count or comma-separated frame indices");
    values.push_back(v);
  }
  require(!values.empty(), "views '", text, "': expected a view count or comma-separated frame indices");
  o.view_count = 0, o.view_list.clear();
  if (values.size() == 1 && text.find(',') == std::string::npos) {
    require(values[0] >= 1, "views ", values[0], ": need at least one input view");
    o.view_count = values[0];
  } else {
    o.view_list = values;
  }
}

// Means over the targets; NaN = not measured.
struct EvalScores {
  double psnr = 0, ssim = 0, lpips = std::numeric_limits<double>::quiet_NaN();
};

struct EvalResult {
  std::vector<int> inputs, targets;
  EvalScores model, white;
  double rotation_error_deg = 0;  // median over the input views, after alignment
  double center_error_rel = 0;    // median camera-centre distance after alignment / object_size
  double object_size = 0;         // diagonal of the box around the input views' ground-truth depth points
  Similarity alignment;           // model frame -> world
  std::vector<std::vector<float>> grid_gt, grid_render;  // [h, w, 3] each
};

struct EvalWorkspace {
  loss::SsimWorkspace ssim;
  loss::LpipsCache<float> lpips;
  std::vector<float> a_chw, b_chw, target_chw, target, white;
  raster::RenderWorkspace<float> render;
  raster::RenderOutputs<float> out;
};

inline double median_of(std::vector<double> v) {
  require(!v.empty(), "eval: median of no values");
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Input frames and targets of a folder under the protocol.
inline void eval_views(const data::ObjectRecord& rec, const EvalOptions& o, std::vector<int>& in,
                       std::vector<int>& targets) {
  const int frames = static_cast<int>(rec.frames.size());
  in.clear();
  if (!o.view_list.empty()) {
    in = o.view_list;
  } else if (o.view_count == 0 || o.view_count == static_cast<int>(rec.input_views.size())) {
    in = rec.input_views;
    require(!in.empty(), "eval: '", rec.dir.string(), "/cameras.json' lists no input_views; pass a view count or list");
  } else {
    require(o.view_count >= 1 && o.view_count < frames, "eval: ", o.view_count, " input views of the ", frames,
            " frames of '", rec.dir.string(), "' leave no target");
    for (int i = 0; i < o.view_count; ++i) in.push_back(i * frames / o.view_count);
  }
  for (int v : in) {
    require(v >= 0 && v < frames, "eval: input view ", v, " is not a frame of '", rec.dir.string(), "' (", frames,
            " frames)");
    require(std::count(in.begin(), in.end(), v) == 1, "eval: input view ", v, " is listed twice");
  }
  targets.clear();
  for (int f = 0; f < frames; ++f)
    if (std::find(in.begin(), in.end(), f) == in.end()) targets.push_back(f);
  require(!targets.empty(), "eval: all ", frames, " frames of '", rec.dir.string(), "' are inputs; no target is left");
  if (o.max_targets > 0 && static_cast<int>(targets.size()) > o.max_targets)
    targets.resize(static_cast<std::size_t>(o.max_targets));
}

// Diagonal of the axis-aligned box around the ground-truth surface points the input views see (their depth maps
// unprojected to the world): the object's size, the unit of center_error_rel.
inline double eval_object_size(const data::ObjectRecord& rec, const std::vector<int>& in) {
  glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
  for (int v : in) {
    const data::FrameRecord& fr = rec.frames[static_cast<std::size_t>(v)];
    const Tensor<double, 2> depth = image::read_depth_png<double>(fr.depth, rec.depth_scale);
    const Camera& c = fr.camera;
    for (index_t y = 0; y < depth.shape(0); ++y)
      for (index_t x = 0; x < depth.shape(1); ++x) {
        const double z = depth(y, x);
        if (!(z > 0)) continue;
        const glm::dvec3 p =
            c.to_world(c.unproject({static_cast<double>(x) + 0.5, static_cast<double>(y) + 0.5}, z));
        lo = glm::min(lo, p), hi = glm::max(hi, p);
      }
  }
  const double size = glm::length(hi - lo);
  require(std::isfinite(size) && size > 0, "eval: the input views' depth maps of '", rec.dir.string(),
          "' show no surface; the object size is undefined");
  return size;
}

namespace detail {
// a, b [h, w, 3] in [0, 1]: adds PSNR, SSIM and (with weights) LPIPS into s.
inline void add_scores(EvalScores& s, EvalWorkspace& ws, const EvalOptions& o, const float* a, const float* b,
                       index_t h, index_t w) {
  s.psnr += loss::psnr(a, b, 3 * h * w);
  s.ssim += loss::ssim_forward(a, b, loss::ImageShape{1, 3, h, w, loss::Layout::nhwc}, loss::SsimConfig{}, ws.ssim);
  if (!o.lpips) return;
  ws.a_chw.resize(static_cast<std::size_t>(3 * h * w)), ws.b_chw.resize(ws.a_chw.size());
  image::hwc_to_chw(ws.a_chw.data(), a, h, w);
  image::hwc_to_chw(ws.b_chw.data(), b, h, w);
  float value = 0;
  loss::lpips_forward(&value, static_cast<float*>(nullptr), ws.a_chw.data(), ws.b_chw.data(), 1, h, w,
                      o.lpips->params.data(), o.lpips->layout, ws.lpips, true);
  s.lpips = (std::isnan(s.lpips) ? 0.0 : s.lpips) + value;
}
}  // namespace detail

// Scores a prediction of the folder's input views `in` (cameras pred_w2c [V, 3, 4] in the model's frame, Gaussians
// in that frame) on `targets`, rendered at h x w (the model's size).
inline EvalResult score_prediction(const data::ObjectRecord& rec, const std::vector<int>& in,
                                   const std::vector<int>& targets, const float* pred_w2c,
                                   const GaussianSet<float>& gaussians, index_t h, index_t w, const EvalOptions& o,
                                   EvalWorkspace& ws) {
  const index_t V = static_cast<index_t>(in.size()), px = h * w;
  require(V >= 1 && !targets.empty(), "eval: ", V, " inputs and ", targets.size(), " targets; need at least one of each");
  EvalResult r;
  r.inputs = in, r.targets = targets;
  std::vector<double> pred(static_cast<std::size_t>(12 * V)), gt(static_cast<std::size_t>(12 * V));
  for (index_t v = 0; v < V; ++v) {
    double K[9];
    camera_arrays(rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])].camera, K, &gt[12 * v]);
    for (int i = 0; i < 12; ++i) pred[static_cast<std::size_t>(12 * v + i)] = pred_w2c[12 * v + i];
  }
  const Similarity S = align_cameras(pred.data(), gt.data(), V);
  r.alignment = S;
  r.object_size = eval_object_size(rec, in);
  std::vector<double> rot, centre;
  for (index_t v = 0; v < V; ++v) {
    double aligned[12];
    std::copy(&pred[12 * v], &pred[12 * v] + 12, aligned);
    transform_camera(aligned, S);
    rot.push_back(rotation_error_deg(aligned, &gt[12 * v]));
    centre.push_back((camera_centre(aligned) - camera_centre(&gt[12 * v])).norm() / r.object_size);
  }
  r.rotation_error_deg = median_of(rot);
  r.center_error_rel = median_of(centre);

  // Ground-truth target cameras go to the model's frame through the inverse similarity.
  Similarity inv;
  inv.R = S.R.transpose();
  inv.scale = 1.0 / S.scale;
  inv.t = -inv.scale * (inv.R * S.t);
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  ws.target_chw.resize(static_cast<std::size_t>(3 * px));
  ws.target.resize(ws.target_chw.size());
  ws.white.assign(ws.target_chw.size(), 1.0f);
  for (std::size_t m = 0; m < targets.size(); ++m) {
    const data::FrameRecord& fr = rec.frames[static_cast<std::size_t>(targets[m])];
    const Tensor<float, 3> rgba = image::read_float<float>(fr.image, 4);
    const ViewMapping map = model_view<float>(ws.target_chw.data(), TensorView<const float, 3>(rgba.view()), h, w);
    image::chw_to_hwc(ws.target.data(), ws.target_chw.data(), h, w);
    double K[9], E[12];
    camera_arrays(fr.camera, K, E);
    map.intrinsics(K);
    transform_camera(E, inv);
    float Kf[9], Ef[12];
    std::copy(K, K + 9, Kf);
    std::copy(E, E + 12, Ef);
    raster::render_forward(gaussians, raster::view_from_arrays(Kf, Ef, static_cast<int>(w), static_cast<int>(h)), ro, ws.render,
                           ws.out);
    const float* img = ws.out.image.data();
    detail::add_scores(r.model, ws, o, img, ws.target.data(), h, w);
    if (o.white_baseline) detail::add_scores(r.white, ws, o, ws.white.data(), ws.target.data(), h, w);
    if (static_cast<int>(m) < o.grid_targets) {
      r.grid_gt.push_back(ws.target);
      r.grid_render.emplace_back(img, img + 3 * px);
    }
  }
  const double n = static_cast<double>(targets.size());
  for (EvalScores* s : {&r.model, &r.white}) s->psnr /= n, s->ssim /= n, s->lpips /= n;
  if (!o.white_baseline) r.white = EvalScores{std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN()};
  return r;
}

// The seed of one object's random draws: seed XOR FNV-1a of its name, so an object's draws do not depend on which
// other objects are evaluated with it.
inline std::uint64_t object_seed(const std::string& name, std::uint64_t seed) {
  std::uint64_t h = 1469598103934665603ull;
  for (unsigned char ch : name) h = (h ^ ch) * 1099511628211ull;
  return seed ^ h;
}

// The folder's own cameras of the input views `in` in place of the predicted ones (g at the model's size): w2c
// relative to the first input view, K through the model's window, translations in the predicted depth's units (the
// median over the input views' surface pixels of predicted / true depth, which is returned), so that the decoder's
// depth-tied centres and the cameras agree. What the appearance side makes of exact cameras (eval --cameras truth).
template <class T>
double true_input_cameras(const data::ObjectRecord& rec, const std::vector<int>& in, GeometryResult<T>& g) {
  const index_t V = static_cast<index_t>(in.size());
  require(V == g.views, "true input cameras: ", V, " input views and a prediction of ", g.views);
  std::vector<double> ratios, E(static_cast<std::size_t>(12 * V));
  for (index_t v = 0; v < V; ++v) {
    const data::FrameRecord& fr = rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])];
    const Tensor<double, 2> depth = image::read_depth_png<double>(fr.depth, rec.depth_scale);
    const ViewMapping map = view_mapping(depth.shape(1), depth.shape(0), g.h, g.w);
    for (index_t y = 0; y < g.h; ++y)
      for (index_t x = 0; x < g.w; ++x) {
        const auto sx = std::min(depth.shape(1) - 1, map.x0 + static_cast<index_t>((x + 0.5) / map.scale_x));
        const auto sy = std::min(depth.shape(0) - 1, map.y0 + static_cast<index_t>((y + 0.5) / map.scale_y));
        const double z = depth(sy, sx);
        const double p = static_cast<double>(g.depth[static_cast<std::size_t>((v * g.h + y) * g.w + x)]);
        if (z > 0 && p > 0) ratios.push_back(p / z);
      }
    double K[9];
    camera_arrays(fr.camera, K, &E[static_cast<std::size_t>(12 * v)]);
    map.intrinsics(K);
    for (int i = 0; i < 9; ++i) g.K[static_cast<std::size_t>(9 * v + i)] = static_cast<T>(K[i]);
  }
  require(!ratios.empty(), "true input cameras: the depth maps of '", rec.dir.string(),
          "' show no surface where the predicted depth is positive; the depth scale is undefined");
  const double s = median_of(ratios);
  FirstCameraFrame frame;  // the first input's camera frame, lengths times s
  frame.first_w2c = to_matrix4(E.data());
  frame.scale = 1.0 / s;
  for (index_t v = 0; v < V; ++v) frame.camera(&E[static_cast<std::size_t>(12 * v)]);
  std::transform(E.begin(), E.end(), g.extrinsics.begin(), [](double x) { return static_cast<T>(x); });
  return s;
}

// A folder's input views at h x w (model::photo_targets) with their ground-truth cameras: what the posed-fit
// baseline is given.
struct PosedViews {
  PhotoTargets<float> photos;
  std::vector<float> w2c;  // [V, 3, 4]

  RefineViews<float> refine_views() {
    return {photos.views, photos.h, photos.w, photos.images.data(), photos.K.data(), w2c.data(), photos.alpha.data()};
  }
};

inline PosedViews posed_views(const data::ObjectRecord& rec, const std::vector<int>& in, index_t h, index_t w) {
  std::vector<Tensor<float, 3>> rgba;
  std::vector<Camera> cameras;
  PosedViews p;
  for (int v : in) {
    const data::FrameRecord& fr = rec.frames[static_cast<std::size_t>(v)];
    rgba.push_back(image::read_float<float>(fr.image, 4));
    cameras.push_back(fr.camera);
    double E[12];
    camera_arrays(fr.camera, static_cast<double*>(nullptr), E);
    p.w2c.insert(p.w2c.end(), E, E + 12);
  }
  p.photos = photo_targets<float>(rgba, cameras, h, w);
  return p;
}

struct PosedFit {
  GaussianSet<float> gaussians;
  std::vector<float> w2c;  // the ground-truth input cameras (the fit's frame is the world)
  RefineResult refine;
  double seconds = 0;      // reading the views, the initialisation and the fit
};

// The posed-fit baseline: n Gaussians of SH degree `degree` started by random_gaussians_in_views (uniform in the
// views' silhouettes, seeded), then refine with the cameras fixed until `seconds` have passed since the start
// (reading the views included; at least one step).
inline PosedFit posed_fit(const data::ObjectRecord& rec, const std::vector<int>& in, index_t h, index_t w, index_t n,
                          int degree, double seconds, std::uint64_t seed) {
  const auto t0 = std::chrono::steady_clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(); };
  PosedViews views = posed_views(rec, in, h, w);
  PosedFit f;
  f.gaussians = random_gaussians_in_views<float>(n, degree, views.refine_views(), views.photos.alpha.data(), seed);
  RefineConfig rc;
  rc.optimize_cameras = false;
  rc.carve = false;  // the start lies in the silhouettes already
  rc.seconds = std::max(0.0, seconds - elapsed());
  if (rc.seconds <= 0) rc.steps = 1;
  RefineWorkspace<float> ws;
  f.refine = refine(f.gaussians, views.refine_views(), rc, ws);
  f.w2c = views.w2c;
  f.seconds = elapsed();
  return f;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
