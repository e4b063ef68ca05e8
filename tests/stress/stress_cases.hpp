#pragma once
// Numerical stress of every stage with random extreme inputs (docs/reliability.md, "Numerical stress"): each case
// must give finite outputs and gradients, or end in a flexsplat::Error when its input is invalid. Shared by the
// program bench/stress.cpp (--cases N per stage) and the small sample in tests/stress/test_stress.cpp.
//
// Stages and what a case draws:
//   raster    1-64 Gaussians, images 1-48 px: scales 0 and log-uniform in [1e-30, 1e30], quaternions random, tiny,
//             huge, zero or NaN, means on the camera centre, at / behind the near plane or far away, cameras behind
//             the object, focal lengths 1e-3..1e6; forward, then backward of random output cotangents (camera too).
//   decoder   the tiny decoder (UNet, fusion, 2 layers) on 1-4 views: images random, all white, all black or with a
//             NaN / Inf pixel, depth 0, negative or huge, intrinsics and extrinsics extreme; forward and backward.
//   geometry  the tiny VGGT forward on 1 or 8 views of 28 x 28 with the same image kinds.
//   model     model::scene_gradient at the tiny configuration on procedural scenes (1-4 views) with the same image
//             kinds, random stage settings (camera / depth terms, appearance, geometry frozen, 1-64 Gaussians).
// Invalid input (a non-finite pixel, a zero or non-finite quaternion) must be refused with an Error; an Error on a
// valid case is a failure too, as is any non-finite value, any other exception type.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/decoder/model.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/model/weights.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat_stress {

using flexsplat::index_t;

struct StageResult {
  std::string stage;
  long cases = 0, finite = 0, refused = 0, failures = 0;  // finite: ran and all values finite; refused: clear Error
  double seconds = 0;
  std::map<std::string, long> errors;    // refusal messages (first 80 characters) and their counts
  std::vector<std::string> failed;       // "case N: what"
};

// The verdict of one case: valid says whether its input was valid (an Error is then a failure).
struct Verdict {
  bool valid = true;
  std::string problem;  // non-empty: a non-finite value was found (names the tensor)
};

class Rng {
public:
  explicit Rng(std::uint64_t seed) : g_(seed) {}
  double uniform(double lo = 0, double hi = 1) { return std::uniform_real_distribution<double>(lo, hi)(g_); }
  double normal() { return std::normal_distribution<double>(0, 1)(g_); }
  int integer(int lo, int hi) { return std::uniform_int_distribution<int>(lo, hi)(g_); }
  bool chance(double p) { return uniform() < p; }
  double log_uniform(double lo, double hi) { return std::exp(uniform(std::log(lo), std::log(hi))); }
  std::uint64_t bits() { return g_(); }

private:
  std::mt19937_64 g_;
};

template <class T>
std::string first_nonfinite(const T* p, std::size_t n, const std::string& what) {
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(p[i])) return what + "[" + std::to_string(i) + "] = " + std::to_string(static_cast<double>(p[i]));
  return {};
}
template <class C>
std::string first_nonfinite(const C& c, const std::string& what) {
  return first_nonfinite(c.data(), static_cast<std::size_t>(c.size()), what);
}

// Runs `cases` cases of `one(rng, case, verdict)`, each from its own seed, and classifies them. The case sets
// verdict.valid before it runs the stage, so an Error is judged against it: a refusal of valid input is a failure.
inline StageResult run_stage(const std::string& stage, long cases, std::uint64_t seed,
                             const std::function<void(Rng&, long, Verdict&)>& one, long first = 0) {
  StageResult r;
  r.stage = stage;
  const auto start = std::chrono::steady_clock::now();
  for (long k = first; k < first + cases; ++k) {
    Rng rng(seed * 0x9E3779B97F4A7C15ull + static_cast<std::uint64_t>(k) * 0xD1B54A32D192ED03ull + 1);
    ++r.cases;
    Verdict v;
    const std::string at = "case " + std::to_string(k) + ": ";
    try {
      one(rng, k, v);
      if (!v.problem.empty()) {
        ++r.failures, r.failed.push_back(at + "non-finite " + v.problem);
      } else if (!v.valid) {
        ++r.failures, r.failed.push_back(at + "invalid input accepted without an error");
      } else {
        ++r.finite;
      }
    } catch (const flexsplat::Error& e) {
      if (v.valid) {
        ++r.failures, r.failed.push_back(at + "valid input refused: " + e.what());
      } else {
        ++r.refused;
        const std::string what = e.what();  // grouped by the message up to its first number
        const std::string m = what.substr(0, std::min(what.find_first_of("0123456789"), std::size_t(60))) + "...";
        ++r.errors[m];
      }
    } catch (const std::exception& e) {
      ++r.failures, r.failed.push_back(at + typeid(e).name() + ": " + e.what());
    }
  }
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return r;
}

// An input image batch [V, 3, h, w] in [0, 1] of one of the kinds every image-taking stage sees; returns whether it
// is valid (no NaN / Inf pixel).
template <class T>
bool fill_images(Rng& rng, std::vector<T>& images, index_t views, index_t h, index_t w, std::string* kind = nullptr) {
  images.assign(static_cast<std::size_t>(views * 3 * h * w), T(0));
  const int k = rng.integer(0, 5);
  const char* names[] = {"random", "white", "black", "NaN pixel", "Inf pixel", "constant grey"};
  if (kind) *kind = names[k];
  for (auto& v : images) v = k == 1 ? T(1) : k == 2 ? T(0) : k == 5 ? T(0.5) : static_cast<T>(rng.uniform());
  if (k == 3 || k == 4) {
    const std::size_t at = static_cast<std::size_t>(rng.integer(0, static_cast<int>(images.size()) - 1));
    images[at] = k == 3 ? std::numeric_limits<T>::quiet_NaN()
                        : (rng.chance(0.5) ? 1 : -1) * std::numeric_limits<T>::infinity();
    return false;
  }
  return true;
}

// ---------------------------------------------------------------------------------------------------------------
// raster
// ---------------------------------------------------------------------------------------------------------------

// A rotation from a random unit quaternion, as a row-major world_to_camera with the camera centre at `c`.
inline void look_from(Rng& rng, const double c[3], std::array<float, 16>& m) {
  double q[4] = {rng.normal(), rng.normal(), rng.normal(), rng.normal()};
  const double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) + 1e-300;
  for (double& x : q) x /= n;
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  const double R[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                       2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                       2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)};
  m = {};
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) m[static_cast<std::size_t>(4 * i + j)] = static_cast<float>(R[3 * i + j]);
    m[static_cast<std::size_t>(4 * i + 3)] = static_cast<float>(-(R[3 * i] * c[0] + R[3 * i + 1] * c[1] + R[3 * i + 2] * c[2]));
  }
  m[15] = 1;
}

inline void raster_case(Rng& rng, long, Verdict& v) {
  namespace raster = flexsplat::raster;
  const index_t n = rng.integer(1, 64);
  const int degree = rng.integer(0, 3);
  auto set = flexsplat::make_gaussian_set<float>(n, degree, rng.chance(0.3) ? rng.integer(1, 4) : 0);
  raster::View<float> cam;
  cam.width = rng.integer(1, 48), cam.height = rng.integer(1, 48);
  cam.fx = static_cast<float>(rng.log_uniform(1e-3, 1e6)), cam.fy = rng.chance(0.5) ? cam.fx : static_cast<float>(rng.log_uniform(1e-3, 1e6));
  cam.cx = static_cast<float>(rng.uniform(-1, 1) * cam.width), cam.cy = static_cast<float>(rng.uniform(-1, 1) * cam.height);
  // Mostly identity-like cameras looking down +z at the cloud; sometimes a random pose (object behind the camera).
  const double centre[3] = {0, 0, 0};
  if (rng.chance(0.3)) {
    const double c[3] = {rng.normal() * 3, rng.normal() * 3, rng.normal() * 3};
    look_from(rng, c, cam.world_to_camera);
  } else {
    look_from(rng, centre, cam.world_to_camera);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) cam.world_to_camera[static_cast<std::size_t>(4 * i + j)] = i == j ? 1.f : 0.f;
    cam.world_to_camera[3] = cam.world_to_camera[7] = cam.world_to_camera[11] = 0;
  }
  bool valid = true;
  const double near = raster::default_near;
  // At most one Gaussian per case gets a degenerate rotation (zero, NaN, or a length that under/overflows in float).
  const index_t odd = rng.chance(0.3) ? rng.integer(0, static_cast<int>(n) - 1) : -1;
  const int odd_kind = rng.integer(0, 2);
  for (index_t g = 0; g < n; ++g) {
    const int where = rng.integer(0, 7);
    double m[3] = {rng.normal(), rng.normal(), rng.uniform(0.5, 5)};
    switch (where) {
      case 0: m[0] = m[1] = m[2] = 0; break;                                   // on the camera centre
      case 1: m[2] = near * (1 + rng.uniform(-1e-3, 1e-3)); break;             // at the near plane
      case 2: m[2] = near * rng.uniform(-2, 1); break;                         // around / behind it
      case 3: m[2] = -rng.uniform(0.1, 10); break;                             // behind the camera
      case 4: for (double& x : m) x *= rng.log_uniform(1, 1e6); break;         // far away
      case 5: m[0] *= 1e-6, m[1] *= 1e-6, m[2] = rng.log_uniform(1e-6, 1e-1); break;  // tiny, close
      default: break;
    }
    for (int c = 0; c < 3; ++c) set.means(g, c) = static_cast<float>(m[c]);
    const int sk = rng.integer(0, 4);
    for (int c = 0; c < 3; ++c) {
      const double s = sk == 0 ? rng.log_uniform(1e-30, 1e30) : sk == 1 ? (rng.chance(0.5) ? 0.0 : 1e-30)
                     : sk == 2 ? rng.log_uniform(1e3, 1e30) : rng.log_uniform(1e-3, 1);
      set.scales(g, c) = static_cast<float>(s);
    }
    const int qk = g == odd ? odd_kind : 3;
    for (int c = 0; c < 4; ++c)
      set.quats(g, c) = static_cast<float>(qk == 0 ? rng.normal() * 1e-30 : qk == 1 ? rng.normal() * 1e30 : rng.normal());
    if (qk == 2) {  // degenerate: zero or NaN
      const bool nan = rng.chance(0.5);
      for (int c = 0; c < 4; ++c) set.quats(g, c) = nan && c == 0 ? std::numeric_limits<float>::quiet_NaN() : 0.f;
      valid = false;
    }
    if (qk == 0 || qk == 1) {  // length underflows to 0 or overflows in float: the renderer refuses it
      double len2 = 0;
      for (int c = 0; c < 4; ++c) len2 += static_cast<double>(set.quats(g, c)) * set.quats(g, c);
      const float f = static_cast<float>(len2);
      if (!(f > 0 && std::isfinite(f))) valid = false;
    }
    set.opacities(g) = static_cast<float>(rng.chance(0.2) ? (rng.chance(0.5) ? 0.0 : 1.0) : rng.uniform());
    for (index_t k = 0; k < set.sh.shape(1); ++k)
      for (int c = 0; c < 3; ++c) set.sh(g, k, c) = static_cast<float>(rng.normal() * (rng.chance(0.05) ? 1e6 : 1));
    for (index_t f = 0; f < (set.features.empty() ? 0 : set.features.shape(1)); ++f)
      set.features(g, f) = static_cast<float>(rng.normal());
  }
  raster::RenderOptions opt;
  opt.antialiased = rng.chance(0.5);
  opt.expected_depth = rng.chance(0.5);
  opt.background = {rng.uniform(), rng.uniform(), rng.uniform()};
  raster::RenderWorkspace<float> ws;
  raster::RenderOutputs<float> out;
  v.valid = valid;
  if (!valid) {
    raster::render_forward(set, cam, opt, ws, out);  // must throw
    return;
  }
  raster::render_forward(set, cam, opt, ws, out);
  for (auto p : {first_nonfinite(out.image, "image"), first_nonfinite(out.alpha, "alpha"), first_nonfinite(out.depth, "depth"),
                 first_nonfinite(out.features, "features")})
    if (!p.empty()) return void(v.problem = p);
  flexsplat::Tensor<float, 3> d_image(out.image.shape()), d_features(out.features.shape());
  flexsplat::Tensor<float, 2> d_alpha(out.alpha.shape()), d_depth(out.depth.shape());
  for (auto* t : {&d_image, &d_features})
    for (float& x : t->span()) x = static_cast<float>(rng.normal());
  for (auto* t : {&d_alpha, &d_depth})
    for (float& x : t->span()) x = static_cast<float>(rng.normal());
  auto grads = flexsplat::make_gaussian_grad(set);
  raster::ViewGrad<float> d_cam;
  raster::render_backward(set, cam, opt, ws,
                          raster::RenderOutputGrads<float>{d_image.view(), d_alpha.view(), d_depth.view(), d_features.view()},
                          grads, &d_cam);
  for (auto p : {first_nonfinite(grads.means, "d_means"), first_nonfinite(grads.quats, "d_quats"),
                 first_nonfinite(grads.scales, "d_scales"), first_nonfinite(grads.opacities, "d_opacities"),
                 first_nonfinite(grads.sh, "d_sh"), first_nonfinite(grads.features, "d_features"),
                 first_nonfinite(d_cam.world_to_camera, "d_world_to_camera")})
    if (!p.empty()) return void(v.problem = p);
  const float dk[4] = {d_cam.fx, d_cam.fy, d_cam.cx, d_cam.cy};
  v.problem = first_nonfinite(dk, 4, "d_intrinsics");
}

// ---------------------------------------------------------------------------------------------------------------
// decoder
// ---------------------------------------------------------------------------------------------------------------

struct DecoderRig {
  flexsplat::decoder::ModelConfig cfg;
  std::vector<float> params;
  flexsplat::decoder::ModelWorkspace<float> ws;
  DecoderRig() {
    cfg.unet = {3, 2, 1};
    cfg.fusion = {3, 2, 3};
    auto& d = cfg.decoder;
    d.dim = 8, d.ffn = 12, d.heads = 2, d.layers = 2, d.points = 2, d.max_views = 4, d.value_dim = 3, d.max_queries = 64;
    params.resize(static_cast<std::size_t>(flexsplat::decoder::ModelParamLayout(cfg).size));
  }
};

inline void decoder_case(DecoderRig& rig, Rng& rng, long k, Verdict& v) {
  namespace decoder = flexsplat::decoder;
  const auto& cfg = rig.cfg;
  decoder::model_init(rig.params.data(), cfg, static_cast<std::uint64_t>(k));
  const double noise = rng.chance(0.2) ? rng.log_uniform(1, 100) : 0.1;
  for (float& p : rig.params) p += static_cast<float>(rng.normal() * noise * 0.1);
  const index_t V = rng.integer(1, 4), h = rng.integer(4, 16), w = rng.integer(4, 16), dh = rng.integer(1, 8),
                dw = rng.integer(1, 8), n = rng.integer(1, 64);
  std::vector<float> images, feats(static_cast<std::size_t>(V * 3 * dh * dw)), K, E, depth;
  v.valid = fill_images(rng, images, V, h, w);
  for (float& f : feats) f = static_cast<float>(rng.normal() * (rng.chance(0.05) ? 1e4 : 1));
  for (index_t i = 0; i < V; ++i) {
    const double f = rng.log_uniform(1e-2, 1e5);
    const float k9[9] = {static_cast<float>(f), 0, static_cast<float>(rng.uniform(-1, 2) * w), 0,
                         static_cast<float>(f * rng.log_uniform(0.1, 10)), static_cast<float>(rng.uniform(-1, 2) * h), 0, 0, 1};
    K.insert(K.end(), k9, k9 + 9);
    std::array<float, 16> m;
    const double r = rng.chance(0.2) ? rng.log_uniform(1e-4, 1e4) : 2.5;
    const double c[3] = {rng.normal() * r, rng.normal() * r, rng.normal() * r};
    look_from(rng, c, m);
    E.insert(E.end(), m.begin(), m.begin() + 12);
    const int dk = rng.integer(0, 4);
    for (index_t p = 0; p < dh * dw; ++p)
      depth.push_back(static_cast<float>(dk == 0 ? 0.0 : dk == 1 ? -rng.uniform(0, 5) : dk == 2 ? rng.log_uniform(1e-6, 1e6)
                                                                                           : rng.uniform(0.5, 5)));
  }
  const decoder::ViewGeometry<float> g{V, w, h, dw, dh, K.data(), E.data(), depth.data()};
  decoder::model_forward(rig.ws, n, rig.params.data(), cfg, images.data(), h, w, feats.data(), dh, dw, g);
  if (!v.valid) return;  // reaching here with a NaN / Inf pixel is the failure
  for (std::size_t s = 0; s < rig.ws.gaussians().size(); ++s) {
    const auto& set = rig.ws.gaussians()[s];
    const std::string at = "layer " + std::to_string(s) + " ";
    for (auto p : {first_nonfinite(set.means, at + "means"), first_nonfinite(set.quats, at + "quats"),
                   first_nonfinite(set.scales, at + "scales"), first_nonfinite(set.opacities, at + "opacities"),
                   first_nonfinite(set.sh, at + "sh")})
      if (!p.empty()) return void(v.problem = p);
  }
  if (auto p = first_nonfinite(rig.ws.rgb, "rgb"); !p.empty()) return void(v.problem = p);
  std::vector<flexsplat::GaussianSetGrad<float>> dg;
  for (const auto& set : rig.ws.gaussians()) {
    dg.push_back(flexsplat::make_gaussian_grad(set));
    for (auto* t : {&dg.back().means, &dg.back().quats, &dg.back().scales})
      for (float& x : t->span()) x = static_cast<float>(rng.normal());
    for (float& x : dg.back().opacities.span()) x = static_cast<float>(rng.normal());
    for (float& x : dg.back().sh.span()) x = static_cast<float>(rng.normal());
  }
  std::vector<float> d_rgb(rig.ws.rgb.size()), dp(rig.params.size()), dfeat(feats.size()), dK(K.size()), dE(E.size()),
      dD(depth.size());
  for (float& x : d_rgb) x = static_cast<float>(rng.normal());
  decoder::model_backward(dp.data(), dfeat.data(), {dK.data(), dE.data(), dD.data()}, dg, d_rgb.data(), rig.ws,
                          rig.params.data(), cfg, images.data(), feats.data(), g);
  for (auto p : {first_nonfinite(dp, "d_params"), first_nonfinite(dfeat, "d_depth_features"), first_nonfinite(dK, "d_K"),
                 first_nonfinite(dE, "d_world_to_camera"), first_nonfinite(dD, "d_depth")})
    if (!p.empty()) return void(v.problem = p);
}

// ---------------------------------------------------------------------------------------------------------------
// geometry and the whole model (tiny configuration)
// ---------------------------------------------------------------------------------------------------------------

struct ModelRig {
  flexsplat::model::FlexSplatConfig cfg = flexsplat::model::flexsplat_tiny_config();
  std::unique_ptr<flexsplat::model::FlexSplatWeights<float>> w = flexsplat::model::FlexSplatWeights<float>::create(cfg, true);
  flexsplat::geometry::VggtWorkspace<float> vggt_ws;
  flexsplat::model::SceneWorkspace<float> scene_ws;
  std::vector<flexsplat::model::TrainExample<float>> scenes;  // procedural, 1-4 views, made once
  ModelRig() {
    flexsplat::data::GeneratorConfig g;
    g.size = static_cast<int>(cfg.image_h);
    g.supersample = 1;
    for (int views = 1; views <= cfg.appearance.decoder.max_views; ++views)
      for (int targets : {0, 2}) {
        flexsplat::data::BatchOptions o;
        o.inputs = views, o.targets = targets, o.structured_inputs = false;
        scenes.push_back(flexsplat::model::make_train_example<float>(
            flexsplat::data::generate_batch(g, 1, 11, static_cast<std::uint64_t>(views * 3 + targets), o)[0], cfg));
      }
  }
};

inline void geometry_case(ModelRig& rig, Rng& rng, long k, Verdict& v) {
  rig.w->init(static_cast<std::uint64_t>(k));
  const index_t V = rng.chance(0.5) ? 1 : 8, h = rig.cfg.image_h, w = rig.cfg.image_w;
  std::vector<float> images;
  v.valid = fill_images(rng, images, V, h, w);
  const auto out = flexsplat::geometry::vggt_forward(images.data(), V, h, w, rig.cfg.geometry, rig.w->geometry(), rig.vggt_ws);
  if (!v.valid) return;
  for (auto p : {first_nonfinite(out.pose_enc, "pose_enc"), first_nonfinite(out.extrinsics, "extrinsics"),
                 first_nonfinite(out.intrinsics, "intrinsics"), first_nonfinite(out.depth, "depth"),
                 first_nonfinite(out.depth_conf, "depth_conf"), first_nonfinite(out.world_points, "world_points")})
    if (!p.empty()) return void(v.problem = p);
}

inline void model_case(ModelRig& rig, Rng& rng, long k, Verdict& v) {
  rig.w->init(static_cast<std::uint64_t>(k));
  flexsplat::model::TrainExample<float> e = rig.scenes[static_cast<std::size_t>(rng.integer(0, static_cast<int>(rig.scenes.size()) - 1))];
  std::vector<float> images;
  v.valid = fill_images(rng, images, e.views, e.h, e.w);
  const int kind = rng.integer(0, 2);  // keep the scene's pixels, or replace the inputs, or the inputs and targets
  if (kind > 0 || !v.valid) {
    e.images = images;
    const index_t px = e.h * e.w;
    for (index_t i = 0; i < e.views; ++i)
      for (index_t p = 0; p < px; ++p)
        for (int c = 0; c < 3; ++c) e.inputs_hwc[static_cast<std::size_t>((i * px + p) * 3 + c)] = images[static_cast<std::size_t>((i * 3 + c) * px + p)];
    if (kind == 2)
      for (std::size_t i = 0; i < e.target_images.size(); ++i) e.target_images[i] = images[i % images.size()];
  }
  flexsplat::model::StepConfig sc;
  sc.camera_weight = rng.chance(0.5) ? rng.uniform(0, 2) : 0;
  sc.depth_weight = rng.chance(0.5) ? rng.uniform(0, 2) : 0;
  sc.appearance = rng.chance(0.8) || (sc.camera_weight == 0 && sc.depth_weight == 0);
  sc.train_geometry = rng.chance(0.8) || !sc.appearance;
  sc.gaussians = rng.integer(1, static_cast<int>(rig.cfg.appearance.decoder.max_queries));
  auto& store = rig.w->store();
  store.zero_grads();
  const auto r = flexsplat::model::scene_gradient(rig.scene_ws, *rig.w, store.grads(), e, sc);
  if (!v.valid) return;
  const double parts[8] = {r.loss, r.camera, r.depth, r.rgb_head, r.render, r.render_depth, r.lpips, r.psnr};
  if (auto p = first_nonfinite(parts, 8, "loss parts (loss, camera, depth, rgb_head, render, render_depth, lpips, psnr)");
      !p.empty())
    return void(v.problem = p);
  v.problem = first_nonfinite(store.grads(), static_cast<std::size_t>(store.size()), "parameter gradient");
  if (!v.problem.empty()) {
    const auto i = std::stol(v.problem.substr(v.problem.find('[') + 1));
    for (const auto& t : store.tensors())
      if (i >= t.offset && i < t.offset + t.numel) v.problem += " (" + t.name + ")";
  }
}

// Every stage, cases [first, first + cases) each, from `seed`; `only` (if non-empty) picks one stage.
inline std::vector<StageResult> run_all(long cases, std::uint64_t seed, const std::string& only = {}, long first = 0) {
  std::vector<StageResult> out;
  if (only.empty() || only == "raster") out.push_back(run_stage("raster", cases, seed, raster_case, first));
  if (only.empty() || only == "decoder") {
    DecoderRig rig;
    out.push_back(run_stage(
        "decoder", cases, seed, [&](Rng& r, long k, Verdict& v) { decoder_case(rig, r, k, v); }, first));
  }
  if (only.empty() || only == "geometry" || only == "model") {
    ModelRig rig;
    if (only.empty() || only == "geometry")
      out.push_back(run_stage(
          "geometry", cases, seed, [&](Rng& r, long k, Verdict& v) { geometry_case(rig, r, k, v); }, first));
    if (only.empty() || only == "model")
      out.push_back(run_stage(
          "model", cases, seed, [&](Rng& r, long k, Verdict& v) { model_case(rig, r, k, v); }, first));
  }
  return out;
}

}  // namespace flexsplat_stress
