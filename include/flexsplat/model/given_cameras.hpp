#pragma once
// A capture's own cameras (io/capture_cameras.hpp) handed to the model in place of its predicted ones. The model works
// in its frame (first input camera = identity, lengths in its predicted depth's units); the capture's world has its
// own origin and scale. The frame is the first camera's; the scale is the one at which every view's predicted depth,
// unprojected through the given cameras, lands inside the other views' silhouettes and on their surfaces (the orbit
// search's objective, solvers/orbit_search.hpp, minimised over the scale alone). One view cannot tell a scale: its
// object is taken to lie where the optical axis passes nearest the world origin. The prediction is brought back to the
// capture's world afterwards (to_capture_world), so that a held-out camera of the same capture sees the splat in place.
//
//   GivenCameras<float> gc = given_cameras<float>(rgba, cams, config);   // cams: io::cameras_for_images(...)
//   ws.cameras = CameraSource::given; ws.given = gc;  Prediction<float> p = predict(ws, weights, images);
//   to_capture_world(p);                                                  // Gaussians and cameras in the capture's frame
#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/solvers/orbit_search.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/model/frames.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// The scale search's grid: the first guess times 2^(k / steps_per_octave) for |k| <= octaves * steps_per_octave.
inline constexpr int given_scale_octaves = 3;
inline constexpr int given_scale_steps_per_octave = 16;

template <class T>
struct GivenCameras {  // T: the model's scalar, which the scale search reads its maps in
  std::vector<double> K;    // [V, 3, 3] at the model's size, pixel centres at +0.5 (through each photo's window)
  std::vector<double> w2c;  // [V, 3, 4] world-to-camera in the capture's world and units
  index_t views() const { return static_cast<index_t>(w2c.size() / 12); }
};

// How the capture's world maps to the model's frame: world-to-camera matrices go through `frame` (FirstCameraFrame);
// `cost` is the consistency objective at the chosen scale, `from_views` false when one view (or views without a
// silhouette) left the scale to the world origin's distance.
struct GivenFrame {
  FirstCameraFrame frame;
  double cost = 0;
  bool from_views = false;
};

// The model-frame world-to-camera [V, 3, 4] of the given cameras at `scale` (world lengths / scale = model lengths).
inline std::vector<double> given_model_extrinsics(const std::vector<double>& w2c, double scale) {
  FirstCameraFrame f;
  f.first_w2c = to_matrix4(w2c.data());
  f.scale = scale;
  std::vector<double> out = w2c;
  for (std::size_t v = 0; v < out.size() / 12; ++v) f.camera(out.data() + 12 * v);
  return out;
}

// The frame and scale of the given cameras for a prediction's depth [V, h, w] (model units) and the model's input
// images [V, 3, h, w]. foreground [V, h, w]: object probability (the photos' alpha, else a match head's, else null:
// every pixel is object).
template <class T>
GivenFrame given_frame(const GivenCameras<T>& gc, const T* images, const T* depth, const T* foreground, index_t h,
                       index_t w) {
  const index_t V = gc.views();
  require(V >= 1 && gc.K.size() == static_cast<std::size_t>(9 * V), "given cameras: ", gc.K.size() / 9,
          " intrinsics for ", V, " world-to-cameras");
  std::vector<T> ones;
  if (!foreground) {
    ones.assign(static_cast<std::size_t>(V * h * w), T(1));
    foreground = ones.data();
  }
  // The first view's median depth on its object pixels: the model's distance to the object.
  std::vector<double> d0;
  for (index_t i = 0; i < h * w; ++i)
    if (foreground[i] >= T(0.5) && depth[i] > T(0)) d0.push_back(static_cast<double>(depth[i]));
  require(!d0.empty(), "given cameras: the first view shows no object (no pixel with alpha >= 0.5 and positive "
          "predicted depth)");
  std::nth_element(d0.begin(), d0.begin() + static_cast<std::ptrdiff_t>(d0.size() / 2), d0.end());
  const double model_distance = d0[d0.size() / 2];
  // The world distance along the first axis to the point nearest every axis (the decoder's query centre), or to the
  // point nearest the world origin when the axes do not pin one down.
  const Eigen::Matrix4d E0 = to_matrix4(gc.w2c.data());
  const Eigen::Vector3d c0 = -E0.block<3, 3>(0, 0).transpose() * E0.block<3, 1>(0, 3);
  const Eigen::Vector3d a0 = E0.block<3, 3>(0, 0).row(2).transpose();
  Eigen::Vector3d target = Eigen::Vector3d::Zero();
  bool from_axes = false;
  if (V >= 2) {
    const double no_depth = 1;  // the axes alone decide; the fallback's depth is not used
    const decoder::ViewGeometry<double> g{V, 1, 1, 1, 1, gc.K.data(), gc.w2c.data(), &no_depth};
    const decoder::SceneCentre sc = decoder::scene_centre_from_axes(g);
    if (sc.from_axes) target = Eigen::Vector3d(sc.centre[0], sc.centre[1], sc.centre[2]), from_axes = true;
  }
  const double world_distance = a0.dot(target - c0);
  require(world_distance > 0 && std::isfinite(world_distance), "given cameras: the first camera looks away from ",
          from_axes ? "the point its views' optical axes meet" : "the world origin", " (distance ", world_distance,
          " along its axis); with one view the object must lie on the world origin's side of the camera");
  const double guess = world_distance / model_distance;
  GivenFrame out;
  out.frame.first_w2c = E0;
  out.frame.scale = guess;
  if (V < 2) return out;
  // 1-D search of the consistency objective over the scale, on a log grid around the guess, then a golden section.
  // The depth as given (no depth range): a range would let every point absorb a scale error of its size.
  const geometry::OrbitSearchConfig cfg;
  std::vector<T> K_int(static_cast<std::size_t>(9 * V)), E(static_cast<std::size_t>(12 * V));
  for (std::size_t i = 0; i < K_int.size(); ++i) K_int[i] = static_cast<T>(gc.K[i]);
  intrinsics_to_vggt(K_int.data(), std::vector<T>(K_int).data(), V);
  auto cost = [&](double log_scale) {
    const std::vector<double> m = given_model_extrinsics(gc.w2c, std::exp(log_scale));
    std::transform(m.begin(), m.end(), E.begin(), [](double x) { return static_cast<T>(x); });
    return geometry::orbit_search_cost<T>(E.data(), images, foreground, depth, K_int.data(), V, h, w, cfg);
  };
  const double step = std::log(2.0) / given_scale_steps_per_octave;
  const int n = given_scale_octaves * given_scale_steps_per_octave;
  double best = std::log(guess), best_cost = cost(best);
  for (int k = -n; k <= n; ++k) {
    const double ls = std::log(guess) + k * step, c = cost(ls);
    if (c < best_cost) best = ls, best_cost = c;
  }
  double lo = best - step, hi = best + step;
  const double phi = 0.5 * (std::sqrt(5.0) - 1.0);
  double x1 = hi - phi * (hi - lo), x2 = lo + phi * (hi - lo), f1 = cost(x1), f2 = cost(x2);
  for (int it = 0; it < 20; ++it) {
    if (f1 < f2) hi = x2, x2 = x1, f2 = f1, x1 = hi - phi * (hi - lo), f1 = cost(x1);
    else lo = x1, x1 = x2, f1 = f2, x2 = lo + phi * (hi - lo), f2 = cost(x2);
  }
  const double xm = f1 < f2 ? x1 : x2, fm = std::min(f1, f2);
  if (fm < best_cost) best = xm, best_cost = fm;
  out.frame.scale = std::exp(best);
  out.cost = best_cost;
  out.from_views = true;
  return out;
}

// The given cameras in the model's frame written into a prediction's geometry (K at the model's size, w2c).
template <class T>
void place_given_cameras(const GivenCameras<T>& gc, const GivenFrame& f, T* K, T* w2c) {
  std::vector<double> E = gc.w2c;
  for (std::size_t v = 0; v < E.size() / 12; ++v) f.frame.camera(E.data() + 12 * v);
  std::transform(E.begin(), E.end(), w2c, [](double x) { return static_cast<T>(x); });
  std::transform(gc.K.begin(), gc.K.end(), K, [](double x) { return static_cast<T>(x); });
}

// The similarity from the model's frame to the capture's world: x_world = R0^T (scale x - t0).
inline Similarity model_to_world(const FirstCameraFrame& f) {
  Similarity s;
  const Eigen::Matrix3d R0 = f.first_w2c.block<3, 3>(0, 0);
  s.R = R0.transpose();
  s.scale = f.scale;
  s.t = -R0.transpose() * f.first_w2c.block<3, 1>(0, 3);
  return s;
}

// A Gaussian set from the model's frame to the capture's world.
template <class T>
void gaussians_to_world(GaussianSet<T>& set, const FirstCameraFrame& f) {
  const Similarity s = model_to_world(f);
  glm::dmat3 R;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) R[c][r] = s.R(r, c);
  transform_gaussians(set, R, glm::dvec3(s.t(0), s.t(1), s.t(2)), s.scale);
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
