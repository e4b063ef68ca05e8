#pragma once
// The appearance half of FlexSplat's training objective: from the geometry stage's outputs (cameras, depth,
// confidence, depth features) through UNet, fusion and the Gaussian decoder, every decoder layer rendered at every
// requested view, and the paper's loss
//   L = lambda_E MSE(RGB head, inputs) + sum over layers [lambda_D MSE(render, target) + lambda_P LPIPS(render, target)]
//       + lambda_depth |(D_rendered - D_vggt) * U|   (input views rendered with their predicted cameras)
// with gradients into the appearance parameters and into the geometry outputs (extrinsics and K through the
// rasterizer's camera adjoints, depth through both the decoder's eq. 2 and the depth term, depth features through
// the fusion). Each view is rendered, scored and differentiated before the next, so one render workspace serves all.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <span>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/profile.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/model.hpp"
#include "flexsplat/image/layout.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/geometry_result.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

struct ObjectiveWeights {
  double rgb_head = 1.0;       // lambda_E: the UNet/fusion RGB head reconstructs the inputs
  double render = 1.0;         // lambda_D: per decoder layer, mean over views
  double depth = 0.1;          // confidence-weighted L1 of rendered against predicted depth, input views
  double lpips = 0.0;          // lambda_P: per decoder layer; 0 until the LPIPS stage (the paper adds it later)
  bool initial_layer = false;  // also render the initial splat head's Gaussians (before the first decoder layer)

  void validate() const {
    for (double v : {rgb_head, render, depth, lpips})
      require(std::isfinite(v) && v >= 0, "objective: loss weights must be finite and >= 0, got ", v);
  }
};

// A camera to render and what it should show. input_view >= 0 renders with that input view's predicted camera (its
// gradient reaches the geometry stage); otherwise K and world_to_camera (in the model's frame) are used as given.
template <class T>
struct RenderView {
  std::array<T, 9> K{};
  std::array<T, 12> world_to_camera{};
  int width = 0, height = 0;
  index_t input_view = -1;
  const T* target = nullptr;  // [height, width, 3] in [0, 1]
  const T* mask = nullptr;    // [height, width] object mask for the depth term (input views; null: every pixel)
};

struct LossParts {
  double total = 0, rgb_head = 0, render = 0, depth = 0, lpips = 0;
  double psnr_last = 0;  // mean PSNR of the last decoder layer's renders (a metric; a view counts at most 100 dB)
};

// One value per phase of a training step.
struct PhaseValues {
  double geometry_forward = 0, geometry_backward = 0, decoder_forward = 0, decoder_backward = 0;
  double raster_forward = 0, raster_backward = 0, losses = 0, update = 0;
  double total() const {
    return geometry_forward + geometry_backward + decoder_forward + decoder_backward + raster_forward +
           raster_backward + losses + update;
  }
  PhaseValues& operator+=(const PhaseValues& o) {
    for (double PhaseValues::*f : {&PhaseValues::geometry_forward, &PhaseValues::geometry_backward,
                                   &PhaseValues::decoder_forward, &PhaseValues::decoder_backward,
                                   &PhaseValues::raster_forward, &PhaseValues::raster_backward, &PhaseValues::losses,
                                   &PhaseValues::update})
      this->*f += o.*f;
    return *this;
  }
};

// Wall time per phase in milliseconds, accumulated (benchmarks and the training log read it), and the GEMM and
// attention FLOPs each phase ran while profile:: is enabled.
struct PhaseTimes : PhaseValues {
  PhaseValues flops;
  PhaseTimes& operator+=(const PhaseTimes& o) {
    PhaseValues::operator+=(o);
    flops += o.flops;
    return *this;
  }
};

// Adds the time (and profiled FLOPs) since construction or the last lap to a PhaseTimes field.
class PhaseClock {
public:
  explicit PhaseClock(PhaseTimes* times)
      : times_(times), last_(std::chrono::steady_clock::now()), last_flops_(profiled_flops()) {}
  void lap(double PhaseValues::*field) {
    const auto now = std::chrono::steady_clock::now();
    const double flops = profiled_flops();
    if (times_) {
      times_->*field += std::chrono::duration<double, std::milli>(now - last_).count();
      times_->flops.*field += flops - last_flops_;
    }
    last_ = now, last_flops_ = flops;
  }

private:
  // Inside a SerialScope other threads run other scenes: only this thread's FLOPs are the phase's.
  static double profiled_flops() {
    if (!profile::enabled()) return 0;
    if (serial_scope_open()) return profile::thread_flops();
    const profile::Totals t = profile::totals();
    double sum = 0;
    for (double f : t.flops) sum += f;
    return sum;
  }
  PhaseTimes* times_;
  std::chrono::steady_clock::time_point last_;
  double last_flops_;
};

template <class T>
struct ObjectiveWorkspace {
  decoder::ModelWorkspace<T> model;
  raster::RenderWorkspace<T> render;
  raster::RenderOutputs<T> out;
  std::vector<GaussianSetGrad<T>> d_gaussians;
  AlignedVector<T> d_rgb, d_image, d_depth, weights;
  loss::LpipsCache<T> lpips;
  AlignedVector<T> render_chw, target_chw, d_render_chw;
};

// Forward, loss and backward of the appearance side for one scene. images [V, 3, h, w] in [0, 1]; params/d_params:
// the decoder::ModelParamLayout block and its gradient (added into; null: forward and losses only, d_geometry null
// too); d_geometry (may be null: geometry frozen) is added into and must be shaped like g (GeometryResult::zero_like).
// lpips may be null when weights.lpips is 0.
template <class T>
LossParts appearance_objective(ObjectiveWorkspace<T>& ws, const T* params, T* d_params, const decoder::ModelConfig& c,
                               index_t n_queries, const T* images, const GeometryResult<T>& g,
                               GeometryResult<T>* d_geometry, std::span<const RenderView<T>> views,
                               const ObjectiveWeights& weights, const raster::RenderOptions& render_options,
                               const loss::LpipsWeights<T>* lpips = nullptr, PhaseTimes* times = nullptr) {
  weights.validate();
  PhaseClock clock(times);
  require(!views.empty(), "objective: no views to render");
  require(weights.lpips == 0 || lpips, "objective: lambda_P is ", weights.lpips, " but no LPIPS weights were given");
  const bool backward = d_params != nullptr;
  require(backward || !d_geometry, "objective: geometry gradients asked for without parameter gradients");
  const index_t V = g.views, h = g.h, w = g.w;
  const decoder::ViewGeometry<T> vg = g.view_geometry();
  decoder::model_forward(ws.model, n_queries, params, c, images, h, w, g.features.data(), g.feature_h, g.feature_w, vg);
  clock.lap(&PhaseTimes::decoder_forward);
  const auto& sets = ws.model.gaussians();
  const index_t first = weights.initial_layer ? 0 : 1, layers = static_cast<index_t>(sets.size()) - first;
  require(layers >= 1, "objective: the decoder returned no layer to render");

  LossParts parts;
  // lambda_E: the RGB head against the inputs.
  const loss::ImageShape rgb_shape{V, 3, h, w, loss::Layout::nchw};
  if (weights.rgb_head > 0)
    parts.rgb_head = weights.rgb_head * loss::mse_forward(ws.model.rgb.data(), images, static_cast<const T*>(nullptr), rgb_shape);
  if (backward) {
    ws.d_rgb.assign(ws.model.rgb.size(), T(0));
    if (weights.rgb_head > 0)
      loss::mse_backward(ws.d_rgb.data(), static_cast<T*>(nullptr), weights.rgb_head, ws.model.rgb.data(), images,
                         static_cast<const T*>(nullptr), rgb_shape);
    ws.d_gaussians.resize(sets.size());
    for (std::size_t s = 0; s < sets.size(); ++s) {
      if (static_cast<index_t>(s) >= first) resize_gaussian_grad(ws.d_gaussians[s], sets[s]);
      else ws.d_gaussians[s] = GaussianSetGrad<T>();
      ws.d_gaussians[s].zero();
    }
  }
  raster::RenderOptions ro = render_options;
  ro.expected_depth = true;  // the depth term compares camera z with the depth head's
  const double per_view = 1.0 / static_cast<double>(views.size());
  double psnr_sum = 0;
  for (const auto& view : views) {
    require(view.target, "objective: a render view has no target image");
    const bool predicted = view.input_view >= 0;
    require(view.input_view < V, "objective: render view refers to input view ", view.input_view, " of ", V);
    require(!predicted || (view.width == w && view.height == h), "objective: input view ", view.input_view,
            " is rendered at ", view.width, " x ", view.height, ", the model's input is ", w, " x ", h);
    const T* K = predicted ? g.K.data() + 9 * view.input_view : view.K.data();
    const T* E = predicted ? g.extrinsics.data() + 12 * view.input_view : view.world_to_camera.data();
    const raster::View<T> cam = raster::view_from_arrays(K, E, view.width, view.height);
    const index_t H = view.height, W = view.width, pixels = H * W;
    const loss::ImageShape shape{1, 3, H, W, loss::Layout::nhwc};
    for (index_t l = 0; l < layers; ++l) {
      const auto& set = sets[static_cast<std::size_t>(first + l)];
      clock.lap(&PhaseTimes::losses);
      raster::render_forward(set, cam, ro, ws.render, ws.out);
      clock.lap(&PhaseTimes::raster_forward);
      const T* img = ws.out.image.data();
      if (backward) {
        ws.d_image.assign(static_cast<std::size_t>(3 * pixels), T(0));
        ws.d_depth.assign(static_cast<std::size_t>(pixels), T(0));
      }
      bool any_depth = false;
      if (weights.render > 0) {
        const double scale = weights.render * per_view;
        parts.render += scale * loss::mse_forward(img, view.target, static_cast<const T*>(nullptr), shape);
        if (backward)
          loss::mse_backward(ws.d_image.data(), static_cast<T*>(nullptr), scale, img, view.target,
                             static_cast<const T*>(nullptr), shape);
      }
      if (weights.lpips > 0) {
        const double scale = weights.lpips * per_view;
        ws.render_chw.resize(static_cast<std::size_t>(3 * pixels));
        ws.target_chw.resize(ws.render_chw.size());
        image::hwc_to_chw(ws.render_chw.data(), img, H, W);
        image::hwc_to_chw(ws.target_chw.data(), view.target, H, W);
        T value = 0;
        // Every layer of a view meets the same target: its trunk runs once per view.
        loss::lpips_forward(&value, static_cast<T*>(nullptr), ws.render_chw.data(), ws.target_chw.data(), 1, H, W,
                            lpips->params.data(), lpips->layout, ws.lpips, true, l > 0);
        parts.lpips += scale * static_cast<double>(value);
        if (backward) {
          ws.d_render_chw.assign(ws.render_chw.size(), T(0));
          const T d_value = static_cast<T>(scale);
          loss::lpips_backward(ws.d_render_chw.data(), static_cast<T*>(nullptr), &d_value,
                               static_cast<const T*>(nullptr), lpips->params.data(), lpips->layout, ws.lpips);
          image::add_chw_to_hwc(ws.d_image.data(), ws.d_render_chw.data(), H, W);
        }
      }
      if (predicted && weights.depth > 0) {
        // U is the depth head's confidence normalised to mean 1 over the compared pixels, held constant.
        const T* conf = g.confidence.data() + view.input_view * pixels;
        ws.weights.resize(static_cast<std::size_t>(pixels));
        double sum = 0, count = 0;
        for (index_t p = 0; p < pixels; ++p) {
          const double m = view.mask ? static_cast<double>(view.mask[p]) : 1.0;
          sum += m * static_cast<double>(conf[p]);
          count += m;
        }
        const double norm = sum > 0 ? count / sum : 0.0;
        for (index_t p = 0; p < pixels; ++p) ws.weights[static_cast<std::size_t>(p)] = static_cast<T>(conf[p] * norm);
        const T* vggt_depth = g.depth.data() + view.input_view * pixels;
        const double scale = weights.depth * per_view;
        parts.depth += scale * loss::depth_l1_forward(ws.out.depth.data(), vggt_depth, ws.weights.data(), view.mask, pixels);
        if (backward)
          loss::depth_l1_backward(ws.d_depth.data(),
                                  d_geometry ? d_geometry->depth.data() + view.input_view * pixels : static_cast<T*>(nullptr),
                                  scale, ws.out.depth.data(), vggt_depth, ws.weights.data(), view.mask, pixels);
        any_depth = true;
      }
      // A pixel-exact render (an empty scene over its own background) counts as 100 dB (MSE floored at 1e-10, far
      // below 16-bit quantisation) instead of loss::psnr's +inf, so the logged mean stays a number.
      if (first + l == static_cast<index_t>(sets.size()) - 1)
        psnr_sum += std::min(loss::psnr(img, view.target, 3 * pixels), 100.0);
      if (!backward) continue;
      raster::RenderOutputGrads<T> d_out;
      d_out.image = TensorView<const T, 3>(ws.d_image.data(), Shape<3>{H, W, 3});
      if (any_depth) d_out.depth = TensorView<const T, 2>(ws.d_depth.data(), Shape<2>{H, W});
      raster::ViewGrad<T> d_cam;
      const bool camera_grad = predicted && d_geometry;
      clock.lap(&PhaseTimes::losses);
      raster::render_backward(set, cam, ro, ws.render, d_out, ws.d_gaussians[static_cast<std::size_t>(first + l)],
                              camera_grad ? &d_cam : nullptr);
      clock.lap(&PhaseTimes::raster_backward);
      if (camera_grad)
        raster::view_from_arrays_backward(d_geometry->K.data() + 9 * view.input_view,
                               d_geometry->extrinsics.data() + 12 * view.input_view, d_cam);
    }
  }
  parts.psnr_last = psnr_sum * per_view;
  parts.total = parts.rgb_head + parts.render + parts.depth + parts.lpips;
  if (!backward) return parts;

  decoder::ViewGeometryGrad<T> d_vg;
  if (d_geometry) d_vg = {d_geometry->K.data(), d_geometry->extrinsics.data(), d_geometry->depth.data()};
  clock.lap(&PhaseTimes::losses);
  decoder::model_backward(d_params, d_geometry ? d_geometry->features.data() : static_cast<T*>(nullptr), d_vg,
                          ws.d_gaussians, ws.d_rgb.data(), ws.model, params, c, images, g.features.data(), vg);
  clock.lap(&PhaseTimes::decoder_backward);
  return parts;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
