#pragma once
// One training step of the whole FlexSplat model: a batch of scenes, each turned into the model's frame (first input
// camera = identity, unit mean point distance, as VGGT normalises its data), forward through geometry and appearance,
// the stage's losses, backward into one gradient per scene, the per-scene gradients summed in global scene order
// across ranks (optim/distributed.hpp), averaged, clipped, and one AdamW update.
//
// Stages: geometry pre-training (VGGT's supervised camera and depth losses; the appearance side is not run), joint
// training (the FlexSplat objective, plus optionally the supervised geometry terms), both with every parameter
// trained unless the geometry is frozen.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <iterator>
#include <span>
#include <utility>
#include <vector>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/geometry/pose_encoding.hpp"
#include "flexsplat/geometry/unproject.hpp"
#include "flexsplat/loss/geometry.hpp"
#include "flexsplat/loss/match.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/frames.hpp"
#include "flexsplat/model/geometry_stage.hpp"
#include "flexsplat/train/objective.hpp"
#include "flexsplat/model/weights.hpp"
#include "flexsplat/optim/distributed.hpp"
#include "flexsplat/optim/optimizer.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// One scene at the model's resolution, in the model's frame.
template <class T>
struct TrainExample {
  index_t views = 0, targets = 0, h = 0, w = 0;
  std::vector<T> images;         // [V, 3, h, w] inputs in [0, 1], composited over the background
  std::vector<T> inputs_hwc;     // [V, h, w, 3] the same, as render targets
  std::vector<T> masks;          // [V, h, w] object alpha
  std::vector<T> gt_extrinsics;  // [V, 3, 4]
  std::vector<T> gt_K;           // [V, 3, 3] pixel centres at +0.5
  std::vector<T> gt_depth;       // [V, h, w] camera z / scale, 0 for background
  std::vector<T> gt_pose_enc;    // [V, 9] VGGT's encoding of the ground-truth cameras
  std::vector<T> gt_points;      // [V, h, w, 3] surface points in the model's frame (background: the camera centre)
  std::vector<loss::PixelMatch> matches;  // ground-truth correspondences (matches_per_pair), for the match loss
  std::vector<T> target_images;  // [M, h, w, 3]
  std::vector<std::array<T, 9>> target_K;
  std::vector<std::array<T, 12>> target_w2c;
  std::array<T, 3> background{1, 1, 1};
};

// Ground-truth correspondences a training example keeps: about `samples` per scene (the run config's match_samples)
// spread over its ordered view pairs, at least 8 per pair (64 per pair for 4 views at the default 768; the match
// loss's cost grows with their number).
inline constexpr index_t match_samples = 768;
inline index_t matches_per_pair(index_t views, index_t samples = match_samples) {
  return views < 2 ? 0 : std::max<index_t>(8, samples / (views * (views - 1)));
}

// A data::SceneSample (inputs and targets of one scene, square views of the model's size) in the model's frame.
template <class T>
TrainExample<T> make_train_example(const data::SceneSample& s, const FlexSplatConfig& c,
                                   index_t samples = match_samples) {
  const index_t V = s.inputs.rgb.shape(0), M = s.targets.rgb.empty() ? 0 : s.targets.rgb.shape(0);
  require(V >= 1, "training example '", s.name, "': no input views");
  const index_t h = s.inputs.rgb.shape(1), w = s.inputs.rgb.shape(2);
  require(h == c.image_h && w == c.image_w, "training example '", s.name, "': views are ", w, " x ", h,
          ", the model takes ", c.image_w, " x ", c.image_h, " (set the batch crop to the model size)");
  require(V <= c.appearance.decoder.max_views, "training example '", s.name, "': ", V,
          " input views, the decoder has parameter slots for ", c.appearance.decoder.max_views);
  TrainExample<T> e;
  e.views = V, e.targets = M, e.h = h, e.w = w;
  const index_t px = h * w;
  std::vector<double> K(static_cast<std::size_t>(9 * V)), E(static_cast<std::size_t>(12 * V)),
      depth(static_cast<std::size_t>(V * px));
  for (index_t v = 0; v < V; ++v) camera_arrays(s.inputs.cameras[static_cast<std::size_t>(v)], &K[9 * v], &E[12 * v]);
  for (index_t i = 0; i < V * px; ++i) depth[static_cast<std::size_t>(i)] = s.inputs.depth.data()[i];
  const FirstCameraFrame frame = first_camera_frame(E.data(), K.data(), depth.data(), V, h, w);

  e.images.resize(static_cast<std::size_t>(V * 3 * px));
  e.inputs_hwc.assign(s.inputs.rgb.data(), s.inputs.rgb.data() + V * px * 3);
  e.masks.assign(s.inputs.alpha.data(), s.inputs.alpha.data() + V * px);
  for (index_t v = 0; v < V; ++v)
    for (index_t p = 0; p < px; ++p)
      for (int ch = 0; ch < 3; ++ch) e.images[static_cast<std::size_t>((v * 3 + ch) * px + p)] = s.inputs.rgb.data()[(v * px + p) * 3 + ch];
  e.gt_K.assign(K.begin(), K.end());
  for (index_t v = 0; v < V; ++v) frame.camera(&E[12 * v]);
  e.gt_extrinsics.assign(E.begin(), E.end());
  e.gt_depth.resize(depth.size());
  for (std::size_t i = 0; i < depth.size(); ++i) e.gt_depth[i] = static_cast<T>(depth[i] / frame.scale);
  // VGGT encodes intrinsics with pixel u at the integer coordinate u.
  std::vector<T> K_vggt(e.gt_K.size());
  intrinsics_to_vggt(K_vggt.data(), e.gt_K.data(), V);
  e.gt_pose_enc.resize(static_cast<std::size_t>(9 * V));
  geometry::extri_intri_to_pose_encoding(e.gt_pose_enc.data(), e.gt_extrinsics.data(), K_vggt.data(), V, h, w);
  e.gt_points.resize(static_cast<std::size_t>(V * px * 3));
  geometry::unproject_depth_forward<T>(e.gt_points.data(), e.gt_depth.data(), e.gt_extrinsics.data(), K_vggt.data(), V,
                                       h, w);
  e.matches = loss::ground_truth_matches(e.gt_depth.data(), e.gt_K.data(), e.gt_extrinsics.data(), V, h, w,
                                         matches_per_pair(V, samples));

  e.target_images.assign(s.targets.rgb.data(), s.targets.rgb.data() + M * px * 3);
  for (index_t m = 0; m < M; ++m) {
    double k[9], w2c[12];
    camera_arrays(s.targets.cameras[static_cast<std::size_t>(m)], k, w2c);
    frame.camera(w2c);
    std::array<T, 9> kk;
    std::array<T, 12> ee;
    for (int i = 0; i < 9; ++i) kk[static_cast<std::size_t>(i)] = static_cast<T>(k[i]);
    for (int i = 0; i < 12; ++i) ee[static_cast<std::size_t>(i)] = static_cast<T>(w2c[i]);
    e.target_K.push_back(kk);
    e.target_w2c.push_back(ee);
  }
  for (int ch = 0; ch < 3; ++ch) e.background[static_cast<std::size_t>(ch)] = static_cast<T>(s.background[ch]);
  return e;
}

struct StepConfig {
  bool appearance = true;            // run the FlexSplat objective (off: geometry pre-training only)
  bool train_geometry = true;        // off: geometry frozen (no geometry backward)
  double camera_weight = 0.0;        // VGGT's supervised camera loss on the pose encodings
  // The relative pose loss over all ordered view pairs and the camera loss's FoV term (reported in `camera`).
  double relative_camera_weight = 0.0;
  double depth_weight = 0.0;         // VGGT's supervised depth loss
  double depth_shape_weight = 0.0;   // the per-view scale-blind depth shape loss (loss::depth_shape_loss_forward)
  double point_weight = 0.0;         // VGGT's point-map loss (needs the point head)
  double match_weight = 0.0;         // the match head's correspondence and object-mask losses (needs the match head)
  ObjectiveWeights objective;
  loss::CameraLossConfig camera_loss;
  loss::DepthLossConfig depth_loss;
  loss::PointLossConfig point_loss;
  loss::MatchLossConfig match_loss;
  bool render_inputs = true;         // input views (predicted cameras) are rendered targets too
  // The decoder and the input views' renders see the ground-truth cameras in place of the predicted ones (teacher
  // forcing): the appearance side learns to use every view while the cameras are still poor, and the render loss then
  // sends no gradient to the cameras (only the camera, pose and match losses train them).
  bool decoder_true_cameras = false;
  index_t gaussians = 0;             // 0: the configuration's budget for the view count
  double max_grad_norm = 1.0;        // <= 0: no clipping
  train::AdamWConfig adamw;
};

struct StepReport {
  double loss = 0, camera = 0, depth = 0, depth_shape = 0, points = 0, match = 0, rgb_head = 0, render = 0, render_depth = 0, lpips = 0, psnr = 0;
  double grad_norm = 0;
  index_t scenes = 0;
};

// The per-scene parts a step averages over the global batch (summed across ranks in this order).
inline constexpr double StepReport::*step_report_means[] = {
    &StepReport::loss,   &StepReport::camera, &StepReport::depth,        &StepReport::rgb_head,
    &StepReport::render, &StepReport::render_depth, &StepReport::lpips, &StepReport::psnr,
    &StepReport::points, &StepReport::match,  &StepReport::depth_shape};

template <class T>
struct SceneWorkspace {
  GeometryStage<T> geometry;
  GeometryResult<T> d_geometry;
  std::vector<T> d_pose_enc, stage_extrinsics, d_stage_extrinsics;
  ObjectiveWorkspace<T> objective;
  std::vector<RenderView<T>> views;
  std::vector<std::uint8_t> depth_mask;
  std::vector<T> d_points, d_points_conf, d_descriptors, d_foreground;
  GeometryResult<T> true_camera_geometry;  // StepConfig::decoder_true_cameras: the prediction with the true cameras
};

namespace detail {
// The loss groups of one scene (scene_pass): each adds its weighted parts into r and, with backward, their gradients
// into ws's geometry-output gradients.

// VGGT's supervised camera loss on every camera-head iteration's encoding, and the relative pose loss over all ordered
// view pairs with the camera loss's FoV term.
template <class T>
void camera_losses(StepReport& r, SceneWorkspace<T>& ws, const FlexSplatConfig& c, const TrainExample<T>& e,
                   const StepConfig& sc, bool backward) {
  const index_t V = e.views, iters = ws.geometry.iterations;
  // Every camera-head iteration's encoding and its gradient slot, for the camera losses.
  std::vector<const T*> enc;
  std::vector<T*> d_enc;
  for (index_t i = 0; i < iters; ++i) {
    enc.push_back(ws.geometry.pose_enc.data() + i * V * 9);
    d_enc.push_back(backward ? ws.d_pose_enc.data() + i * V * 9 : nullptr);
  }
  if (sc.camera_weight > 0) {
    r.camera = sc.camera_weight * loss::camera_loss_forward(enc, e.gt_pose_enc.data(), nullptr, V, sc.camera_loss).total;
    if (backward)
      loss::camera_loss_backward(d_enc, sc.camera_weight, enc, e.gt_pose_enc.data(), nullptr, V, sc.camera_loss);
  }
  if (sc.relative_camera_weight > 0) {
    // The field of view is each frame's own, so the camera loss's FoV term supervises it in any world frame.
    loss::CameraLossConfig fov = sc.camera_loss;
    fov.weight_translation = fov.weight_rotation = 0;
    const T* gt = e.gt_pose_enc.data();
    std::vector<const T*> extr;
    ws.stage_extrinsics.resize(static_cast<std::size_t>(iters * V * 12));
    for (index_t i = 0; i < iters; ++i) {
      // Every iteration's encoding decoded to extrinsics; the pair loss's gradient goes back through the decoding.
      T* E = ws.stage_extrinsics.data() + i * V * 12;
      geometry::pose_encoding_to_extri_intri<T>(E, nullptr, enc[static_cast<std::size_t>(i)], V, e.h, e.w,
                                                c.geometry.pose_decode);
      extr.push_back(E);
    }
    r.camera += sc.relative_camera_weight * (loss::camera_loss_forward(enc, gt, nullptr, V, fov).total +
                                             loss::relative_pose_loss_forward(extr, e.gt_extrinsics.data(), V,
                                                                              sc.camera_loss).total);
    if (backward) {
      ws.d_stage_extrinsics.assign(ws.stage_extrinsics.size(), T(0));
      std::vector<T*> d_extr;
      for (index_t i = 0; i < iters; ++i) d_extr.push_back(ws.d_stage_extrinsics.data() + i * V * 12);
      loss::camera_loss_backward(d_enc, sc.relative_camera_weight, enc, gt, nullptr, V, fov);
      loss::relative_pose_loss_backward(d_extr, sc.relative_camera_weight, extr, e.gt_extrinsics.data(), V,
                                        sc.camera_loss);
      for (index_t i = 0; i < iters; ++i) {
        const auto k = static_cast<std::size_t>(i);
        geometry::pose_encoding_to_extri_intri_backward<T>(d_enc[k], d_extr[k], nullptr, enc[k], V, e.h, e.w,
                                                           c.geometry.pose_decode);
      }
    }
  }
}

// VGGT's supervised depth loss, the scale-blind depth shape loss and the point-map loss, on the pixels with
// ground-truth depth.
template <class T>
void depth_losses(StepReport& r, SceneWorkspace<T>& ws, const FlexSplatConfig& c, const TrainExample<T>& e,
                  const StepConfig& sc, bool backward) {
  const index_t V = e.views, px = e.h * e.w;
  const GeometryResult<T>& g = ws.geometry.result;
  if (sc.depth_weight > 0 || sc.depth_shape_weight > 0 || sc.point_weight > 0) {
    ws.depth_mask.resize(static_cast<std::size_t>(V * px));
    for (index_t i = 0; i < V * px; ++i) ws.depth_mask[static_cast<std::size_t>(i)] = e.gt_depth[static_cast<std::size_t>(i)] > T(0);
  }
  if (sc.depth_weight > 0) {
    r.depth = sc.depth_weight * loss::depth_loss_forward(g.depth.data(), g.confidence.data(), e.gt_depth.data(),
                                                        ws.depth_mask.data(), V, e.h, e.w, sc.depth_loss).total;
    if (backward)
      loss::depth_loss_backward(ws.d_geometry.depth.data(), ws.d_geometry.confidence.data(), sc.depth_weight,
                                g.depth.data(), g.confidence.data(), e.gt_depth.data(), ws.depth_mask.data(), V, e.h,
                                e.w, sc.depth_loss);
  }
  if (sc.depth_shape_weight > 0) {
    const index_t least = sc.depth_loss.min_valid_pixels;
    r.depth_shape = sc.depth_shape_weight * loss::depth_shape_loss_forward(g.depth.data(), e.gt_depth.data(),
                                                                           ws.depth_mask.data(), V, e.h, e.w, least);
    if (backward)
      loss::depth_shape_loss_backward(ws.d_geometry.depth.data(), sc.depth_shape_weight, g.depth.data(),
                                      e.gt_depth.data(), ws.depth_mask.data(), V, e.h, e.w, least);
  }
  if (sc.point_weight > 0) {
    require(c.geometry.point_head, "training: point_weight ", sc.point_weight, " needs a model with the point head");
    const auto& o = ws.geometry.outputs;
    r.points = sc.point_weight * loss::point_loss_forward(o.points.data(), o.points_conf.data(), e.gt_points.data(),
                                                          ws.depth_mask.data(), V * px, sc.point_loss).total;
    if (backward) {
      ws.d_points.assign(static_cast<std::size_t>(V * px * 3), T(0));
      ws.d_points_conf.assign(static_cast<std::size_t>(V * px), T(0));
      loss::point_loss_backward(ws.d_points.data(), ws.d_points_conf.data(), sc.point_weight, o.points.data(),
                                o.points_conf.data(), e.gt_points.data(), ws.depth_mask.data(), V * px, sc.point_loss);
    }
  }
}

// The match head's correspondence and object-mask losses.
template <class T>
void match_losses(StepReport& r, SceneWorkspace<T>& ws, const FlexSplatConfig& c, const TrainExample<T>& e,
                  const StepConfig& sc, bool backward) {
  if (!(sc.match_weight > 0)) return;
  const index_t V = e.views, px = e.h * e.w, D = c.geometry.match_dim;
  require(D > 0, "training: match_weight ", sc.match_weight, " needs a model with the match head (match_dim > 0)");
  const auto& o = ws.geometry.outputs;
  const std::span<const loss::PixelMatch> m(e.matches);
  r.match = sc.match_weight * loss::match_loss_forward(o.descriptors.data(), o.foreground.data(), e.masks.data(), m, V,
                                                       px, D, sc.match_loss).total;
  if (backward) {
    ws.d_descriptors.assign(static_cast<std::size_t>(V * px * D), T(0));
    ws.d_foreground.assign(static_cast<std::size_t>(V * px), T(0));
    loss::match_loss_backward(ws.d_descriptors.data(), ws.d_foreground.data(), sc.match_weight, o.descriptors.data(),
                              o.foreground.data(), e.masks.data(), m, V, px, D, sc.match_loss);
  }
}

// The FlexSplat objective (appearance_objective): the decoder's Gaussians rendered into the input views (predicted
// cameras) and the targets; with decoder_true_cameras the decoder and the input views' renders see the ground-truth
// cameras. d_app: the appearance segment's gradients (null: forward only).
template <class T>
void appearance_losses(StepReport& r, SceneWorkspace<T>& ws, const FlexSplatWeights<T>& w, T* d_app,
                       const TrainExample<T>& e, const StepConfig& sc, const loss::LpipsWeights<T>* lpips,
                       PhaseTimes* times) {
  const FlexSplatConfig& c = w.config();
  const index_t V = e.views, px = e.h * e.w;
  const bool backward = d_app != nullptr;
  const GeometryResult<T>* seen = &ws.geometry.result;
  if (sc.decoder_true_cameras) {
    ws.true_camera_geometry = ws.geometry.result;
    std::copy(e.gt_extrinsics.begin(), e.gt_extrinsics.end(), ws.true_camera_geometry.extrinsics.begin());
    std::copy(e.gt_K.begin(), e.gt_K.end(), ws.true_camera_geometry.K.begin());
    seen = &ws.true_camera_geometry;
  }
  ws.views.clear();
  if (sc.render_inputs)
    for (index_t v = 0; v < V; ++v) {
      RenderView<T> rv;
      rv.width = static_cast<int>(e.w), rv.height = static_cast<int>(e.h), rv.input_view = v;
      rv.target = e.inputs_hwc.data() + v * px * 3;
      rv.mask = e.masks.data() + v * px;
      ws.views.push_back(rv);
    }
  for (index_t m = 0; m < e.targets; ++m) {
    RenderView<T> rv;
    rv.K = e.target_K[static_cast<std::size_t>(m)];
    rv.world_to_camera = e.target_w2c[static_cast<std::size_t>(m)];
    rv.width = static_cast<int>(e.w), rv.height = static_cast<int>(e.h);
    rv.target = e.target_images.data() + m * px * 3;
    ws.views.push_back(rv);
  }
  raster::RenderOptions ro;
  ro.background = {static_cast<double>(e.background[0]), static_cast<double>(e.background[1]),
                   static_cast<double>(e.background[2])};
  const index_t n = sc.gaussians > 0 ? sc.gaussians : c.gaussians_for(V);
  const LossParts p = appearance_objective<T>(ws.objective, w.appearance(), d_app, c.appearance, n, e.images.data(),
                                              *seen, backward && sc.train_geometry ? &ws.d_geometry : nullptr,
                                              ws.views, sc.objective, ro, lpips, times);
  if (sc.decoder_true_cameras && backward && sc.train_geometry)  // no other loss reaches these two fields
    for (auto* f : {&ws.d_geometry.extrinsics, &ws.d_geometry.K}) std::fill(f->begin(), f->end(), T(0));
  r.rgb_head = p.rgb_head, r.render = p.render, r.render_depth = p.depth, r.lpips = p.lpips, r.psnr = p.psnr_last;
}

// One scene's forward and loss parts; grads non-null: then its backward, added into grads. scene_loss and
// scene_gradient are its two modes, so both report the one computation of the loss.
template <class T>
StepReport scene_pass(SceneWorkspace<T>& ws, const FlexSplatWeights<T>& w, T* grads, const TrainExample<T>& e,
                      const StepConfig& sc, const loss::LpipsWeights<T>* lpips, PhaseTimes* times) {
  const FlexSplatConfig& c = w.config();
  const index_t V = e.views;
  const bool backward = grads != nullptr;
  StepReport r;
  PhaseClock clock(times);
  geometry_stage_forward(ws.geometry, w, e.images.data(), V, sc.train_geometry);
  clock.lap(&PhaseTimes::geometry_forward);
  if (backward) {
    ws.d_geometry.zero_like(ws.geometry.result);
    ws.d_pose_enc.assign(static_cast<std::size_t>(ws.geometry.iterations * V * 9), T(0));
  }
  camera_losses(r, ws, c, e, sc, backward);
  depth_losses(r, ws, c, e, sc, backward);
  match_losses(r, ws, c, e, sc, backward);
  if (sc.appearance) {
    T* d_app = backward ? grads + w.store().segment(appearance_segment).offset : nullptr;
    appearance_losses(r, ws, w, d_app, e, sc, lpips, times);
    clock = PhaseClock(times);
  }
  clock.lap(&PhaseTimes::losses);
  if (backward && sc.train_geometry) {
    const bool points = sc.point_weight > 0, match = sc.match_weight > 0;
    geometry_stage_backward(ws.geometry, w, grads, ws.d_geometry, ws.d_pose_enc.data(),
                            points ? ws.d_points.data() : nullptr, points ? ws.d_points_conf.data() : nullptr,
                            match ? ws.d_descriptors.data() : nullptr, match ? ws.d_foreground.data() : nullptr);
    clock.lap(&PhaseTimes::geometry_backward);
  }
  r.loss = r.camera + r.depth + r.depth_shape + r.points + r.match + r.rgb_head + r.render + r.render_depth + r.lpips;
  r.scenes = 1;
  return r;
}
}  // namespace detail

// One scene's loss parts (unweighted sums as they enter the total), forward only: what scene_gradient reports, to the
// bit, at about a third of its cost.
template <class T>
StepReport scene_loss(SceneWorkspace<T>& ws, const FlexSplatWeights<T>& w, const TrainExample<T>& e,
                      const StepConfig& sc, const loss::LpipsWeights<T>* lpips = nullptr, PhaseTimes* times = nullptr) {
  return detail::scene_pass<T>(ws, w, nullptr, e, sc, lpips, times);
}

// Adds one scene's loss gradient into `grads` (the store's layout) and returns its loss parts (as scene_loss).
template <class T>
StepReport scene_gradient(SceneWorkspace<T>& ws, const FlexSplatWeights<T>& w, T* grads, const TrainExample<T>& e,
                          const StepConfig& sc, const loss::LpipsWeights<T>* lpips = nullptr,
                          PhaseTimes* times = nullptr) {
  require(grads, "scene_gradient: null gradient block (scene_loss is the forward-only pass)");
  return detail::scene_pass<T>(ws, w, grads, e, sc, lpips, times);
}

// Whether a step's `scenes` local scenes run side by side, one per thread (train_step, make_train_scenes): with several
// threads and at least as many scenes; at this model's size one scene's operations split poorly over threads.
inline bool scenes_side_by_side(index_t scenes, ThreadPool& pool = global_pool()) {
  return pool.size() > 1 && scenes >= pool.size() && ThreadPool::current_worker() < 0;
}

// task(i, worker) for i in [0, n + extra): side by side, one task per thread, when scenes_side_by_side(n), else in
// order on this thread as worker 0. The `extra` tasks come after the n scenes, so the first thread to run out of scenes
// takes them. Unlike parallel_tasks, fewer scenes than threads run in order (each then splits its work).
template <class Task>
void run_scenes(index_t n, Task&& task, index_t extra = 0) {
  if (scenes_side_by_side(n)) parallel_tasks(n + extra, task);
  else
    for (index_t i = 0; i < n + extra; ++i) task(i, 0);
}

// Work that does not read the step's parameters (the trainer's next scenes), run(i) for i < count: with scenes side by
// side the first thread out of scenes takes it (each task as on one thread), filling its wait for the others' last
// scene; otherwise it runs after the scenes.
struct SideTasks {
  index_t count = 0;
  std::function<void(index_t)> run;
};

template <class T>
struct StepWorkspace {
  std::vector<SceneWorkspace<T>> scenes;  // one per worker that runs scenes side by side (train_step)
  bool recompute = false;                 // the geometry's transformer blocks rerun in backward (GeometryStage)
  std::vector<std::vector<T, AlignedAllocator<T>>> scene_grads;  // one gradient per local scene
};

// One update from a global batch: `local` are this rank's scenes of `plan`, in global order (plan.scenes_of). lr from
// the schedule; step counts updates done before this one. Returns the global batch's mean losses. Scenes side by side
// (scenes_side_by_side) each run as on one thread: the step is then bit-identical to one thread and to any number of
// ranks and plans, and `times` sums the threads' phase times (the side tasks' time is not in them).
template <class T>
StepReport train_step(StepWorkspace<T>& ws, FlexSplatWeights<T>& w, std::span<const TrainExample<T>> local,
                      const train::ScenePlan& plan, const StepConfig& sc, double lr, std::uint64_t step,
                      train::Communicator& comm, const loss::LpipsWeights<T>* lpips = nullptr,
                      PhaseTimes* times = nullptr, const SideTasks& side = {}) {
  require(!local.empty(), "train_step: rank ", comm.rank(), " has no scenes");
  auto& store = w.store();
  const index_t n = store.size();
  // One scene on one rank: its gradient is the sum, so it goes straight into the store (no second gradient-sized
  // buffer; the same values as the copy ordered_sum would make).
  const bool direct = comm.size() == 1 && local.size() == 1;
  const index_t workers = global_pool().size(), scenes = static_cast<index_t>(local.size());
  const bool side_by_side = scenes_side_by_side(scenes);
  ws.scenes.resize(static_cast<std::size_t>(std::max<index_t>(side_by_side ? workers : 1,
                                                              static_cast<index_t>(ws.scenes.size()))));
  for (SceneWorkspace<T>& s : ws.scenes) s.geometry.recompute = ws.recompute;
  ws.scene_grads.resize(direct ? 0 : local.size());
  if (direct) store.zero_grads();
  constexpr std::size_t means = std::size(step_report_means), fields = means + 1;  // + the scene count
  std::vector<double> values(local.size() * fields);
  std::vector<PhaseTimes> worker_times(times && side_by_side ? static_cast<std::size_t>(workers) : 0);
  auto run = [&](index_t s, int worker) {
    T* g = direct ? store.grads() : nullptr;
    if (!direct) {
      ws.scene_grads[static_cast<std::size_t>(s)].assign(static_cast<std::size_t>(n), T(0));
      g = ws.scene_grads[static_cast<std::size_t>(s)].data();
    }
    PhaseTimes* t = side_by_side && times ? &worker_times[static_cast<std::size_t>(worker)] : times;
    const StepReport r = scene_gradient(ws.scenes[static_cast<std::size_t>(worker)], w, g,
                                        local[static_cast<std::size_t>(s)], sc, lpips, t);
    double* v = values.data() + fields * static_cast<std::size_t>(s);
    for (std::size_t i = 0; i < means; ++i) v[i] = r.*step_report_means[i];
    v[means] = 1.0;
  };
  // Largest first (views, then rendered targets), so that threads side by side finish close together; each scene
  // writes only its own gradient and values, so the order does not change the result.
  std::vector<index_t> order(static_cast<std::size_t>(scenes));
  for (index_t s = 0; s < scenes; ++s) order[static_cast<std::size_t>(s)] = s;
  auto cost = [&](index_t s) {
    const TrainExample<T>& e = local[static_cast<std::size_t>(s)];
    return std::pair<index_t, index_t>{e.views, e.targets};
  };
  std::stable_sort(order.begin(), order.end(), [&](index_t a, index_t b) { return cost(a) > cost(b); });
  const index_t side_count = side.run ? side.count : 0;
  run_scenes(
      scenes,
      [&](index_t i, int worker) {
        if (i < scenes) run(order[static_cast<std::size_t>(i)], worker);
        else side.run(i - scenes);
      },
      side_count);
  for (const PhaseTimes& t : worker_times) *times += t;
  PhaseClock clock(times);
  std::vector<const T*> ptrs;
  for (auto& g : ws.scene_grads) ptrs.push_back(g.data());
  if (!direct) train::ordered_sum<T>(comm, store.grads(), n, plan, ptrs);
  std::vector<const double*> vptrs;
  for (std::size_t s = 0; s < local.size(); ++s) vptrs.push_back(values.data() + fields * s);
  double totals[fields];
  train::ordered_sum<double>(comm, totals, fields, plan, vptrs);
  const index_t global_batch = plan.global();
  require(static_cast<index_t>(totals[means]) == global_batch, "train_step: the ranks hold ", totals[means],
          " scenes, the global batch is ", global_batch);
  const T inv = static_cast<T>(1.0 / static_cast<double>(global_batch));
  T* grads = store.grads();
  for (index_t i = 0; i < n; ++i) grads[i] *= inv;
  StepReport r;
  const double ib = 1.0 / static_cast<double>(global_batch);
  for (std::size_t i = 0; i < means; ++i) r.*step_report_means[i] = totals[i] * ib;
  r.scenes = global_batch;
  r.grad_norm = sc.max_grad_norm > 0 ? train::clip_grad_norm(store, sc.max_grad_norm) : train::grad_norm(store);
  train::adamw_step(store, sc.adamw, lr, step + 1);
  clock.lap(&PhaseTimes::update);
  return r;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
