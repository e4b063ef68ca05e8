#pragma once
// What `flexsplat reconstruct` does between reading the photos and writing the file: the prediction with the model's,
// the orbit search's, the turntable's or the capture's own cameras, test-time refinement, the compact splat, the
// cameras for the .glb, and the turntable picture. docs/app.md.
//
//   model::ReconstructOptions o;
//   o.refine_seconds = 10;
//   const model::Reconstruction r = model::reconstruct(*weights, rgba, o);   // rgba: [H, W, 4] photos, any size
//   gltf::WriteOptions wo;
//   wo.cameras = r.cameras;
//   gaussians::write_gaussians(r.prediction.gaussians, "out.glb", wo);
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdarg>
#include <cstdio>
#include <functional>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <glm/glm.hpp>
#include <glm/gtc/matrix_transform.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/eval/compact.hpp"
#include "flexsplat/eval/refine.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

struct ReconstructOptions {
  CameraSource cameras = CameraSource::model;  // given: the photos' own cameras in `given`
  std::vector<Camera> given;       // with CameraSource::given: each photo's camera, at its size (io::cameras_for_photos)
  index_t gaussians = 0;           // 0: the model's budget for the view count
  bool auto_budget = false;        // only the budget's queries on the photos' outline (PredictWorkspace::auto_budget)
  double refine_seconds = 0;       // > 0: test-time refinement on the photos
  index_t refine_longer = 0;       // its longer side in pixels (0: the photos' own resolution)
  bool refine_validate = false;    // its step count chosen on the last photo held out of a trial
  index_t refine_grow = refine_grow_gaussians;
  bool compact = true;             // compact_splat before returning
  std::vector<std::string> names;  // the photos' names for the .glb cameras (empty: unnamed)
  // Progress lines (no trailing newline); empty: silent.
  std::function<void(const std::string&)> log;
};

struct Reconstruction {
  // In the capture's world and units with given cameras (to_capture_world), else the first view's frame.
  Prediction<float> prediction;
  std::vector<Camera> cameras;         // the .glb's: the capture's with given cameras, else the predicted (refined)
  std::optional<RefineResult> refine;  // with refine_seconds > 0
  std::optional<CompactReport> compact;
  std::vector<std::pair<std::string, double>> stage_ms;  // wall time of each stage, in order
};

namespace reconstruct_detail {
inline std::string format(const char* f, ...) {
  char buf[512];
  va_list args;
  va_start(args, f);
  std::vsnprintf(buf, sizeof buf, f, args);
  va_end(args);
  return buf;
}
}  // namespace reconstruct_detail

// Photos (RGBA [H, W, 4] in [0, 1], any size, 1 to the model's max_views) -> the splat reconstruct writes.
inline Reconstruction reconstruct(const FlexSplatWeights<float>& w, const std::vector<Tensor<float, 3>>& rgba,
                                  const ReconstructOptions& o) {
  using reconstruct_detail::format;
  const FlexSplatConfig& c = w.config();
  const bool given = o.cameras == CameraSource::given;
  require(!rgba.empty(), "reconstruct: no photos");
  require(static_cast<index_t>(rgba.size()) <= c.appearance.decoder.max_views, "reconstruct: ", rgba.size(),
          " images; the model takes 1 to ", c.appearance.decoder.max_views);
  require(!given || o.given.size() == rgba.size(), "reconstruct: ", o.given.size(), " given cameras for ",
          rgba.size(), " photos");
  require(o.names.empty() || o.names.size() == rgba.size(), "reconstruct: ", o.names.size(), " names for ",
          rgba.size(), " photos");
  auto say = [&](const std::string& line) {
    if (o.log) o.log(line);
  };
  Reconstruction r;
  auto last = std::chrono::steady_clock::now();
  auto lap = [&](const char* stage) {
    const auto now = std::chrono::steady_clock::now();
    r.stage_ms.emplace_back(stage, std::chrono::duration<double, std::milli>(now - last).count());
    last = now;
  };
  say(format("predicting at %lld x %lld", static_cast<long long>(c.image_w), static_cast<long long>(c.image_h)));
  PredictWorkspace<float> ws;
  ws.cameras = o.cameras;
  ws.auto_budget = o.auto_budget;
  Prediction<float>& p = r.prediction;
  if (given) {
    p = predict_posed<float>(ws, w, rgba, o.given, o.gaussians);
  } else {
    ModelPhotos<float> photos = model_photos<float>(rgba, c);
    ws.silhouettes = std::move(photos.silhouettes);
    lap("preprocess");
    p = predict<float>(ws, w, TensorView<const float, 4>(photos.images.view()), o.gaussians);
  }
  if (o.auto_budget)
    say(format("--budget auto: the decoder ran %lld of the budget's %lld queries (those on the object's outline)",
               static_cast<long long>(p.budget_queries), static_cast<long long>(p.budget)));
  r.stage_ms.emplace_back("geometry (VGGT)", p.geometry_ms);
  r.stage_ms.emplace_back("cameras", p.cameras_ms);
  r.stage_ms.emplace_back("decoder", p.decoder_ms);
  if (o.cameras == CameraSource::turntable)
    say(format("turntable at elevation %.1f deg, turning %s", ws.turntable.elevation_deg,
               ws.turntable.direction > 0 ? "counter-clockwise seen from above" : "clockwise seen from above"));
  if (p.given)
    say(format("the capture's scale %.6g world units per model unit (%s)", p.given->frame.scale,
               p.given->from_views ? "the views' consistency" : "one view: the object at the world origin's distance"));
  last = std::chrono::steady_clock::now();
  // The photos as targets at h x w in the prediction's cameras, made once for refinement and compaction alike (K is
  // neither refined nor moved to the capture's world).
  std::optional<PhotoTargets<float>> targets;
  auto targets_at = [&](std::array<index_t, 2> size) -> const PhotoTargets<float>& {
    if (!targets || targets->h != size[0] || targets->w != size[1])
      targets = given ? photo_targets<float>(rgba, o.given, size[0], size[1])
                      : photo_targets<float>(rgba, c, p.geometry.K.data(), size[0], size[1]);
    return *targets;
  };
  if (o.refine_seconds > 0) {
    // Test-time refinement of the Gaussians and the predicted cameras on the input pictures (camera 0 stays fixed).
    const std::array<index_t, 2> size = refine_size(rgba, c, o.refine_longer);
    say(format("refining for %g s on the input views at %lld x %lld", o.refine_seconds,
               static_cast<long long>(size[1]), static_cast<long long>(size[0])));
    const PhotoTargets<float>& photos = targets_at(size);
    const RefineViews<float> rv{p.views,         photos.h, photos.w, photos.images.data(),
                                photos.K.data(), p.geometry.extrinsics.data(), photos.alpha.data()};
    RefineConfig rc = prediction_refine_config(rv, o.refine_seconds, 0, o.refine_grow);
    rc.validate = o.refine_validate;
    rc.optimize_cameras = !given;  // given cameras are the capture's: kept as they are
    RefineWorkspace<float> rws;
    const RefineResult& rr = r.refine.emplace(refine(p.gaussians, rv, rc, rws));
    if (rr.chosen_steps >= 0)
      say(format("held-out trial of %lld steps on all views but the last: its loss %.5f -> %.5f at step %lld",
                 static_cast<long long>(rr.trial_steps), rr.holdout_initial, rr.holdout_best,
                 static_cast<long long>(rr.chosen_steps)));
    say(format("%lld refinement steps, loss on the inputs %.5f -> %.5f, %lld Gaussians carved away (seen on a photo's "
               "background), %lld grown in the silhouettes, %lld pruned", static_cast<long long>(rr.steps),
               rr.loss_initial, rr.loss_final, static_cast<long long>(rr.carved), static_cast<long long>(rr.grown),
               static_cast<long long>(rr.pruned)));
    lap("refine");
  }
  if (p.given) to_capture_world(p);  // the splat in the capture's world and units
  if (o.compact) {
    // The input views at the photos' resolution in the prediction's frame, with their alpha.
    const std::array<index_t, 2> size = refine_size(rgba, c);
    const PhotoTargets<float>& photos = targets_at(size);
    std::vector<Camera> views;
    for (index_t v = 0; v < p.views; ++v)
      views.push_back(camera_from_arrays(photos.K.data() + 9 * v, p.geometry.extrinsics.data() + 12 * v,
                                         static_cast<int>(size[1]), static_cast<int>(size[0])));
    const CompactReport& cr = r.compact.emplace(compact_splat(p.gaussians, views, photos.alpha.data()));
    say(format("compact: %lld of %lld Gaussians kept (%lld outside the silhouettes, %lld unseen, %lld degenerate)",
               static_cast<long long>(cr.after), static_cast<long long>(cr.before), static_cast<long long>(cr.outside),
               static_cast<long long>(cr.unseen), static_cast<long long>(cr.degenerate)));
    lap("compact");
  }
  if (given) {
    r.cameras = o.given;
    for (std::size_t v = 0; v < o.names.size(); ++v) r.cameras[v].name = o.names[v];
  } else {
    r.cameras = input_cameras(p, o.names);
  }
  return r;
}

// `frames` views orbiting the Gaussians' opacity-weighted centre about the first camera's up axis, at the first
// camera's distance, side by side in one picture [h, frames * w + 2 (frames - 1), 3] on white (each h x w, the first
// camera's predicted K scaled to that size, 2-pixel gaps).
inline Tensor<float, 3> turntable_strip(const Prediction<float>& p, int frames, index_t h, index_t w) {
  require(frames >= 1 && h >= 1 && w >= 1, "turntable: ", frames, " frames of ", w, " x ", h);
  const auto& s = p.gaussians;
  glm::dvec3 centre(0.0);
  double weight = 0;
  for (index_t i = 0; i < s.size(); ++i) {
    const double o = s.opacities(i);
    centre += o * glm::dvec3(s.means(i, 0), s.means(i, 1), s.means(i, 2));
    weight += o;
  }
  require(weight > 0, "turntable: every Gaussian is transparent");
  centre /= weight;
  Camera first = input_cameras(p)[0];
  const glm::dvec3 eye0 = first.centre();
  const glm::dvec3 up = -glm::transpose(first.R)[1];  // rows of R are the camera's axes; OpenCV y points down
  const double sx = static_cast<double>(w) / static_cast<double>(p.w), sy = static_cast<double>(h) / static_cast<double>(p.h);
  first.K[0][0] *= sx, first.K[1][0] *= sx, first.K[2][0] *= sx;  // column-major: fx, skew, cx
  first.K[1][1] *= sy, first.K[2][1] *= sy;
  const index_t gap = 2;
  Tensor<float, 3> strip(Shape<3>{h, frames * w + (frames - 1) * gap, 3}, 1.0f);
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  raster::RenderWorkspace<float> ws;
  raster::RenderOutputs<float> out;
  for (int f = 0; f < frames; ++f) {
    const double angle = 2.0 * 3.14159265358979323846 * f / frames;
    const glm::dmat4 turn = glm::rotate(glm::dmat4(1.0), angle, glm::normalize(up));
    const glm::dvec3 eye = centre + glm::dvec3(turn * glm::dvec4(eye0 - centre, 0.0));
    raster::render_forward(
        s, raster::camera_view<float>(look_at(eye, centre, static_cast<int>(w), static_cast<int>(h), first.K, up)), ro,
        ws, out);
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x)
        for (int c = 0; c < 3; ++c) strip(y, f * (w + gap) + x, c) = std::clamp(out.image(y, x, c), 0.0f, 1.0f);
  }
  return strip;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
