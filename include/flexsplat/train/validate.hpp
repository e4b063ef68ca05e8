#pragma once
// Validation during training: a held-out scene through the forward model, its target views rendered with the
// ground-truth cameras in the training frame (first input camera = identity, ground-truth scale normalised as in
// make_train_example), scored against the targets. No similarity alignment: this measures what the training
// objective asks of the model; `flexsplat eval` runs the paper's aligned protocol.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <vector>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/solvers/procrustes.hpp"
#include "flexsplat/loss/geometry.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/loss/match.hpp"
#include "flexsplat/loss/ssim.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/frames.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// Bins of ValidationScore::match_hits_by_baseline: the angle (degrees) between a view pair's true orientations.
inline constexpr std::array<double, 5> match_baseline_edges_deg{0, 30, 60, 90, 180};

// The bin of match_baseline_edges_deg an angle falls in (the last holds 180).
inline std::size_t baseline_bin(double angle_deg) {
  std::size_t bin = 0;
  while (bin + 2 < match_baseline_edges_deg.size() && angle_deg >= match_baseline_edges_deg[bin + 1]) ++bin;
  return bin;
}

struct ValidationScore {
  double psnr = 0, ssim = 0;    // means over the scene's target views
  // The same with the ground-truth input cameras handed to the decoder (validate_scene's true_cameras: what a
  // StepConfig::decoder_true_cameras stage trains); NaN otherwise.
  double psnr_true_cameras = std::numeric_limits<double>::quiet_NaN();
  double ssim_true_cameras = std::numeric_limits<double>::quiet_NaN();
  double rotation_deg = 0;      // mean over input views 2..V of the relative rotation error (0 for one view)
  double rra15 = 1, rra30 = 1;  // fraction of input-view pairs whose relative rotation is within 15 / 30 deg
  // The same three for the camera head's own cameras (the same as above unless another source placed the views).
  double head_rotation_deg = 0, head_rra15 = 1, head_rra30 = 1;
  // The same three for the cameras solved from the point head's map (solvers/procrustes.hpp); 0 without the head.
  double points_rotation_deg = 0, points_rra15 = 0, points_rra30 = 0;
  // The same for the cameras solved from the match head's correspondences; 0 without the head.
  double matches_rotation_deg = 0, matches_rra15 = 0, matches_rra30 = 0;
  // What limits the matched cameras: the fraction of the scene's ground-truth correspondences whose nearest
  // descriptor in the other view is within one pixel of the true one, and matches_rotation_deg with the renderer's
  // depth in place of the predicted one. 0 without the head.
  double match_accuracy = 0, matches_gt_depth_rotation_deg = 0;
  double match_accuracy_4px = 0;  // match_accuracy within four pixels: whether the descriptors find the region
  // match_accuracy's hits and correspondences by the ground-truth angle between the pair's views (baseline_bin).
  std::array<double, 4> match_hits_by_baseline{}, matches_by_baseline{};
  // View pairs by the same bins, and how many of them have their own fit (descriptor matches with the renderer's
  // depth, before the spanning tree) within 15 degrees of the true relative rotation.
  std::array<double, 4> pairs_by_baseline{}, pairs_within15_by_baseline{};
  // The ceiling of matching: the same solver on the renderer's correspondences with the true depth and intrinsics
  // (a view pair that shares too few surface points cannot be linked by any descriptor). 0 without the head.
  double matches_oracle_rotation_deg = 0, matches_oracle_rra15 = 0;
  double chance_rotation_deg = 0;  // rotation_deg of a constant guess (every camera the first one's orientation)
  double depth_rel = 0;         // mean |predicted - ground-truth depth| / ground-truth depth on object pixels
  // The same after each view's depth is scaled by its median ratio to the ground truth: the shape alone (what
  // solvers/orbit_search.hpp needs; a view's scale is absorbed by its distance), mean over views with object pixels.
  double depth_shape_rel = 0;
  index_t targets = 0, views = 0;
};

namespace detail {
// Mean error of views 2..V against the ground truth (both in the first camera's frame) and RRA@15/30 over all pairs.
inline void score_rotations(const double* pred, const double* gt, index_t views, double& mean, double& rra15,
                            double& rra30) {
  mean = 0, rra15 = rra30 = 1;
  if (views < 2) return;
  for (index_t v = 1; v < views; ++v) mean += rotation_error_deg(pred + 12 * v, gt + 12 * v) / static_cast<double>(views - 1);
  double pairs = 0, in15 = 0, in30 = 0;
  for (index_t i = 0; i < views; ++i)
    for (index_t j = i + 1; j < views; ++j) {
      const double e = relative_rotation_error_deg(pred + 12 * i, pred + 12 * j, gt + 12 * i, gt + 12 * j);
      pairs += 1, in15 += e <= 15, in30 += e <= 30;
    }
  rra15 = in15 / pairs, rra30 = in30 / pairs;
}
}  // namespace detail

template <class T>
struct ValidationWorkspace {
  PredictWorkspace<T> predict;
  raster::RenderWorkspace<T> render;
  raster::RenderOutputs<T> out;
  loss::SsimWorkspace ssim;
};

namespace detail {
// Mean PSNR and SSIM of a Gaussian set's renders of the scene's targets; each render appended to `renders` (may be null).
template <class T>
std::array<double, 2> score_targets(ValidationWorkspace<T>& ws, const GaussianSet<T>& gaussians, const TrainExample<T>& e,
                                    std::vector<Tensor<T, 3>>* renders) {
  raster::RenderOptions ro;
  ro.background = {static_cast<double>(e.background[0]), static_cast<double>(e.background[1]),
                   static_cast<double>(e.background[2])};
  const index_t px = e.h * e.w;
  const loss::ImageShape shape{1, 3, e.h, e.w, loss::Layout::nhwc};
  std::array<double, 2> score{0, 0};
  for (index_t m = 0; m < e.targets; ++m) {
    const auto& K = e.target_K[static_cast<std::size_t>(m)];
    const auto& E = e.target_w2c[static_cast<std::size_t>(m)];
    const raster::View<T> cam = raster::view_from_arrays(K.data(), E.data(), static_cast<int>(e.w), static_cast<int>(e.h));
    raster::render_forward(gaussians, cam, ro, ws.render, ws.out);
    const T* target = e.target_images.data() + m * px * 3;
    score[0] += loss::psnr(ws.out.image.data(), target, 3 * px);
    score[1] += loss::ssim_forward(ws.out.image.data(), target, shape, loss::SsimConfig{}, ws.ssim);
    if (renders) renders->push_back(ws.out.image);
  }
  score[0] /= static_cast<double>(e.targets), score[1] /= static_cast<double>(e.targets);
  return score;
}
}  // namespace detail

// Scores one scene. With `renders`, each target's render [h, w, 3] is appended (for pictures): with true_cameras the
// renders of the decoder given the ground-truth input cameras, which psnr_true_cameras / ssim_true_cameras score.
template <class T>
ValidationScore validate_scene(ValidationWorkspace<T>& ws, const FlexSplatWeights<T>& w, const TrainExample<T>& e,
                               std::vector<Tensor<T, 3>>* renders = nullptr, bool true_cameras = false) {
  require(e.targets >= 1, "validation: the scene has no target views");
  ValidationScore s;
  s.views = e.views, s.targets = e.targets;
  if (true_cameras) {
    const BeforeDecoder<T> given = [&](GeometryResult<T>& g) {
      std::copy(e.gt_extrinsics.begin(), e.gt_extrinsics.end(), g.extrinsics.begin());
      std::copy(e.gt_K.begin(), e.gt_K.end(), g.K.begin());
    };
    const Prediction<T> t = predict(ws.predict, w, e.images.data(), e.views, 0, given);
    const std::array<double, 2> score = detail::score_targets(ws, t.gaussians, e, renders);
    s.psnr_true_cameras = score[0], s.ssim_true_cameras = score[1];
  }
  const Prediction<T> p = predict(ws.predict, w, e.images.data(), e.views);
  const std::array<double, 2> score = detail::score_targets(ws, p.gaussians, e, true_cameras ? nullptr : renders);
  s.psnr = score[0], s.ssim = score[1];
  const index_t px = e.h * e.w;
  const index_t V = e.views;
  std::vector<double> pred(static_cast<std::size_t>(12 * V)), gt(pred.size());
  for (std::size_t i = 0; i < pred.size(); ++i)
    pred[i] = static_cast<double>(p.geometry.extrinsics[i]), gt[i] = static_cast<double>(e.gt_extrinsics[i]);
  detail::score_rotations(pred.data(), gt.data(), V, s.rotation_deg, s.rra15, s.rra30);
  const auto& head = ws.predict.geometry.outputs.extrinsics;  // before predict's matched or searched cameras
  for (std::size_t i = 0; i < pred.size(); ++i) pred[i] = static_cast<double>(head.data()[i]);
  detail::score_rotations(pred.data(), gt.data(), V, s.head_rotation_deg, s.head_rra15, s.head_rra30);
  for (index_t v = 1; v < V; ++v) s.chance_rotation_deg += rotation_error_deg(gt.data(), gt.data() + 12 * v) / static_cast<double>(V - 1);
  if (w.config().geometry.point_head) {
    const auto& o = ws.predict.geometry.outputs;
    std::vector<T> solved(static_cast<std::size_t>(12 * V));
    geometry::cameras_from_points<T>(solved.data(), o.points.data(), o.points_conf.data(), o.depth.data(),
                                     o.intrinsics.data(), V, e.h, e.w);
    for (std::size_t i = 0; i < pred.size(); ++i) pred[i] = static_cast<double>(solved[i]);
    detail::score_rotations(pred.data(), gt.data(), V, s.points_rotation_deg, s.points_rra15, s.points_rra30);
  }
  if (w.config().geometry.match_dim > 0) {
    // predict's matched cameras; a view no match placed counts as the first view's camera, not the camera head's.
    for (std::size_t i = 0; i < pred.size(); ++i) pred[i] = static_cast<double>(p.geometry.extrinsics[i]);
    for (index_t v = 1; v < V; ++v)
      if (p.camera_matches[static_cast<std::size_t>(v)] == 0)
        std::copy_n(identity_w2c, 12, pred.begin() + 12 * v);
    detail::score_rotations(pred.data(), gt.data(), V, s.matches_rotation_deg, s.matches_rra15, s.matches_rra30);
    const auto& o = ws.predict.geometry.outputs;
    const index_t D = w.config().geometry.match_dim;
    std::vector<T> solved(static_cast<std::size_t>(12 * V));
    std::vector<std::size_t> pair_bin(static_cast<std::size_t>(V * V));  // each view pair's true baseline bin
    for (index_t a = 0; a < V; ++a)
      for (index_t b = 0; b < V; ++b)
        pair_bin[static_cast<std::size_t>(a * V + b)] = baseline_bin(rotation_error_deg(gt.data() + 12 * a, gt.data() + 12 * b));
    std::vector<geometry::PairFit> pair_fits;
    geometry::cameras_from_matches<T>(solved.data(), o.descriptors.data(), o.foreground.data(), e.gt_depth.data(),
                                      o.intrinsics.data(), V, e.h, e.w, D, nullptr, nullptr, {}, &pair_fits);
    for (index_t a = 0; a < V; ++a)
      for (index_t b = a + 1; b < V; ++b) {
        const geometry::PairFit& f = pair_fits[static_cast<std::size_t>(a * V + b)];
        double fit_b[12];  // the fit as view b's camera with view a at the identity
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 4; ++c) fit_b[4 * r + c] = c < 3 ? f.R[3 * r + c] : f.t[r];
        const double err = relative_rotation_error_deg(identity_w2c, fit_b, gt.data() + 12 * a, gt.data() + 12 * b);
        const std::size_t bin = pair_bin[static_cast<std::size_t>(a * V + b)];
        s.pairs_by_baseline[bin] += 1;
        s.pairs_within15_by_baseline[bin] += f.inliers >= geometry::MatchFitConfig{}.min_inliers && err <= 15;
      }
    for (std::size_t i = 0; i < pred.size(); ++i) pred[i] = static_cast<double>(solved[i]);
    double unused15, unused30;
    detail::score_rotations(pred.data(), gt.data(), V, s.matches_gt_depth_rotation_deg, unused15, unused30);
    std::vector<T> K(e.gt_K.size());
    intrinsics_to_vggt(K.data(), e.gt_K.data(), V);
    geometry::cameras_from_correspondences<T, loss::PixelMatch>(solved.data(), std::span<const loss::PixelMatch>(e.matches),
                                                                e.gt_depth.data(), K.data(), V, e.h, e.w);
    for (std::size_t i = 0; i < pred.size(); ++i) pred[i] = static_cast<double>(solved[i]);
    detail::score_rotations(pred.data(), gt.data(), V, s.matches_oracle_rotation_deg, s.matches_oracle_rra15, unused30);
    const std::span<const loss::PixelMatch> matches(e.matches);
    const std::vector<index_t> nearest = loss::nearest_descriptor_pixels(o.descriptors.data(), matches, V, e.h, e.w, D);
    if (!matches.empty()) {
      const double count = static_cast<double>(matches.size());
      s.match_accuracy = loss::match_hits(nearest, matches, e.w, 1) / count;
      s.match_accuracy_4px = loss::match_hits(nearest, matches, e.w, 4) / count;
    }
    for (std::size_t i = 0; i < matches.size(); ++i) {
      const std::size_t bin = pair_bin[static_cast<std::size_t>(matches[i].view_a * V + matches[i].view_b)];
      s.matches_by_baseline[bin] += 1;
      s.match_hits_by_baseline[bin] += loss::within_pixels(nearest[i], matches[i].pixel_b, e.w, 1);
    }
  }
  double err = 0;
  index_t n = 0;
  for (std::size_t i = 0; i < e.gt_depth.size(); ++i)
    if (e.gt_depth[i] > T(0)) {
      err += std::abs(static_cast<double>(p.geometry.depth[i]) - static_cast<double>(e.gt_depth[i])) /
             static_cast<double>(e.gt_depth[i]);
      ++n;
    }
  s.depth_rel = n > 0 ? err / static_cast<double>(n) : 0.0;
  s.depth_shape_rel = loss::depth_scaled_error(p.geometry.depth.data(), e.gt_depth.data(), V, px);
  return s;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
