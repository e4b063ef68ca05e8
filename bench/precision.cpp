// Time against error of core/gemm's bf16 backend (operands rounded to bf16, fp32 accumulation, oneDNN).
//  1. A FlexSplat model (default: the shipped one) on an object's input views: predict() in float64 (the reference),
//     fp32 (the BLAS) and bf16; the error of each output against float64 (depth, cameras, Gaussians) and the eval
//     protocol's PSNR on the held-out views, with the time per forward pass (fp32 and bf16 interleaved, best of R).
//  2. With --vggt-size N: VGGT-1B with random weights on 4 frames at N x N, fp32 against bf16 (time, depth, cameras).
//   bench/precision [--model M] [--object DIR] [--rounds R] [--vggt-size N]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "flexsplat/core/gemm.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/geometry/random_weights.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/model/weights.hpp"
#include "sgemm_rate.hpp"

using namespace flexsplat;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

template <class A, class B>
double max_abs_diff(const A* a, const B* b, std::size_t n) {
  double m = 0;
  for (std::size_t i = 0; i < n; ++i) m = std::max(m, std::abs(double(a[i]) - double(b[i])));
  return m;
}

template <class A>
double max_abs(const A* a, std::size_t n) {
  double m = 0;
  for (std::size_t i = 0; i < n; ++i) m = std::max(m, std::abs(double(a[i])));
  return m;
}

// Angle of R_a^T R_b, in degrees, for two [3, 4] world-to-camera matrices: ||R_a - R_b||_F = 2 sqrt(2) sin(angle / 2),
// accurate for the tiny angles here (acos of the trace is not: float rounding alone reads as 0.01 degrees).
template <class A, class B>
double rotation_deg(const A* a, const B* b) {
  double f = 0;
  for (int k = 0; k < 3; ++k)
    for (int i = 0; i < 3; ++i) f += std::pow(double(a[4 * k + i]) - double(b[4 * k + i]), 2);
  return 2.0 * std::asin(std::min(1.0, std::sqrt(f) / (2.0 * std::sqrt(2.0)))) * 180.0 / 3.14159265358979323846;
}

// Camera centre -R^T t of a [3, 4] world-to-camera matrix.
template <class A>
std::array<double, 3> centre(const A* m) {
  std::array<double, 3> c{};
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) c[static_cast<std::size_t>(i)] -= double(m[4 * k + i]) * double(m[4 * k + 3]);
  return c;
}

template <class A, class B>
void camera_errors(const A* ref, const B* x, index_t views, double scale, double& rot_deg, double& centre_rel) {
  rot_deg = centre_rel = 0;
  for (index_t v = 0; v < views; ++v) {
    rot_deg = std::max(rot_deg, rotation_deg(ref + 12 * v, x + 12 * v));
    const auto a = centre(ref + 12 * v), b = centre(x + 12 * v);
    centre_rel = std::max(centre_rel, std::hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]) / scale);
  }
}

template <class T>
GaussianSet<float> to_float(const GaussianSet<T>& g) {
  GaussianSet<float> f;
  resize_gaussian_set(f, g.size(), g.sh_degree(), g.feature_count());
  auto copy = [](const auto& from, auto& to) { std::copy(from.data(), from.data() + from.size(), to.data()); };
  copy(g.means, f.means), copy(g.quats, f.quats), copy(g.scales, f.scales), copy(g.opacities, f.opacities);
  copy(g.sh, f.sh);
  if (g.feature_count() > 0) copy(g.features, f.features);
  return f;
}

struct Row {
  std::string name;
  double ms = 0, depth_rel = 0, rot_deg = 0, centre_rel = 0, means_rel = 0, opacity = 0, sh = 0, psnr = 0;
};

void model_table(const std::string& model_path, const std::string& object_dir, int rounds) {
  const auto w64 = model::load_flexsplat<double>(model_path);
  const auto w32 = model::load_flexsplat<float>(model_path);
  const model::FlexSplatConfig& c = w32->config();
  const std::vector<data::ObjectRecord> objects = data::load_objects({object_dir});
  const data::ObjectRecord& rec = objects.at(0);
  model::EvalOptions eo;
  std::vector<int> in, targets;
  model::eval_views(rec, eo, in, targets);
  std::vector<Tensor<float, 3>> rgba;
  for (int v : in) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
  const Tensor<float, 4> images32 = model::model_input<float>(rgba, c);
  const Tensor<double, 4> images64 = model::model_input<double>(rgba, c);

  model::PredictWorkspace<double> ws64;
  const model::Prediction<double> ref =
      model::predict<double>(ws64, *w64, TensorView<const double, 4>(images64.view()));
  model::PredictWorkspace<float> ws32;
  const GemmBackend backends[2] = {bench::best_gemm_backend(), GemmBackend::bf16};
  model::Prediction<float> pred[2];
  double best_ms[2] = {1e300, 1e300};
  for (int r = 0; r < rounds; ++r)
    for (int b = 0; b < 2; ++b) {
      set_default_gemm_backend(backends[b]);
      const auto t0 = Clock::now();
      pred[b] = model::predict<float>(ws32, *w32, TensorView<const float, 4>(images32.view()));
      best_ms[b] = std::min(best_ms[b], seconds_since(t0) * 1e3);
    }
  set_default_gemm_backend(backends[0]);

  const std::size_t depth_n = ref.geometry.depth.size(), n = static_cast<std::size_t>(ref.gaussians.size());
  const double depth_scale = max_abs(ref.geometry.depth.data(), depth_n);
  const double means_scale = max_abs(ref.gaussians.means.data(), 3 * n);
  model::EvalWorkspace ews;
  auto psnr = [&](const float* w2c, const GaussianSet<float>& g) {
    return model::score_prediction(rec, in, targets, w2c, g, c.image_h, c.image_w, eo, ews).model.psnr;
  };
  std::vector<Row> rows;
  {
    Row r;
    r.name = "float64 (reference)";
    const std::vector<float> w2c(ref.geometry.extrinsics.begin(), ref.geometry.extrinsics.end());
    r.psnr = psnr(w2c.data(), to_float(ref.gaussians));
    rows.push_back(r);
  }
  for (int b = 0; b < 2; ++b) {
    const model::Prediction<float>& p = pred[b];
    Row r;
    r.name = b == 0 ? "fp32" : "bf16";
    r.ms = best_ms[b];
    r.depth_rel = max_abs_diff(ref.geometry.depth.data(), p.geometry.depth.data(), depth_n) / depth_scale;
    camera_errors(ref.geometry.extrinsics.data(), p.geometry.extrinsics.data(), ref.views, depth_scale, r.rot_deg,
                  r.centre_rel);
    if (static_cast<std::size_t>(p.gaussians.size()) == n) {
      r.means_rel = max_abs_diff(ref.gaussians.means.data(), p.gaussians.means.data(), 3 * n) / means_scale;
      r.opacity = max_abs_diff(ref.gaussians.opacities.data(), p.gaussians.opacities.data(), n);
      r.sh = max_abs_diff(ref.gaussians.sh.data(), p.gaussians.sh.data(), ref.gaussians.sh.size());
    } else {
      r.means_rel = r.opacity = r.sh = std::nan("");
    }
    r.psnr = psnr(p.geometry.extrinsics.data(), p.gaussians);
    rows.push_back(r);
  }
  std::printf("model %s (%lld x %lld, %lld Gaussians), object %s, input views", model_path.c_str(),
              static_cast<long long>(c.image_h), static_cast<long long>(c.image_w), static_cast<long long>(n),
              rec.name.c_str());
  for (int v : in) std::printf(" %d", v);
  std::printf("; errors are maxima against float64 (depth and centres relative to the largest depth, means to the "
              "largest |mean|); PSNR on the %zu held-out views\n", targets.size());
  std::printf("| precision | ms per predict | depth | rotation (deg) | centre | means | opacity | SH | PSNR (dB) |\n");
  std::printf("|---|---:|---:|---:|---:|---:|---:|---:|---:|\n");
  for (const Row& r : rows) {
    if (r.ms == 0)
      std::printf("| %s | | | | | | | | %.2f |\n", r.name.c_str(), r.psnr);
    else
      std::printf("| %s | %.1f | %.2e | %.2e | %.2e | %.2e | %.2e | %.2e | %.2f |\n", r.name.c_str(), r.ms,
                  r.depth_rel, r.rot_deg, r.centre_rel, r.means_rel, r.opacity, r.sh, r.psnr);
  }
  std::fflush(stdout);
}

void vggt_table(index_t size, int rounds) {
  geometry::VggtConfig cfg;  // VGGT-1B
  cfg.pose_decode.policy = geometry::DegeneratePosePolicy::clamp;
  io::ParamSource<float> src;
  geometry::add_random_parameters(src, geometry::vggt_parameter_specs(cfg), 1234);
  const auto weights = geometry::load_vggt_weights(src, cfg);
  const index_t frames = 4;
  std::vector<float> images(static_cast<std::size_t>(frames * 3 * size * size));
  for (std::size_t i = 0; i < images.size(); ++i) images[i] = float((i * 2654435761u) % 1000) / 1000.0f;
  const GemmBackend backends[2] = {bench::best_gemm_backend(), GemmBackend::bf16};
  std::vector<float> depth[2], w2c[2];
  double best[2] = {1e300, 1e300};
  geometry::VggtWorkspace<float> ws;
  for (int r = 0; r < rounds; ++r)
    for (int b = 0; b < 2; ++b) {
      set_default_gemm_backend(backends[b]);
      const auto t0 = Clock::now();
      const auto out = geometry::vggt_forward<float>(images.data(), frames, size, size, cfg, weights, ws, {});
      best[b] = std::min(best[b], seconds_since(t0));
      depth[b].assign(out.depth.data(), out.depth.data() + out.depth.size());
      w2c[b].assign(out.extrinsics.data(), out.extrinsics.data() + out.extrinsics.size());
      std::printf("  round %d %s: %.2f s\n", r, b == 0 ? "fp32" : "bf16", best[b]);
      std::fflush(stdout);
    }
  set_default_gemm_backend(backends[0]);
  const double depth_scale = max_abs(depth[0].data(), depth[0].size());
  double rot = 0, cen = 0;
  camera_errors(w2c[0].data(), w2c[1].data(), frames, depth_scale, rot, cen);
  std::printf("VGGT-1B (random weights), %lld frames at %lld x %lld, best of %d; bf16 against fp32 (depth and centres "
              "relative to the largest fp32 depth)\n", static_cast<long long>(frames), static_cast<long long>(size),
              static_cast<long long>(size), rounds);
  std::printf("| fp32 s | bf16 s | speed-up | depth | rotation (deg) | centre |\n|---:|---:|---:|---:|---:|---:|\n");
  std::printf("| %.2f | %.2f | %.2fx | %.2e | %.2e | %.2e |\n", best[0], best[1], best[0] / best[1],
              max_abs_diff(depth[0].data(), depth[1].data(), depth[0].size()) / depth_scale, rot, cen);
}

}  // namespace

int main(int argc, char** argv) try {
  std::string model_path = "models/flexsplat-small.safetensors", object_dir = "../shared/data/objects/spot";
  int rounds = 3;
  index_t vggt_size = 0;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--model" && i + 1 < argc) model_path = argv[++i];
    else if (a == "--object" && i + 1 < argc) object_dir = argv[++i];
    else if (a == "--rounds" && i + 1 < argc) rounds = std::max(1, std::atoi(argv[++i]));
    else if (a == "--vggt-size" && i + 1 < argc) vggt_size = std::atol(argv[++i]);
    else {
      std::fprintf(stderr, "usage: %s [--model M] [--object DIR] [--rounds R] [--vggt-size N]\n", argv[0]);
      return 2;
    }
  }
  if (!have_bf16_gemm) {
    std::fprintf(stderr, "precision: this build has no oneDNN, so no bf16 backend (FLEXSPLAT_USE_DNNL)\n");
    return 1;
  }
  std::printf("precision bench; build: %s; %d threads; fp32 on %s\nbf16 on %s\n\n", bench::build_label().c_str(),
              global_pool().size(), gemm_backend_name(bench::best_gemm_backend()).c_str(),
              gemm_backend_name(GemmBackend::bf16).c_str());
  model_table(model_path, object_dir, rounds);
  if (vggt_size > 0) {
    std::printf("\n");
    vggt_table(vggt_size, rounds);
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "precision: error: %s\n", e.what());
  return 1;
}
