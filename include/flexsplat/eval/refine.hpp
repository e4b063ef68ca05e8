#pragma once
// Test-time refinement: a Gaussian set (and optionally the cameras of its views) optimised through the rasterizer's
// adjoints on those views, for a wall-time and/or step budget. Loss: 3DGS's (1 - w) L1 + w (1 - SSIM), the mean over
// the views, every view rendered at every step. Parameters live in a train::ParamStore updated by train::adamw_step
// (no weight decay): means, quaternions, log scales, opacity logits, SH DC and higher bands (3DGS's learning rates,
// lengths scaled by the scene extent, the position rate decaying 100x over the budget). A camera moves by a rigid
// increment [exp(omega) | tau] left-multiplied onto its world-to-camera and folded in after every step (the gradient
// is taken at omega = tau = 0); camera 0 stays fixed by default, since it is the model's frame. With prune_every > 0,
// Gaussians whose opacity falls below refine_prune_opacity are removed every prune_every steps.
// With the views' alpha, the Gaussians seen on a view's background are carved away first, and with grow > 0 (and some
// view showing background) that many are added uniformly in the silhouettes' visual hull (random_gaussians_in_views):
// the detail a coarse prediction lacks needs Gaussians where it has none. With validate and >= 2
// views the step count is chosen on a view the fit does not see: a trial fits views 0..V-2 for (V-1)/(2V-1) of the
// budget, scoring the held-out last view every validate_every steps; the result is a fit of all views from the same
// start for the trial's best step count (0: the input set and cameras unchanged). Off by default: on 4 views it kept
// far fewer steps than help the novel views (docs/evaluation.md). With a step budget only, the result is
// deterministic for a fixed thread count. Also here: random_gaussians_in_views, the start of a per-scene fit from
// posed views (docs/app.md). Usage:
//   model::RefineConfig rc;  rc.seconds = 5;                       // or rc.steps = 200
//   model::RefineViews<float> v{V, h, w, images_hwc, K, w2c};       // w2c is updated when cameras are optimised
//   model::RefineWorkspace<float> ws;
//   model::RefineResult r = model::refine(set, v, rc, ws);          // set is optimised (and pruned) in place
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/image/layout.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/loss/ssim.hpp"
#include "flexsplat/nn/activations.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/raster/render.hpp"
#include "flexsplat/optim/optimizer.hpp"
#include "flexsplat/optim/params.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

inline constexpr double refine_ssim_weight = 0.2;        // 3DGS's lambda_DSSIM
inline constexpr double refine_prune_opacity = 0.005;    // 3DGS's pruning threshold
inline constexpr double refine_opacity_floor = 1e-4;     // opacities are clamped to [floor, 1 - floor] before the logit
inline constexpr double refine_position_decay = 0.01;    // final / initial position learning rate (3DGS)
inline constexpr double refine_init_opacity = 0.1;       // 3DGS's initial opacity
inline constexpr double refine_mask_threshold = 0.5;     // a view's pixel is foreground at alpha >= this
inline constexpr double refine_carve_margin = 0.01;      // carve: silhouettes widened by this x the longer image side
// Learning rates x this when refining a prediction that does not grow (photos without background): the start is
// already close (docs/evaluation.md: 0.3 gained most on the held-out views after 5 s at 256 x 256 without growth).
inline constexpr double refine_prediction_lr_scale = 0.3;
// Gaussians a prediction grows by in the visual hull (docs/evaluation.md: 4096 measured best after 30 s at 256 x 256).
inline constexpr index_t refine_grow_gaussians = 4096;

struct RefineConfig {
  double seconds = 0;         // wall-time budget; 0: none
  std::int64_t steps = 0;     // step budget; 0: none. At least one budget; at least one step always runs
  bool optimize_cameras = true;
  bool fix_first_camera = true;  // camera 0 defines the frame (the model's gauge)
  double ssim_weight = refine_ssim_weight;
  // AdamW learning rates per tensor (3DGS's, the position and translation rates times the scene extent).
  double lr_means = 1.6e-3, lr_quats = 1e-3, lr_scales = 5e-3, lr_opacity = 5e-2, lr_sh = 2.5e-3;
  double lr_sh_rest_ratio = 1.0 / 20;  // higher SH bands learn at lr_sh x this
  double lr_rotation = 1e-3;           // radians per step (Adam's step size)
  double lr_translation = 1e-3;        // x the scene extent
  double lr_scale = 1;                 // every learning rate x this (refine_prediction_lr_scale for a prediction)
  int prune_every = 0;                 // > 0: prune every this many steps (off: no measurable gain, docs/app.md)
  double prune_opacity = refine_prune_opacity;
  double extent = 0;                   // 0: mean distance from the camera centres to the opacity-weighted centre
  std::array<double, 3> background{1, 1, 1};
  bool carve = true;                   // with the views' alpha: carve_to_silhouettes first (checked like a step)
  index_t grow = 0;                    // with the views' alpha: Gaussians added in the visual hull after carving
  std::uint64_t seed = 0;              // the grown Gaussians' draws
  bool validate = false;               // >= 2 views: choose the step count on the held-out last view (see above)
  int validate_every = 10;             // steps between the held-out view's scores in the trial
};

template <class T>
struct RefineViews {
  index_t views = 0, h = 0, w = 0;
  const T* images = nullptr;        // [V, h, w, 3] targets in [0, 1] (composited on the background)
  const T* K = nullptr;             // [V, 3, 3] row-major, pixel centres at +0.5
  T* world_to_camera = nullptr;     // [V, 3, 4] row-major; updated in place when cameras are optimised
  const T* alpha = nullptr;         // [V, h, w] the targets' alpha, optional (carve)
};

struct RefineResult {
  std::int64_t steps = 0;
  double seconds = 0;
  double loss_initial = 0;  // the objective of the input set on every view
  double loss_final = 0;    // the objective after the last update (one more forward pass)
  double extent = 0;        // the scene extent used
  index_t pruned = 0;       // Gaussians removed
  // The held-out trial (validate with >= 2 views): its steps, the step count it chose (-1: no trial; 0: the input
  // was kept) and the held-out view's loss at the start and at the chosen step.
  std::int64_t trial_steps = 0, chosen_steps = -1;
  index_t carved = 0;       // Gaussians removed by carve_to_silhouettes
  index_t grown = 0;        // Gaussians added in the visual hull
  double holdout_initial = std::numeric_limits<double>::quiet_NaN();
  double holdout_best = std::numeric_limits<double>::quiet_NaN();
};

template <class T>
struct RefineWorkspace {
  train::ParamStore<T> store;
  GaussianSet<T> set;              // the renderable set from the store (exp scales, sigmoid opacities)
  GaussianSetGrad<T> grad;
  raster::RenderWorkspace<T> render;
  raster::RenderOutputs<T> out;
  Tensor<T, 3> d_image;
  loss::SsimWorkspace ssim;
  std::vector<double> w2c;         // [V, 3, 4] the cameras in double (increments are folded in here)
  std::vector<index_t> origin;     // row of the caller's set each stored Gaussian came from
};

// Model input [V, 3, h, w] -> refinement targets [V, h, w, 3].
template <class T>
std::vector<T> views_hwc(const T* chw, index_t views, index_t h, index_t w) {
  std::vector<T> out(static_cast<std::size_t>(views * h * w * 3));
  for (index_t v = 0; v < views; ++v) image::chw_to_hwc(out.data() + v * h * w * 3, chw + v * 3 * h * w, h, w);
  return out;
}

namespace refine_detail {

// Rodrigues: the rotation by angle |omega| about omega / |omega|.
inline Eigen::Matrix3d exp_so3(const Eigen::Vector3d& omega) {
  const double angle = omega.norm();
  if (angle < 1e-12) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
}

template <class T>
void validate(const GaussianSet<T>& set, const RefineViews<T>& v, const RefineConfig& c) {
  require(std::isfinite(c.seconds) && c.seconds >= 0 && c.steps >= 0 && (c.seconds > 0 || c.steps > 0),
          "refine: budget of ", c.seconds, " s and ", c.steps, " steps; give seconds > 0 and/or steps > 0");
  require(c.ssim_weight >= 0 && c.ssim_weight <= 1, "refine: ssim_weight ", c.ssim_weight, " outside [0, 1]");
  for (double lr : {c.lr_means, c.lr_quats, c.lr_scales, c.lr_opacity, c.lr_sh, c.lr_sh_rest_ratio, c.lr_rotation,
                    c.lr_translation, c.lr_scale})
    require(std::isfinite(lr) && lr >= 0, "refine: learning rate ", lr, " must be finite and >= 0");
  require(c.prune_every >= 0 && c.prune_opacity >= 0 && c.prune_opacity < 1, "refine: prune_every ", c.prune_every,
          " must be >= 0 and prune_opacity ", c.prune_opacity, " in [0, 1)");
  require(std::isfinite(c.extent) && c.extent >= 0, "refine: extent ", c.extent, " must be finite and >= 0");
  require(c.validate_every >= 1, "refine: validate_every ", c.validate_every, " must be >= 1");
  require(c.grow >= 0, "refine: grow ", c.grow, " must be >= 0");
  require(v.views >= 1 && v.h >= 1 && v.w >= 1, "refine: ", v.views, " views of ", v.w, " x ", v.h,
          "; need at least one view of positive size");
  require(v.images && v.K && v.world_to_camera, "refine: null images, K or world_to_camera");
  check_gaussian_shapes(set, "refine");
  require(set.size() >= 1, "refine: the Gaussian set is empty");
  const index_t n = set.size();
  for (index_t i = 0; i < n * 3; ++i) {
    const double s = static_cast<double>(set.scales.data()[i]);
    require(std::isfinite(s) && s > 0, "refine: Gaussian ", i / 3, " has scale ", s, " (must be finite and > 0)");
  }
  for (index_t i = 0; i < n; ++i) {
    const double o = static_cast<double>(set.opacities(i));
    require(std::isfinite(o) && o >= 0 && o <= 1, "refine: Gaussian ", i, " has opacity ", o, " outside [0, 1]");
  }
  for (const auto* t : {&set.means, &set.quats})
    for (index_t i = 0; i < t->size(); ++i)
      require(std::isfinite(static_cast<double>(t->data()[i])), "refine: a Gaussian mean or quaternion is not finite (",
              static_cast<double>(t->data()[i]), " at flat index ", i, ")");
  for (index_t i = 0; i < set.sh.size(); ++i)
    require(std::isfinite(static_cast<double>(set.sh.data()[i])), "refine: SH coefficient ", i, " is not finite");
  const index_t values = v.views * v.h * v.w * 3;
  for (index_t i = 0; i < values; ++i) {
    const double x = static_cast<double>(v.images[i]);
    require(x >= 0 && x <= 1, "refine: image value ", x, " at flat index ", i, " of [", v.views, ", ", v.h, ", ", v.w,
            ", 3] is outside [0, 1]");
  }
  if (v.alpha)
    for (index_t i = 0; i < v.views * v.h * v.w; ++i) {
      const double a = static_cast<double>(v.alpha[i]);
      require(a >= 0 && a <= 1, "refine: alpha value ", a, " at flat index ", i, " of [", v.views, ", ", v.h, ", ",
              v.w, "] is outside [0, 1]");
    }
  for (index_t k = 0; k < v.views; ++k) {
    const T* K = v.K + 9 * k;
    require(std::isfinite(static_cast<double>(K[0])) && std::isfinite(static_cast<double>(K[4])) && K[0] > T(0) &&
                K[4] > T(0) && std::isfinite(static_cast<double>(K[2])) && std::isfinite(static_cast<double>(K[5])),
            "refine: view ", k, " has intrinsics fx ", K[0], ", fy ", K[4], ", cx ", K[2], ", cy ", K[5],
            " (must be finite, focal lengths > 0)");
    for (int i = 0; i < 12; ++i)
      require(std::isfinite(static_cast<double>(v.world_to_camera[12 * k + i])), "refine: view ", k,
              " world_to_camera[", i / 4, ",", i % 4, "] = ", v.world_to_camera[12 * k + i], " is not finite");
  }
}

// The views' cameras (K and world-to-camera as given, at the views' size).
template <class T>
std::vector<Camera> view_cameras(const RefineViews<T>& v) {
  std::vector<Camera> cams;
  for (index_t k = 0; k < v.views; ++k)
    cams.push_back(camera_from_arrays(v.K + 9 * k, v.world_to_camera + 12 * k, static_cast<int>(v.w),
                                      static_cast<int>(v.h)));
  return cams;
}

// The opacity-weighted centre of the Gaussians; false when the opacities sum to zero.
template <class T>
bool weighted_centre(const GaussianSet<T>& set, glm::dvec3& centre) {
  centre = glm::dvec3(0.0);
  double weight = 0;
  for (index_t i = 0; i < set.size(); ++i) {
    const double o = static_cast<double>(set.opacities(i));
    centre += o * glm::dvec3(set.means(i, 0), set.means(i, 1), set.means(i, 2));
    weight += o;
  }
  if (!(weight > 0)) return false;
  centre /= weight;
  return std::isfinite(centre.x) && std::isfinite(centre.y) && std::isfinite(centre.z);
}

// Mean distance from the camera centres to the opacity-weighted centre of the Gaussians (1 if that is degenerate).
template <class T>
double scene_extent(const GaussianSet<T>& set, const std::vector<double>& w2c, index_t views) {
  glm::dvec3 c0;
  if (!weighted_centre(set, c0)) return 1.0;
  const Eigen::Vector3d centre(c0.x, c0.y, c0.z);
  double sum = 0;
  for (index_t v = 0; v < views; ++v) {
    const double* E = w2c.data() + 12 * v;
    Eigen::Matrix3d R;
    for (int r = 0; r < 3; ++r)
      for (int col = 0; col < 3; ++col) R(r, col) = E[4 * r + col];
    const Eigen::Vector3d c = -R.transpose() * Eigen::Vector3d(E[3], E[7], E[11]);
    sum += (c - centre).norm();
  }
  const double extent = sum / static_cast<double>(views);
  return std::isfinite(extent) && extent > 0 ? extent : 1.0;
}

// A fresh store for n Gaussians with K SH coefficients and, with `cameras`, the views' rigid increments.
template <class T>
void build_store(train::ParamStore<T>& store, index_t n, index_t K, index_t views, bool cameras) {
  store = train::ParamStore<T>{};
  store.add_segment("gaussians", {{"means", {n, 3}}, {"quats", {n, 4}}, {"log_scales", {n, 3}},
                                  {"opacity_logits", {n}}, {"sh_dc", {n, 1, 3}}, {"sh_rest", {n, K - 1, 3}}});
  if (cameras) store.add_segment("cameras", {{"rotations", {views, 3}}, {"translations", {views, 3}}});
  store.allocate(true);
}

template <class T>
void set_learning_rates(train::ParamStore<T>& store, const RefineConfig& c, double extent, double progress) {
  const double s = c.lr_scale;
  store.set_lr_scale("means", s * c.lr_means * extent * std::pow(refine_position_decay, progress));
  store.set_lr_scale("quats", s * c.lr_quats);
  store.set_lr_scale("log_scales", s * c.lr_scales);
  store.set_lr_scale("opacity_logits", s * c.lr_opacity);
  store.set_lr_scale("sh_dc", s * c.lr_sh);
  store.set_lr_scale("sh_rest", s * c.lr_sh * c.lr_sh_rest_ratio);
  if (store.contains("rotations")) {
    store.set_lr_scale("rotations", s * c.lr_rotation);
    store.set_lr_scale("translations", s * c.lr_translation * extent);
  }
}

// The renderable set from the store's parameters.
template <class T>
void activate(RefineWorkspace<T>& ws, index_t n, index_t K) {
  const auto& st = ws.store;
  resize_gaussian_set(ws.set, n, sh_degree_for(K, "refine"));
  std::copy_n(st.param("means").data(), n * 3, ws.set.means.data());
  std::copy_n(st.param("quats").data(), n * 4, ws.set.quats.data());
  const auto ls = st.param("log_scales");
  for (index_t i = 0; i < n * 3; ++i) ws.set.scales.data()[i] = std::exp(ls[static_cast<std::size_t>(i)]);
  const auto lo = st.param("opacity_logits");
  for (index_t i = 0; i < n; ++i) ws.set.opacities(i) = nn::sigmoid(lo[static_cast<std::size_t>(i)]);
  const auto dc = st.param("sh_dc"), rest = st.param("sh_rest");
  for (index_t i = 0; i < n; ++i) {
    std::copy_n(dc.data() + i * 3, 3, ws.set.sh.data() + i * K * 3);
    std::copy_n(rest.data() + i * (K - 1) * 3, (K - 1) * 3, ws.set.sh.data() + (i * K + 1) * 3);
  }
}

// Mean loss of the views `which` (null: every view) for the current set; with backward, the gradients go into the
// store (cameras too).
template <class T>
double views_loss(RefineWorkspace<T>& ws, const RefineViews<T>& v, const RefineConfig& c, bool backward,
                  const std::vector<index_t>* which = nullptr) {
  const index_t n = ws.set.size(), K = ws.set.sh.shape(1);
  const index_t V = which ? static_cast<index_t>(which->size()) : v.views;
  raster::RenderOptions ro;
  ro.background = c.background;
  const loss::ImageShape shape{1, 3, v.h, v.w, loss::Layout::nhwc};
  const T* no_mask = nullptr;
  const double per_view = 1.0 / static_cast<double>(V);
  const bool cameras = backward && ws.store.contains("rotations");
  if (backward) {
    ws.store.zero_grads();
    resize_gaussian_grad(ws.grad, ws.set);
    ws.grad.zero();
  }
  double total = 0;
  for (index_t j = 0; j < V; ++j) {
    const index_t k = which ? (*which)[static_cast<std::size_t>(j)] : j;
    T Kf[9], E[12];
    for (int i = 0; i < 9; ++i) Kf[i] = v.K[9 * k + i];
    for (int i = 0; i < 12; ++i) E[i] = static_cast<T>(ws.w2c[static_cast<std::size_t>(12 * k + i)]);
    const raster::View<T> cam = raster::view_from_arrays(Kf, E, static_cast<int>(v.w), static_cast<int>(v.h));
    raster::render_forward(ws.set, cam, ro, ws.render, ws.out);
    const T* img = ws.out.image.data();
    const T* target = v.images + k * v.h * v.w * 3;
    const double l1 = loss::l1_forward(img, target, no_mask, shape);
    const double ssim = c.ssim_weight > 0 ? loss::ssim_forward(img, target, shape, loss::SsimConfig{}, ws.ssim) : 1.0;
    total += per_view * ((1 - c.ssim_weight) * l1 + c.ssim_weight * (1 - ssim));
    if (!backward) continue;
    ws.d_image.resize(ws.out.image.shape());
    ws.d_image.fill(T(0));
    loss::l1_backward(ws.d_image.data(), static_cast<T*>(nullptr), per_view * (1 - c.ssim_weight), img, target, no_mask,
                      shape);
    if (c.ssim_weight > 0)
      loss::ssim_backward(ws.d_image.data(), static_cast<T*>(nullptr), -per_view * c.ssim_weight, img, target, shape,
                          loss::SsimConfig{}, ws.ssim);
    const bool this_camera = cameras && !(c.fix_first_camera && k == 0);
    raster::ViewGrad<T> dcam;
    raster::render_backward(ws.set, cam, ro, ws.render,
                            raster::RenderOutputGrads<T>{TensorView<const T, 3>(ws.d_image.view()), {}, {}, {}},
                            ws.grad, this_camera ? &dcam : nullptr);
    if (!this_camera) continue;
    // dL/domega_j = <M, [e_j]x>, M = G_R R^T + G_t t^T; dL/dtau = G_t (R, t: the current camera).
    Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
    const double* W = ws.w2c.data() + 12 * k;
    for (int r = 0; r < 3; ++r)
      for (int col = 0; col < 3; ++col) {
        double s = 0;
        for (int j = 0; j < 3; ++j) s += static_cast<double>(dcam.world_to_camera[4 * r + j]) * W[4 * col + j];
        M(r, col) = s + static_cast<double>(dcam.world_to_camera[4 * r + 3]) * W[4 * col + 3];
      }
    T* dr = ws.store.grad("rotations").data() + 3 * k;
    T* dt = ws.store.grad("translations").data() + 3 * k;
    dr[0] += static_cast<T>(M(2, 1) - M(1, 2));
    dr[1] += static_cast<T>(M(0, 2) - M(2, 0));
    dr[2] += static_cast<T>(M(1, 0) - M(0, 1));
    for (int r = 0; r < 3; ++r) dt[r] += dcam.world_to_camera[4 * r + 3];
  }
  if (!backward) return total;
  // Chain rule through the activations into the store.
  auto& st = ws.store;
  std::copy_n(ws.grad.means.data(), n * 3, st.grad("means").data());
  std::copy_n(ws.grad.quats.data(), n * 4, st.grad("quats").data());
  const auto gls = st.grad("log_scales");
  for (index_t i = 0; i < n * 3; ++i) gls[static_cast<std::size_t>(i)] = ws.grad.scales.data()[i] * ws.set.scales.data()[i];
  const auto glo = st.grad("opacity_logits");
  for (index_t i = 0; i < n; ++i) {
    const T o = ws.set.opacities(i);
    glo[static_cast<std::size_t>(i)] = ws.grad.opacities(i) * o * (T(1) - o);
  }
  const auto gdc = st.grad("sh_dc"), grest = st.grad("sh_rest");
  for (index_t i = 0; i < n; ++i) {
    std::copy_n(ws.grad.sh.data() + i * K * 3, 3, gdc.data() + i * 3);
    std::copy_n(ws.grad.sh.data() + (i * K + 1) * 3, (K - 1) * 3, grest.data() + i * (K - 1) * 3);
  }
  return total;
}

// Removes the Gaussians whose opacity is below the threshold (keeping at least one), with their Adam moments.
template <class T>
index_t prune(RefineWorkspace<T>& ws, index_t K, index_t views, double threshold) {
  const index_t n = ws.set.size();
  std::vector<index_t> keep;
  for (index_t i = 0; i < n; ++i)
    if (static_cast<double>(ws.set.opacities(i)) >= threshold) keep.push_back(i);
  if (keep.empty() || static_cast<index_t>(keep.size()) == n) return 0;
  const index_t m = static_cast<index_t>(keep.size());
  train::ParamStore<T> next;
  build_store(next, m, K, views, ws.store.contains("rotations"));
  for (const auto& t : ws.store.tensors()) {
    const train::ParamInfo& u = next.info(t.name);
    if (t.name == "rotations" || t.name == "translations") {
      std::copy_n(ws.store.params() + t.offset, t.numel, next.params() + u.offset);
      std::copy_n(ws.store.adam_m() + t.offset, t.numel, next.adam_m() + u.offset);
      std::copy_n(ws.store.adam_v() + t.offset, t.numel, next.adam_v() + u.offset);
      continue;
    }
    const index_t row = t.numel / n;
    for (index_t j = 0; j < m; ++j) {
      const index_t src = t.offset + keep[static_cast<std::size_t>(j)] * row, dst = u.offset + j * row;
      std::copy_n(ws.store.params() + src, row, next.params() + dst);
      std::copy_n(ws.store.adam_m() + src, row, next.adam_m() + dst);
      std::copy_n(ws.store.adam_v() + src, row, next.adam_v() + dst);
    }
  }
  for (index_t j = 0; j < m; ++j) ws.origin[static_cast<std::size_t>(j)] = ws.origin[static_cast<std::size_t>(keep[static_cast<std::size_t>(j)])];
  ws.origin.resize(static_cast<std::size_t>(m));
  ws.store = std::move(next);
  return n - m;
}

// A fresh store holding `set` (opacities clamped to [floor, 1 - floor] before the logit) and zero camera increments.
template <class T>
void load(RefineWorkspace<T>& ws, const GaussianSet<T>& set, bool cameras, index_t views) {
  const index_t n = set.size(), K = set.sh.shape(1);
  build_store(ws.store, n, K, views, cameras);
  auto& st = ws.store;
  std::copy_n(set.means.data(), n * 3, st.param("means").data());
  std::copy_n(set.quats.data(), n * 4, st.param("quats").data());
  for (index_t i = 0; i < n * 3; ++i) st.param("log_scales")[static_cast<std::size_t>(i)] = std::log(set.scales.data()[i]);
  for (index_t i = 0; i < n; ++i) {
    const double o = std::clamp(static_cast<double>(set.opacities(i)), refine_opacity_floor, 1 - refine_opacity_floor);
    st.param("opacity_logits")[static_cast<std::size_t>(i)] = static_cast<T>(nn::logit(o, 40.0));
    std::copy_n(set.sh.data() + i * K * 3, 3, st.param("sh_dc").data() + i * 3);
    std::copy_n(set.sh.data() + (i * K + 1) * 3, (K - 1) * 3, st.param("sh_rest").data() + i * (K - 1) * 3);
  }
  ws.origin.resize(static_cast<std::size_t>(n));
  for (index_t i = 0; i < n; ++i) ws.origin[static_cast<std::size_t>(i)] = i;
}

// When an optimisation stops: after `seconds` (0: no limit) or `steps` (0: no limit). The position learning rate
// decays over `horizon` steps when > 0, else over whichever budget is nearer its end.
struct Schedule {
  double seconds = 0;
  std::int64_t steps = 0, horizon = 0;
};

// Optimises the loaded store on the views `fit` until the schedule ends; returns the steps taken. After each step
// after(step, done) runs.
template <class T, class After>
std::int64_t optimise(RefineWorkspace<T>& ws, const RefineViews<T>& v, const RefineConfig& c,
                      const std::vector<index_t>& fit, bool cameras, double extent, const Schedule& s,
                      index_t* pruned, After&& after) {
  using clock = std::chrono::steady_clock;
  const auto start = clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(clock::now() - start).count(); };
  const index_t V = v.views, K = ws.store.info("sh_rest").shape[1] + 1;
  const train::AdamWConfig adam{0.9, 0.999, 1e-15, 0.0};
  std::int64_t steps = 0;
  while (true) {
    const index_t n = ws.store.info("means").shape[0];
    double progress = 0;
    if (s.horizon > 0) progress = static_cast<double>(steps) / static_cast<double>(s.horizon);
    else {
      if (s.steps > 0) progress = static_cast<double>(steps) / static_cast<double>(s.steps);
      if (s.seconds > 0) progress = std::max(progress, elapsed() / s.seconds);
    }
    activate(ws, n, K);
    const double loss = views_loss(ws, v, c, true, &fit);
    require(std::isfinite(loss), "refine: the loss became ", loss, " at step ", steps + 1);
    set_learning_rates(ws.store, c, extent, std::min(1.0, progress));
    ++steps;
    train::adamw_step(ws.store, adam, 1.0, static_cast<std::uint64_t>(steps));
    auto quats = ws.store.param("quats");
    for (index_t i = 0; i < n; ++i) {  // keep quaternions away from zero length
      T* q = quats.data() + 4 * i;
      if (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < T(1e-12)) q[0] = 1, q[1] = q[2] = q[3] = 0;
    }
    if (cameras) {  // fold each increment into its camera; the increments restart from zero
      auto rot = ws.store.param("rotations"), tr = ws.store.param("translations");
      for (index_t k = 0; k < V; ++k) {
        T* o = rot.data() + 3 * k;
        T* t = tr.data() + 3 * k;
        const Eigen::Matrix3d E = exp_so3(Eigen::Vector3d(o[0], o[1], o[2]));
        double* W = ws.w2c.data() + 12 * k;
        Eigen::Matrix<double, 3, 4> M;
        for (int row = 0; row < 3; ++row)
          for (int col = 0; col < 4; ++col) M(row, col) = W[4 * row + col];
        M = (E * M).eval();
        for (int row = 0; row < 3; ++row) {
          M(row, 3) += static_cast<double>(t[row]);
          for (int col = 0; col < 4; ++col) W[4 * row + col] = M(row, col);
        }
        std::fill_n(o, 3, T(0));
        std::fill_n(t, 3, T(0));
      }
    }
    const bool done = (s.steps > 0 && steps >= s.steps) || (s.seconds > 0 && elapsed() >= s.seconds);
    if (c.prune_every > 0 && steps % c.prune_every == 0 && !done) {
      activate(ws, n, K);
      *pruned += prune(ws, K, V, c.prune_opacity);
    }
    after(steps, done);
    if (done) return steps;
  }
}

}  // namespace refine_detail

// Removes the Gaussians whose centre projects onto background in some view: alpha [V, h, w] below
// refine_mask_threshold everywhere within `margin` pixels (the silhouettes widened, for cameras that are estimates).
// Centres behind a camera or outside its picture are kept (that view says nothing about them); at least one Gaussian
// stays. Features follow their rows. Returns the number removed. For photos without alpha (all 1) nothing is removed.
template <class T>
index_t carve_to_silhouettes(GaussianSet<T>& set, const RefineViews<T>& v, const T* alpha, index_t margin) {
  require(alpha && v.K && v.world_to_camera && v.views >= 1 && v.h >= 1 && v.w >= 1 && margin >= 0,
          "carve: need alpha, K and world_to_camera for at least one view, and a margin >= 0 (got ", margin, ")");
  check_gaussian_shapes(set, "carve");
  const index_t V = v.views, h = v.h, w = v.w, n = set.size();
  // Per view the widened silhouette: a pixel is inside when some pixel within `margin` (a square) is foreground.
  std::vector<std::uint8_t> inside(static_cast<std::size_t>(V * h * w), 0), rows(static_cast<std::size_t>(h * w));
  for (index_t k = 0; k < V; ++k) {
    const T* a = alpha + k * h * w;
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x) {
        bool any = false;
        for (index_t xx = std::max<index_t>(0, x - margin); xx <= std::min(w - 1, x + margin) && !any; ++xx)
          any = static_cast<double>(a[y * w + xx]) >= refine_mask_threshold;
        rows[static_cast<std::size_t>(y * w + x)] = any;
      }
    std::uint8_t* in = inside.data() + k * h * w;
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x) {
        bool any = false;
        for (index_t yy = std::max<index_t>(0, y - margin); yy <= std::min(h - 1, y + margin) && !any; ++yy)
          any = rows[static_cast<std::size_t>(yy * w + x)] != 0;
        in[y * w + x] = any;
      }
  }
  const std::vector<Camera> cams = refine_detail::view_cameras(v);
  std::vector<index_t> keep;
  for (index_t i = 0; i < n; ++i) {
    bool out = false;
    const glm::dvec3 p(set.means(i, 0), set.means(i, 1), set.means(i, 2));
    for (index_t k = 0; k < V && !out; ++k) {
      const glm::dvec3 q = cams[static_cast<std::size_t>(k)].to_camera(p);
      if (!(q.z > 0)) continue;
      const glm::dvec2 uv = cams[static_cast<std::size_t>(k)].project(q);
      if (!(uv.x >= 0 && uv.y >= 0 && uv.x < static_cast<double>(w) && uv.y < static_cast<double>(h))) continue;
      out = !inside[static_cast<std::size_t>(k * h * w + static_cast<index_t>(uv.y) * w + static_cast<index_t>(uv.x))];
    }
    if (!out) keep.push_back(i);
  }
  if (keep.empty()) keep.push_back(0);
  const index_t m = static_cast<index_t>(keep.size());
  if (m == n) return 0;
  set = select_gaussians(set, keep);
  return n - m;
}

// n Gaussians for a per-scene fit from posed views, defined by the views alone: uniform in the sphere around the
// point nearest to the optical axes (decoder::scene_centre_from_axes; or centre_given) whose radius the narrowest
// view sees whole (distance x sin of the smallest half field of view), kept where every view's alpha is >=
// refine_mask_threshold (the visual hull of the silhouettes; after 64 n draws the rest is taken without the test).
// Colour: the mean of the views' pixels the centre projects to (occlusion ignored); scale: half the spacing of n
// points in the sphere; opacity refine_init_opacity; identity rotations; SH degree `degree` (higher bands zero).
// images [V, h, w, 3], alpha [V, h, w] (null: no silhouette test), K and w2c as RefineViews.
template <class T>
GaussianSet<T> random_gaussians_in_views(index_t n, int degree, const RefineViews<T>& v, const T* alpha,
                                         std::uint64_t seed, const glm::dvec3* centre_given = nullptr) {
  require(n >= 1, "random Gaussians: count ", n, " must be >= 1");
  require(v.views >= 1 && v.h >= 1 && v.w >= 1 && v.images && v.K && v.world_to_camera,
          "random Gaussians: need at least one view with images, K and world_to_camera");
  const index_t V = v.views;
  const std::vector<Camera> cams = refine_detail::view_cameras(v);
  glm::dvec3 centre;
  if (centre_given) centre = *centre_given;
  else {
    std::vector<double> K(static_cast<std::size_t>(9 * V)), E(static_cast<std::size_t>(12 * V)),
        depth(static_cast<std::size_t>(V), 1.0);
    for (index_t k = 0; k < V; ++k)
      camera_arrays(cams[static_cast<std::size_t>(k)], K.data() + 9 * k, E.data() + 12 * k);
    const decoder::ViewGeometry<double> geometry{V, v.w, v.h, 1, 1, K.data(), E.data(), depth.data()};
    const decoder::SceneCentre scene = decoder::scene_centre_from_axes(geometry);
    centre = glm::dvec3(scene.centre[0], scene.centre[1], scene.centre[2]);
  }
  double radius = std::numeric_limits<double>::infinity();
  for (const Camera& cam : cams) {
    const double fx = cam.K[0][0], fy = cam.K[1][1], cx = cam.K[2][0], cy = cam.K[2][1];
    const double half = std::min({std::atan2(cx, fx), std::atan2(static_cast<double>(v.w) - cx, fx),
                                  std::atan2(cy, fy), std::atan2(static_cast<double>(v.h) - cy, fy)});
    radius = std::min(radius, glm::length(cam.to_camera(centre)) * std::sin(std::max(half, 1e-3)));
  }
  require(std::isfinite(radius) && radius > 0, "random Gaussians: the views see no sphere around the scene centre (",
          "radius ", radius, ")");
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  GaussianSet<T> s = make_gaussian_set<T>(n, degree);
  const index_t px = v.h * v.w;
  index_t made = 0, draws = 0;
  while (made < n) {
    const glm::dvec3 u(uni(rng), uni(rng), uni(rng));
    if (glm::dot(u, u) > 1) continue;
    ++draws;
    const glm::dvec3 p = centre + radius * u;
    const bool test = alpha && draws <= 64 * n;
    bool inside = true;
    double rgb[3] = {0, 0, 0};
    for (index_t k = 0; k < V && inside; ++k) {
      const Camera& cam = cams[static_cast<std::size_t>(k)];
      const glm::dvec3 q = cam.to_camera(p);
      if (!(q.z > 0)) {  // behind this camera: outside its silhouette
        inside = !test;
        if (!inside) break;
        continue;
      }
      const glm::dvec2 uv = cam.project(q);
      const double x = std::clamp(uv.x, 0.0, static_cast<double>(v.w) - 1e-9);
      const double y = std::clamp(uv.y, 0.0, static_cast<double>(v.h) - 1e-9);
      const index_t pix = static_cast<index_t>(y) * v.w + static_cast<index_t>(x);
      if (test && static_cast<double>(alpha[k * px + pix]) < refine_mask_threshold) inside = false;
      for (int ch = 0; ch < 3; ++ch) rgb[ch] += static_cast<double>(v.images[(k * px + pix) * 3 + ch]) / static_cast<double>(V);
    }
    if (!inside) continue;
    for (int ch = 0; ch < 3; ++ch) {
      s.means(made, ch) = static_cast<T>(p[ch]);
      s.sh(made, 0, ch) = static_cast<T>((rgb[ch] - sh_color_offset) / sh_c0);
    }
    ++made;
  }
  const T scale = static_cast<T>(0.5 * radius * std::cbrt(4.18879020478639 / static_cast<double>(n)));
  s.scales.fill(scale);
  s.opacities.fill(static_cast<T>(refine_init_opacity));
  return s;
}

// Whether some view's alpha is below refine_mask_threshold somewhere (the silhouettes say where the object is not).
template <class T>
bool shows_background(const RefineViews<T>& v) {
  return v.alpha && std::any_of(v.alpha, v.alpha + v.views * v.h * v.w,
                                [](T a) { return static_cast<double>(a) < refine_mask_threshold; });
}

// Appends to `set` n Gaussians drawn by random_gaussians_in_views in the visual hull of v's silhouettes (v.alpha)
// around the set's opacity-weighted centre (the set's SH degree; zero feature rows) when some view shows background;
// returns how many were added.
template <class T>
index_t grow_in_hull(GaussianSet<T>& set, const RefineViews<T>& v, index_t n, std::uint64_t seed) {
  if (n <= 0 || !shows_background(v)) return 0;
  glm::dvec3 centre;
  if (!refine_detail::weighted_centre(set, centre)) return 0;
  const GaussianSet<T> more = random_gaussians_in_views<T>(n, set.sh_degree(), v, v.alpha, seed, &centre);
  const index_t m = set.size(), K = set.sh.shape(1), F = set.features.empty() ? 0 : set.features.shape(1);
  GaussianSet<T> all = make_gaussian_set<T>(m + n, set.sh_degree(), F);
  for (const auto& [from, offset] : {std::pair<const GaussianSet<T>*, index_t>{&set, 0}, {&more, m}}) {
    const index_t k = from->size();
    std::copy_n(from->means.data(), k * 3, all.means.data() + offset * 3);
    std::copy_n(from->quats.data(), k * 4, all.quats.data() + offset * 4);
    std::copy_n(from->scales.data(), k * 3, all.scales.data() + offset * 3);
    std::copy_n(from->opacities.data(), k, all.opacities.data() + offset);
    std::copy_n(from->sh.data(), k * K * 3, all.sh.data() + offset * K * 3);
  }
  if (F > 0) {
    std::copy_n(set.features.data(), m * F, all.features.data());
    std::fill_n(all.features.data() + m * F, n * F, T(0));
  }
  set = std::move(all);
  return n;
}

// Optimises `set` (in place; pruned Gaussians are removed, features follow their rows and are not optimised) and,
// with c.optimize_cameras, v.world_to_camera, on the views v. Intrinsics stay fixed.
template <class T>
RefineResult refine(GaussianSet<T>& set, const RefineViews<T>& v, const RefineConfig& c, RefineWorkspace<T>& ws) {
  using clock = std::chrono::steady_clock;
  const auto start = clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(clock::now() - start).count(); };
  refine_detail::validate(set, v, c);
  const index_t V = v.views, K = set.sh.shape(1);
  const std::vector<double> w2c0(v.world_to_camera, v.world_to_camera + 12 * V);
  ws.w2c = w2c0;
  const bool cameras = c.optimize_cameras && V > (c.fix_first_camera ? 1 : 0);
  RefineResult r;
  r.extent = c.extent > 0 ? c.extent : refine_detail::scene_extent(set, ws.w2c, V);
  std::vector<index_t> all(static_cast<std::size_t>(V));
  for (index_t k = 0; k < V; ++k) all[static_cast<std::size_t>(k)] = k;
  refine_detail::load(ws, set, cameras, V);
  refine_detail::activate(ws, set.size(), K);
  r.loss_initial = refine_detail::views_loss(ws, v, c, false);
  refine_detail::Schedule schedule{c.seconds, c.steps, 0};
  const bool carve = c.carve && v.alpha;
  const index_t margin = static_cast<index_t>(std::llround(refine_carve_margin * static_cast<double>(std::max(v.h, v.w))));
  if (c.validate && V >= 2) {
    // The trial: views 0..V-2 carve and fit, the last one scores; the full fit gets the rest of the budget.
    const std::vector<index_t> fit(all.begin(), all.end() - 1), held{V - 1};
    const double share = static_cast<double>(V - 1) / static_cast<double>(2 * V - 1);
    auto held_loss = [&] {
      refine_detail::activate(ws, ws.store.info("means").shape[0], K);
      return refine_detail::views_loss(ws, v, c, false, &held);
    };
    refine_detail::load(ws, set, cameras, V);
    r.holdout_initial = r.holdout_best = held_loss();
    r.chosen_steps = 0;
    bool changed = false;  // the best so far is not the input: carved, or fitted
    GaussianSet<T> start = set;
    if (carve || c.grow > 0) {
      RefineViews<T> seen = v;
      seen.views = V - 1;
      const index_t changes = (carve ? carve_to_silhouettes(start, seen, v.alpha, margin) : 0) +
                              grow_in_hull(start, seen, c.grow, c.seed);
      if (changes > 0) {
        refine_detail::load(ws, start, cameras, V);
        const double l = held_loss();
        if (l < r.holdout_best) r.holdout_best = l, changed = true;
      }
    }
    index_t trial_pruned = 0;
    r.trial_steps = refine_detail::optimise(
        ws, v, c, fit, cameras, r.extent, refine_detail::Schedule{c.seconds * share, c.steps, 0},
        &trial_pruned, [&](std::int64_t step, bool done) {
          if (step % c.validate_every != 0 && !done) return;
          const double l = held_loss();
          if (l < r.holdout_best) r.holdout_best = l, r.chosen_steps = step, changed = true;
        });
    ws.w2c = w2c0;
    if (!changed) {  // neither carving nor any step helped the held-out view: the input stays
      r.loss_final = r.loss_initial;
      r.seconds = elapsed();
      return r;
    }
    schedule = refine_detail::Schedule{0, r.chosen_steps, r.trial_steps};
  }
  if (carve) r.carved = carve_to_silhouettes(set, v, v.alpha, margin);
  r.grown = grow_in_hull(set, v, c.grow, c.seed);
  refine_detail::load(ws, set, cameras, V);
  if (schedule.steps > 0 || schedule.seconds > 0)
    r.steps = refine_detail::optimise(ws, v, c, all, cameras, r.extent, schedule, &r.pruned,
                                      [](std::int64_t, bool) {});
  const index_t n = ws.store.info("means").shape[0];
  refine_detail::activate(ws, n, K);
  r.loss_final = refine_detail::views_loss(ws, v, c, false);
  // Back to the caller: the optimised set (features follow their rows) and cameras.
  Tensor<T, 2> features;
  if (!set.features.empty()) {
    const index_t F = set.features.shape(1);
    features = Tensor<T, 2>(Shape<2>{n, F});
    for (index_t i = 0; i < n; ++i)
      std::copy_n(&set.features(ws.origin[static_cast<std::size_t>(i)], 0), F, &features(i, 0));
  }
  set = ws.set;
  set.features = std::move(features);
  if (cameras)
    for (index_t i = 0; i < 12 * V; ++i) v.world_to_camera[i] = static_cast<T>(ws.w2c[static_cast<std::size_t>(i)]);
  r.seconds = elapsed();
  return r;
}

// How eval and reconstruct refine a prediction for `seconds`: carved, and grown by `grow` Gaussians at 3DGS's
// learning rates when some photo shows background; otherwise the prediction alone at refine_prediction_lr_scale
// (docs/evaluation.md measures both).
template <class T>
RefineConfig prediction_refine_config(const RefineViews<T>& v, double seconds, std::uint64_t seed,
                                      index_t grow = refine_grow_gaussians) {
  RefineConfig c;
  c.seconds = seconds;
  c.seed = seed;
  c.grow = shows_background(v) ? grow : 0;
  c.lr_scale = c.grow > 0 ? 1.0 : refine_prediction_lr_scale;
  return c;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
