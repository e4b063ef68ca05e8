// Rasterizer benchmark: forward and backward time for N in {10K, 100K, 1M}, 256^2 and 512^2, SH degree 0 and 3,
// 1 and 2 threads, the error of each float32 configuration against a float64 run of the same scene, and what each
// skip saves on the target scene. Writes a CSV and an SVG plot of run time against error.
// Usage: raster [out.csv] [out.svg] [--quick (no 1M)] [--target-only (only the skip table of the target scene)]
//              [--rounds R (interleaved rounds of the skip table, default 5)]
//              [--profile R (only the target scene with all skips, R repetitions: for perf/callgrind)]
#include <algorithm>
#include <chrono>
#include <ctime>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/simd.hpp"
#include "flexsplat/raster/render.hpp"

using namespace flexsplat;
using namespace flexsplat::raster;

namespace {

template <class T>
struct Scene : GaussianSet<T> {
  View<T> camera;
};

// The OpenSplat comparison scene: means uniform in a cube of side 2 centred 4 units in front of a pinhole camera
// with fx = fy = W, scales log-uniform in [0.005, 0.05], opacities uniform in (0.05, 0.95).
template <class T>
Scene<T> make_scene(index_t n, int size, int degree, unsigned seed = 7) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> uni(-1, 1), u01(0, 1);
  std::normal_distribution<double> normal;
  const index_t K = (degree + 1) * (degree + 1);
  Scene<T> s;
  s.means.resize({n, 3});
  s.quats.resize({n, 4});
  s.scales.resize({n, 3});
  s.opacities.resize({n});
  s.sh.resize({n, K, 3});
  for (index_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) s.means(i, k) = T(uni(rng));
    for (int k = 0; k < 4; ++k) s.quats(i, k) = T(normal(rng));
    for (int k = 0; k < 3; ++k) s.scales(i, k) = T(std::exp(std::log(0.005) + std::log(10.0) * u01(rng)));
    s.opacities(i) = T(0.05 + 0.9 * u01(rng));
    for (index_t k = 0; k < K; ++k)
      for (int c = 0; c < 3; ++c) s.sh(i, k, c) = T((k == 0 ? 1.0 : 0.2) * normal(rng));
  }
  s.camera.world_to_camera = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 4, 0, 0, 0, 1};
  s.camera.fx = s.camera.fy = T(size);
  s.camera.cx = s.camera.cy = T(size * 0.5);
  s.camera.width = s.camera.height = size;
  return s;
}

template <class T>
struct Result {
  RenderOutputs<T> out;
  GaussianSetGrad<T> d;
  ViewGrad<T> d_cam;
  double forward_ms = 0, backward_ms = 0, forward_cpu_ms = 0, backward_cpu_ms = 0;  // wall and process CPU time
  double contributors_per_pixel = 0, entries = 0;
  ForwardStageTimes stages;  // medians over the repetitions
  BackwardStageTimes backward_stages;
};

template <class T>
Result<T> run(const Scene<T>& s, const RenderOptions& opt, int reps, unsigned cot_seed = 3) {
  Result<T> r;
  const index_t H = s.camera.height, W = s.camera.width;
  Tensor<T, 3> d_image({H, W, 3});
  Tensor<T, 2> d_alpha({H, W}), d_depth({H, W});
  std::mt19937 rng(cot_seed);
  std::normal_distribution<double> normal;
  for (auto& v : d_image.span()) v = T(normal(rng));
  for (auto& v : d_alpha.span()) v = T(normal(rng));
  for (auto& v : d_depth.span()) v = T(0.1 * normal(rng));
  resize_gaussian_grad(r.d, s);
  RenderWorkspace<T> ws;
  std::vector<double> fwd, bwd, fwd_cpu, bwd_cpu;
  std::vector<ForwardStageTimes> stages;
  std::vector<BackwardStageTimes> backward_stages;
  auto cpu_ms = [] {
    timespec ts{};
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
  };
  for (int rep = 0; rep < reps + 1; ++rep) {  // first repetition warms the workspace up
    const double c0 = cpu_ms();
    auto t0 = std::chrono::steady_clock::now();
    render_forward(s, s.camera, opt, ws, r.out);
    auto t1 = std::chrono::steady_clock::now();
    const double c1 = cpu_ms();
    r.d.zero();
    r.d_cam = {};
    const double c2 = cpu_ms();
    auto t2 = std::chrono::steady_clock::now();
    render_backward<T>(s, s.camera, opt, ws, RenderOutputGrads<T>{d_image.view(), d_alpha.view(), d_depth.view(), {}}, r.d,
                       &r.d_cam);
    auto t3 = std::chrono::steady_clock::now();
    const double c3 = cpu_ms();
    if (rep > 0 || reps == 0) {
      fwd.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
      bwd.push_back(std::chrono::duration<double, std::milli>(t3 - t2).count());
      fwd_cpu.push_back(c1 - c0);
      stages.push_back(ws.forward_times);
      backward_stages.push_back(ws.backward_times);
      bwd_cpu.push_back(c3 - c2);
    }
  }
  std::sort(fwd.begin(), fwd.end());
  std::sort(bwd.begin(), bwd.end());
  r.forward_ms = fwd[fwd.size() / 2];
  r.backward_ms = bwd[bwd.size() / 2];
  std::sort(fwd_cpu.begin(), fwd_cpu.end());
  std::sort(bwd_cpu.begin(), bwd_cpu.end());
  r.forward_cpu_ms = fwd_cpu[fwd_cpu.size() / 2];
  r.backward_cpu_ms = bwd_cpu[bwd_cpu.size() / 2];
  auto median = [&](double ForwardStageTimes::*field) {
    std::vector<double> v;
    for (const auto& s : stages) v.push_back(s.*field);
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  for (auto field : {&ForwardStageTimes::validate, &ForwardStageTimes::project, &ForwardStageTimes::intersect,
                     &ForwardStageTimes::rasterize})
    r.stages.*field = median(field);
  for (auto field : {&BackwardStageTimes::validate, &BackwardStageTimes::blend, &BackwardStageTimes::gaussians}) {
    std::vector<double> v;
    for (const auto& s : backward_stages) v.push_back(s.*field);
    std::sort(v.begin(), v.end());
    r.backward_stages.*field = v[v.size() / 2];
  }
  double total = 0;
  for (auto v : r.out.n_contrib.span()) total += v;
  r.contributors_per_pixel = total / double(H * W);
  r.entries = double(ws.tiles.tile_entries.size());
  return r;
}

template <class A, class B>
double max_abs_error(const A& a, const B& b) {
  double m = 0;
  for (index_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(double(a.data()[i]) - double(b.data()[i])));
  return m;
}
template <class A, class B>
double max_rel_error(const A& a, const B& b) {
  double scale = 0;
  for (index_t i = 0; i < b.size(); ++i) scale = std::max(scale, std::abs(double(b.data()[i])));
  return scale > 0 ? max_abs_error(a, b) / scale : 0.0;
}

struct Row {
  index_t n;
  int size, degree, threads;
  double fwd, bwd, contrib, image_err, grad_err;
};

void write_svg(const std::string& path, const std::vector<Row>& rows) {
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (!f) return;
  const double W = 760, H = 460, L = 80, R = 20, T = 30, B = 60;
  double tmin = 1e9, tmax = 0, emin = 1e9, emax = 0;
  for (auto& r : rows) {
    tmin = std::min(tmin, r.fwd), tmax = std::max(tmax, r.bwd);
    emin = std::min(emin, std::max(r.image_err, 1e-9)), emax = std::max(emax, r.grad_err);
  }
  const double lt0 = std::floor(std::log10(tmin)), lt1 = std::ceil(std::log10(tmax));
  const double le0 = std::floor(std::log10(emin)), le1 = std::ceil(std::log10(emax));
  auto X = [&](double t) { return L + (std::log10(t) - lt0) / (lt1 - lt0) * (W - L - R); };
  auto Y = [&](double e) { return H - B - (std::log10(std::max(e, 1e-9)) - le0) / (le1 - le0) * (H - T - B); };
  std::fprintf(f, "<svg xmlns='http://www.w3.org/2000/svg' width='%g' height='%g' font-family='sans-serif' font-size='12'>\n", W, H);
  std::fprintf(f, "<rect width='100%%' height='100%%' fill='white'/>\n");
  for (double e = lt0; e <= lt1; ++e)
    std::fprintf(f, "<line x1='%g' y1='%g' x2='%g' y2='%g' stroke='#ddd'/><text x='%g' y='%g' text-anchor='middle'>%g ms</text>\n",
                 X(std::pow(10, e)), T, X(std::pow(10, e)), H - B, X(std::pow(10, e)), H - B + 16, std::pow(10, e));
  for (double e = le0; e <= le1; ++e)
    std::fprintf(f, "<line x1='%g' y1='%g' x2='%g' y2='%g' stroke='#ddd'/><text x='%g' y='%g' text-anchor='end'>1e%g</text>\n",
                 L, Y(std::pow(10, e)), W - R, Y(std::pow(10, e)), L - 6, Y(std::pow(10, e)) + 4, e);
  std::fprintf(f, "<text x='%g' y='%g' text-anchor='middle'>run time (log)</text>\n", (L + W - R) / 2, H - 20);
  std::fprintf(f, "<text x='16' y='%g' transform='rotate(-90 16 %g)' text-anchor='middle'>error vs float64 (log)</text>\n", (T + H - B) / 2, (T + H - B) / 2);
  std::fprintf(f, "<text x='%g' y='20' text-anchor='middle'>flexsplat raster: circles forward (image max abs error), squares backward (gradient max error / max abs); blue 1 thread, red 2 threads</text>\n", W / 2);
  for (auto& r : rows) {
    const char* colour = r.threads == 1 ? "#1f5fbf" : "#c0392b";
    const double rad = r.n >= 1000000 ? 7 : r.n >= 100000 ? 5 : 3;
    std::fprintf(f, "<circle cx='%g' cy='%g' r='%g' fill='none' stroke='%s'><title>N=%lld %dpx SH%d %dt fwd %.2f ms</title></circle>\n",
                 X(r.fwd), Y(r.image_err), rad, colour, (long long)r.n, r.size, r.degree, r.threads, r.fwd);
    std::fprintf(f, "<rect x='%g' y='%g' width='%g' height='%g' fill='none' stroke='%s'><title>N=%lld %dpx SH%d %dt bwd %.2f ms</title></rect>\n",
                 X(r.bwd) - rad, Y(r.grad_err) - rad, 2 * rad, 2 * rad, colour, (long long)r.n, r.size, r.degree, r.threads, r.bwd);
  }
  std::fprintf(f, "</svg>\n");
  std::fclose(f);
}

}  // namespace

int main(int argc, char** argv) {
  simd::require_cpu_supports_build();
  std::string csv_path = "raster_bench.csv", svg_path = "raster_bench.svg";
  bool quick = false, target_only = false;
  int profile_reps = 0, rounds = 5;
  std::vector<std::string> pos;
  for (int i = 1; i < argc; ++i) {
    if (std::string(argv[i]) == "--quick") quick = true;
    else if (std::string(argv[i]) == "--profile" && i + 1 < argc) profile_reps = std::max(1, std::atoi(argv[++i]));
    else if (std::string(argv[i]) == "--target-only") target_only = true;
    else if (std::string(argv[i]) == "--rounds" && i + 1 < argc) rounds = std::max(1, std::atoi(argv[++i]));
    else pos.push_back(argv[i]);
  }
  if (pos.size() > 0) csv_path = pos[0];
  if (pos.size() > 1) svg_path = pos[1];
  std::printf("simd arch %s (enabled %d), cpu: %s\n", simd::compiled_arch_name(), int(simd::enabled()),
              simd::describe(simd::cpu_features()).c_str());
  ThreadPool one(1), two(2);
  if (profile_reps > 0) {
    const auto target = make_scene<float>(100000, 512, 3);
    RenderOptions opt;
    opt.background = {1, 1, 1};
    opt.pool = &two;
    const auto r = run(target, opt, profile_reps);
    std::printf("target scene, all skips, %d reps: fwd %.2f ms (cpu %.2f), bwd %.2f ms (cpu %.2f), %.0f tile entries, "
                "%.2f contributors/pixel\n", profile_reps, r.forward_ms, r.forward_cpu_ms, r.backward_ms,
                r.backward_cpu_ms, r.entries, r.contributors_per_pixel);
    std::printf("forward stages (median wall ms): validate %.2f, project+SH %.2f, intersect %.2f, rasterize %.2f, "
                "(outputs written by the blend)\n", r.stages.validate, r.stages.project, r.stages.intersect,
                r.stages.rasterize);
    std::printf("backward stages (median wall ms): validate %.2f, blend %.2f, per-Gaussian %.2f\n",
                r.backward_stages.validate, r.backward_stages.blend, r.backward_stages.gaussians);
    return 0;
  }
  std::vector<Row> rows;
  const std::vector<index_t> counts = quick ? std::vector<index_t>{10000, 100000} : std::vector<index_t>{10000, 100000, 1000000};
  std::printf("%8s %5s %3s %3s %10s %10s %8s %10s %10s\n", "N", "size", "SH", "thr", "fwd_ms", "bwd_ms", "contrib",
              "img_err", "grad_err");
  for (index_t n : target_only ? std::vector<index_t>{} : counts)
    for (int size : {256, 512})
      for (int degree : {0, 3}) {
        const auto sf = make_scene<float>(n, size, degree);
        const auto sd = make_scene<double>(n, size, degree);
        RenderOptions opt;
        opt.background = {1, 1, 1};
        opt.pool = &one;
        const auto ref = run(sd, opt, 0);
        for (int threads : {1, 2}) {
          opt.pool = threads == 1 ? &one : &two;
          const int reps = n >= 1000000 ? 3 : 7;
          const auto r = run(sf, opt, reps);
          const double image_err = std::max(max_abs_error(r.out.image, ref.out.image), max_abs_error(r.out.alpha, ref.out.alpha));
          const double grad_err = std::max({max_rel_error(r.d.means, ref.d.means), max_rel_error(r.d.quats, ref.d.quats),
                                            max_rel_error(r.d.scales, ref.d.scales),
                                            max_rel_error(r.d.opacities, ref.d.opacities), max_rel_error(r.d.sh, ref.d.sh)});
          rows.push_back({n, size, degree, threads, r.forward_ms, r.backward_ms, r.contributors_per_pixel, image_err, grad_err});
          std::printf("%8lld %5d %3d %3d %10.2f %10.2f %8.2f %10.2e %10.2e\n", (long long)n, size, degree, threads,
                      r.forward_ms, r.backward_ms, r.contributors_per_pixel, image_err, grad_err);
          std::fflush(stdout);
        }
      }
  if (std::FILE* f = target_only ? nullptr : std::fopen(csv_path.c_str(), "w")) {
    std::fprintf(f, "n,size,sh_degree,threads,forward_ms,backward_ms,contributors_per_pixel,image_max_abs_err,grad_max_rel_err\n");
    for (auto& r : rows)
      std::fprintf(f, "%lld,%d,%d,%d,%.3f,%.3f,%.3f,%.3e,%.3e\n", (long long)r.n, r.size, r.degree, r.threads, r.fwd,
                   r.bwd, r.contrib, r.image_err, r.grad_err);
    std::fclose(f);
  }
  if (!target_only) {
    write_svg(svg_path, rows);
    std::printf("wrote %s and %s\n", csv_path.c_str(), svg_path.c_str());
  }

  // What each skip saves on the target scene (100K Gaussians, 512^2, SH 3, 2 threads).
  const auto target = make_scene<float>(100000, 512, 3);
  // Variants run in interleaved rounds so that a slow phase of a shared machine hits all of them alike.
  std::printf("\nskips on the target scene (100K, 512^2, SH 3, 2 threads), %d interleaved rounds of 5 repetitions: "
              "median over rounds [min]; cpu = process CPU time (both threads)\n"
              "%-26s %21s %21s %9s %9s %12s\n", rounds, "configuration", "fwd_ms", "bwd_ms", "fwd_cpu", "bwd_cpu",
              "tile_entries");
  struct Variant { const char* name; bool opacity, exact, early; };
  const Variant variants[] = {{"all skips", true, true, true}, {"no opacity-aware extent", false, true, true},
                              {"no exact tile test", true, false, true}, {"no early exit", true, true, false},
                              {"no skips", false, false, false}};
  std::vector<std::vector<Result<float>>> results(std::size(variants));
  for (int round = 0; round < rounds; ++round)
    for (std::size_t i = 0; i < std::size(variants); ++i) {
      RenderOptions opt;
      opt.background = {1, 1, 1};
      opt.pool = &two;
      opt.skips.opacity_aware_extent = variants[i].opacity;
      opt.skips.exact_tile_test = variants[i].exact;
      opt.skips.early_exit = variants[i].early;
      results[i].push_back(run(target, opt, 5));
      results[i].back().out = {};  // keep only the timings
    }
  auto stat = [](const std::vector<Result<float>>& rs, double Result<float>::*field, bool minimum) {
    std::vector<double> v;
    for (const auto& r : rs) v.push_back(r.*field);
    std::sort(v.begin(), v.end());
    return minimum ? v.front() : v[v.size() / 2];
  };
  for (std::size_t i = 0; i < std::size(variants); ++i) {
    const auto& rs = results[i];
    std::printf("%-26s %12.2f [%6.2f] %12.2f [%6.2f] %9.2f %9.2f %12.0f\n", variants[i].name,
                stat(rs, &Result<float>::forward_ms, false), stat(rs, &Result<float>::forward_ms, true),
                stat(rs, &Result<float>::backward_ms, false), stat(rs, &Result<float>::backward_ms, true),
                stat(rs, &Result<float>::forward_cpu_ms, false), stat(rs, &Result<float>::backward_cpu_ms, false),
                rs.front().entries);
  }
  return 0;
}
