// Whether the decoder's renders of its own input views tell right cameras from wrong ones (analysis by synthesis).
// Random input view sets of the object folders (views drawn from all frames, in random order):
// - without --search: the folder's true input cameras (model::true_input_cameras, in the predicted depth's units),
//   each turned by D degrees (model::rotation_noise), handed to the decoder; the mean squared error of its renders of
//   the input views against the input pictures, all views decoded, and with each view left out of the decoder (the
//   others keep the geometry predicted from all views).
// - --search all|loo: the orbit-searched cameras (what predict gives) refined by a pattern search over each view's
//   rotation and centre (views 2..V) on that error (all: all views decoded; loo: plus each view left out), then the
//   eval's rotation error and PSNR on 4 other frames before and after.
// Usage: render_consistency --model M.safetensors [--counts 2,4] [--sets 2] [--seed 7] [--noise 0,5,10,15,30]
//                           [--draws 3] [--search all|loo] [--max-evals 400] OBJECT_DIR...
#include <algorithm>
#include <chrono>
#include <cmath>
#include <numbers>
#include <numeric>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/model/weights.hpp"
#include "flexsplat/raster/render.hpp"

#include <Eigen/Geometry>

using namespace flexsplat;

namespace {
std::vector<double> parse_list(const std::string& s) {
  std::vector<double> out;
  std::size_t at = 0;
  while (at < s.size()) {
    const std::size_t comma = s.find(',', at);
    out.push_back(std::stod(s.substr(at, comma == std::string::npos ? std::string::npos : comma - at)));
    if (comma == std::string::npos) break;
    at = comma + 1;
  }
  return out;
}

// Mean squared error of the Gaussians rendered from camera (K, E) at h x w on white against image [3, h, w].
double render_mse(const GaussianSet<float>& g, const float* K, const float* E, const float* image, index_t h,
                  index_t w, raster::RenderWorkspace<float>& rws, raster::RenderOutputs<float>& out) {
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  raster::render_forward(g, raster::view_from_arrays(K, E, static_cast<int>(w), static_cast<int>(h)), ro, rws, out);
  double sum = 0;
  for (index_t y = 0; y < h; ++y)
    for (index_t x = 0; x < w; ++x)
      for (index_t c = 0; c < 3; ++c) {
        const double d = out.image.data()[(y * w + x) * 3 + c] - image[(c * h + y) * w + x];
        sum += d * d;
      }
  return sum / static_cast<double>(3 * h * w);
}

// The decoder's Gaussians for the views `keep` of a prediction's geometry g with extrinsics E [V, 3, 4].
const GaussianSet<float>& decode(model::PredictWorkspace<float>& ws, const model::FlexSplatWeights<float>& w,
                                 const model::GeometryResult<float>& g, const float* images, const float* E,
                                 const std::vector<index_t>& keep) {
  const model::FlexSplatConfig& c = w.config();
  const index_t h = g.h, wd = g.w, k = static_cast<index_t>(keep.size()), px = 3 * h * wd;
  const index_t fs = g.feature_channels * g.feature_h * g.feature_w;
  std::vector<float> im, feat, K, Es, depth;
  for (index_t v : keep) {
    im.insert(im.end(), images + v * px, images + (v + 1) * px);
    feat.insert(feat.end(), g.features.data() + v * fs, g.features.data() + (v + 1) * fs);
    K.insert(K.end(), g.K.data() + 9 * v, g.K.data() + 9 * v + 9);
    Es.insert(Es.end(), E + 12 * v, E + 12 * v + 12);
    depth.insert(depth.end(), g.depth.data() + v * h * wd, g.depth.data() + (v + 1) * h * wd);
  }
  ws.model.keep_for_backward = false;
  const decoder::ViewGeometry<float> vg{k, wd, h, wd, h, K.data(), Es.data(), depth.data()};
  decoder::model_forward(ws.model, c.gaussians_for(k), w.appearance(), c.appearance, im.data(), h, wd, feat.data(),
                         g.feature_h, g.feature_w, vg);
  return ws.model.gaussians().back();
}

// Render consistency of extrinsics E: the mean over the views of the MSE of their renders with all views decoded,
// and (with `loo`) the same with each view left out of the decoder (the others' geometry as predicted with it).
struct Consistency {
  double all_in = 0, left_out = 0;
};
Consistency consistency(model::PredictWorkspace<float>& ws, const model::FlexSplatWeights<float>& w,
                        const model::GeometryResult<float>& g, const float* images, const float* E, bool loo,
                        raster::RenderWorkspace<float>& rws, raster::RenderOutputs<float>& out) {
  const index_t V = g.views, h = g.h, wd = g.w, px = 3 * h * wd;
  std::vector<index_t> all(static_cast<std::size_t>(V));
  std::iota(all.begin(), all.end(), index_t(0));
  Consistency r;
  const GaussianSet<float>& gs = decode(ws, w, g, images, E, all);
  for (index_t v = 0; v < V; ++v) r.all_in += render_mse(gs, g.K.data() + 9 * v, E + 12 * v, images + v * px, h, wd, rws, out);
  if (loo && V >= 2)
    for (index_t leave = 0; leave < V; ++leave) {
      std::vector<index_t> keep;
      for (index_t v = 0; v < V; ++v)
        if (v != leave) keep.push_back(v);
      const GaussianSet<float>& q = decode(ws, w, g, images, E, keep);
      r.left_out += render_mse(q, g.K.data() + 9 * leave, E + 12 * leave, images + leave * px, h, wd, rws, out);
    }
  r.all_in /= static_cast<double>(V), r.left_out /= static_cast<double>(V);
  return r;
}

// The search's objective: the all-in error, plus with `loo` the left-out one.
double objective(const Consistency& c, bool loo) { return c.all_in + (loo ? c.left_out : 0.0); }

// Camera v of E turned by axis-angle (rx, ry, rz) radians (in its own frame) about its centre, and its centre moved
// by (cx, cy, cz) in the world: [R | t] -> [Q R | -Q R (c + dc)].
void perturb(float* E, const double* x) {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) R(i, j) = E[4 * i + j];
    t(i) = E[4 * i + 3];
  }
  const Eigen::Vector3d centre = -R.transpose() * t + Eigen::Vector3d(x[3], x[4], x[5]);
  const Eigen::Vector3d axis(x[0], x[1], x[2]);
  Eigen::Matrix3d Q = Eigen::Matrix3d::Identity();
  if (axis.norm() > 0) Q = Eigen::AngleAxisd(axis.norm(), axis.normalized()).toRotationMatrix();
  const Eigen::Matrix3d R2 = Q * R;
  const Eigen::Vector3d t2 = -R2 * centre;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) E[4 * i + j] = static_cast<float>(R2(i, j));
    E[4 * i + 3] = static_cast<float>(t2(i));
  }
}

// A random set of V input frames of rec (one shuffle of all its frames), the next 4 frames as targets, and the inputs
// at the model's size.
struct ViewSet {
  std::vector<int> in, targets;
  Tensor<float, 4> images;
  std::string name;
};
ViewSet draw_set(const data::ObjectRecord& rec, index_t V, std::mt19937& rng, const model::FlexSplatConfig& c) {
  std::vector<int> all(rec.frames.size());
  std::iota(all.begin(), all.end(), 0);
  std::shuffle(all.begin(), all.end(), rng);
  ViewSet set;
  set.in.assign(all.begin(), all.begin() + V);
  set.targets.assign(all.begin() + V, all.begin() + V + 4);
  std::vector<Tensor<float, 3>> rgba;
  for (int v : set.in) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
  set.images = model::model_input<float>(rgba, c);
  for (int v : set.in) set.name += (set.name.empty() ? "" : ",") + std::to_string(v);
  return set;
}
}  // namespace

int main(int argc, char** argv) {
  try {
    std::string model_path;
    std::vector<double> counts{2, 4}, noise{0, 5, 10, 15, 30};
    int sets = 2, draws = 3;
    unsigned seed = 7;
    std::string search;  // "", "all" or "loo": refine the orbit-searched cameras on that consistency
    int max_evals = 400;
    std::vector<std::filesystem::path> dirs;
    for (int i = 1; i < argc; ++i) {
      const std::string a = argv[i];
      const bool more = i + 1 < argc;
      if (a == "--model" && more) model_path = argv[++i];
      else if (a == "--counts" && more) counts = parse_list(argv[++i]);
      else if (a == "--noise" && more) noise = parse_list(argv[++i]);
      else if (a == "--sets" && more) sets = std::stoi(argv[++i]);
      else if (a == "--draws" && more) draws = std::stoi(argv[++i]);
      else if (a == "--search" && more) search = argv[++i];
      else if (a == "--max-evals" && more) max_evals = std::stoi(argv[++i]);
      else if (a == "--seed" && more) seed = static_cast<unsigned>(std::stoul(argv[++i]));
      else dirs.emplace_back(a);
    }
    require(!model_path.empty() && !dirs.empty(), "usage: render_consistency --model M.safetensors [--counts 2,4] "
            "[--sets 2] [--seed 7] [--noise 0,5,10,15,30] [--draws 3] [--search all|loo] [--max-evals 400] OBJECT_DIR...");
    require(search.empty() || search == "all" || search == "loo", "--search '", search,
            "' must be all or loo");
    require(sets >= 1 && draws >= 1 && max_evals >= 1, "--sets, --draws and --max-evals must be >= 1");
    for (double n : counts)
      require(n >= 1 && n <= 28 && n == std::floor(n), "view count ", n, " must be 1 to 28 (4 frames stay targets)");
    const auto w = model::load_flexsplat<float>(model_path);
    const model::FlexSplatConfig& c = w->config();
    const index_t h = c.image_h, wd = c.image_w;
    const std::vector<data::ObjectRecord> objects = data::load_objects(dirs);
    model::PredictWorkspace<float> ws;
    raster::RenderWorkspace<float> rws;
    raster::RenderOutputs<float> out;
    std::mt19937 rng(seed);

    if (!search.empty()) {
      const bool loo = search == "loo";
      std::printf("| views | object | set | orbit: rotation error | PSNR | consistency | refined: rotation error | PSNR | "
                  "consistency | evaluations | seconds |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
      std::vector<double> before, after;
      for (double count : counts) {
        const index_t V = static_cast<index_t>(count);
        before.clear(), after.clear();
        for (const data::ObjectRecord& rec : objects) {
          for (int s = 0; s < sets; ++s) {
            const ViewSet set = draw_set(rec, V, rng, c);
            const std::vector<int>& in = set.in;
            const std::vector<int>& targets = set.targets;
            const Tensor<float, 4>& images = set.images;
            const std::string& set_name = set.name;
            const auto t0 = std::chrono::steady_clock::now();
            ws.cameras = model::CameraSource::orbit_search;
            const model::Prediction<float> p = model::predict<float>(ws, *w, images.data(), V);
            ws.cameras = model::CameraSource::model;
            const model::GeometryResult<float>& g = p.geometry;
            std::vector<float> E(g.extrinsics.begin(), g.extrinsics.end());
            model::EvalOptions eo;
            model::EvalWorkspace ews;
            const model::EvalResult e0 = model::score_prediction(rec, in, targets, E.data(), p.gaussians, h, wd, eo, ews);
            double best = objective(consistency(ws, *w, g, images.data(), E.data(), loo, rws, out), loo);
            const double start = best;
            std::vector<double> depths(g.depth.begin(), g.depth.begin() + h * wd);
            std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
            const double unit = depths[depths.size() / 2];
            double rot_step = 8.0 * std::numbers::pi / 180.0, move_step = 0.1 * unit;
            int evals = 1;
            while (rot_step > 0.4 * std::numbers::pi / 180.0 && evals < max_evals) {
              bool improved = false;
              for (index_t v = 1; v < V && evals < max_evals; ++v)
                for (int k = 0; k < 6 && evals < max_evals; ++k)
                  for (double sign : {1.0, -1.0}) {
                    double x[6] = {0, 0, 0, 0, 0, 0};
                    x[k] = sign * (k < 3 ? rot_step : move_step);
                    std::vector<float> trial = E;
                    perturb(trial.data() + 12 * v, x);
                    const double f = objective(consistency(ws, *w, g, images.data(), trial.data(), loo, rws, out), loo);
                    ++evals;
                    if (f < best) {
                      best = f, E = trial, improved = true;
                      break;
                    }
                  }
              if (!improved) rot_step *= 0.5, move_step *= 0.5;
            }
            std::vector<index_t> every(static_cast<std::size_t>(V));
            std::iota(every.begin(), every.end(), index_t(0));
            const GaussianSet<float> final_set = decode(ws, *w, g, images.data(), E.data(), every);
            const model::EvalResult e1 = model::score_prediction(rec, in, targets, E.data(), final_set, h, wd, eo, ews);
            const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            before.push_back(e0.rotation_error_deg), after.push_back(e1.rotation_error_deg);
            std::printf("| %d | %s | %s | %.2f | %.2f | %.5f | %.2f | %.2f | %.5f | %d | %.1f |\n", static_cast<int>(V),
                        rec.name.c_str(), set_name.c_str(), e0.rotation_error_deg, e0.model.psnr, start,
                        e1.rotation_error_deg, e1.model.psnr, best, evals, secs);
            std::fflush(stdout);
          }
        }
        std::printf("views %d: median rotation error, orbit %.2f, refined %.2f (%zu sets)\n", static_cast<int>(V),
                    model::median_of(before), model::median_of(after), before.size());
      }
      return 0;
    }
    std::printf("| views | object | set | noise (deg) | draws | MSE, all views in | MSE, each view left out |\n"
                "|---|---|---|---|---|---|---|\n");
    for (double count : counts) {
      const index_t V = static_cast<index_t>(count);
      for (const data::ObjectRecord& rec : objects) {
        for (int s = 0; s < sets; ++s) {
          const ViewSet set = draw_set(rec, V, rng, c);
          const std::vector<int>& in = set.in;
          const Tensor<float, 4>& images = set.images;
          const std::string& set_name = set.name;
          for (double deg : noise) {
            double all_in = 0, left_out = 0;
            const int n_draws = deg > 0 ? draws : 1;
            for (int d = 0; d < n_draws; ++d) {
              const model::BeforeDecoder<float> cams = [&](model::GeometryResult<float>& g) {
                model::true_input_cameras(rec, in, g);
                if (deg > 0) model::rotation_noise(g.extrinsics.data(), g.views, deg, seed * 1000u + unsigned(d));
              };
              // The prediction holds the cameras the decoder saw: the true K and the turned extrinsics.
              const model::Prediction<float> p = model::predict<float>(ws, *w, images.data(), V, 0, cams);
              const Consistency r = consistency(ws, *w, p.geometry, images.data(), p.geometry.extrinsics.data(), true,
                                                rws, out);
              all_in += r.all_in, left_out += r.left_out;
            }
            std::printf("| %d | %s | %s | %g | %d | %.5f | %.5f |\n", static_cast<int>(V), rec.name.c_str(),
                        set_name.c_str(), deg, n_draws, all_in / n_draws, left_out / n_draws);
            std::fflush(stdout);
          }
        }
      }
    }
  } catch (const Error& e) {
    std::fprintf(stderr, "render_consistency: %s\n", e.what());
    return 1;
  }
  return 0;
}
