// Per-scene fit: Gaussians drawn at random in a cube around the point the cameras look at (no ground-truth geometry)
// are optimised with Adam through the rasterizer's adjoints on 24 of the 32 views of an object, then evaluated
// (PSNR, SSIM) on the 8 held-out views. Writes a PNG: held-out view | render | error map.
// Usage: fit_object [object_dir] [--gaussians N] [--iters N] [--seconds S] [--out file.png] [--half-extent H]
//                   [--export fitted.glb|fitted.ply (the fitted set with the training cameras)]
//                   [--sh-degree D (default 1, raised from 0 after 20% of the budget)]
//                   [--densify-every N (default 100 iterations, 0: off)]
// Schedules (position learning rate decay, SH warm-up, densification window) follow the fraction of the time or
// iteration budget used, whichever is larger.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/export/cameras_json.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/export/render_set.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/raster/render.hpp"

using namespace flexsplat;
using namespace flexsplat::raster;

namespace {

struct View {
  Camera<float> camera;
  gaussians::Camera source;  // as read from cameras.json, exported with the set
  std::vector<float> rgb;  // [H, W, 3], composited on white
};

std::vector<View> load_views(const std::string& dir) {
  std::vector<View> views;
  for (const auto& cam : gaussians::load_cameras_json(dir + "/cameras.json")) {
    View v;
    v.camera = gaussians::raster_camera<float>(cam);
    v.source = cam;
    const Tensor<float, 3> rgb = image::read_rgb<float>(dir + "/" + cam.name);  // composited on white
    require(rgb.shape(0) == cam.height && rgb.shape(1) == cam.width, "fit_object: image '", cam.name, "' is ",
            rgb.shape(1), "x", rgb.shape(0), ", cameras.json says ", cam.width, "x", cam.height);
    v.rgb.assign(rgb.data(), rgb.data() + rgb.size());
    views.push_back(std::move(v));
  }
  require(!views.empty(), "fit_object: no frames in '", dir, "/cameras.json'");
  return views;
}

// Least-squares point closest to every optical axis: where the cameras look.
std::array<double, 3> look_at_point(const std::vector<View>& views) {
  double A[9] = {0}, b[3] = {0};
  for (const auto& v : views) {
    const auto& m = v.camera.world_to_camera;
    double c[3], d[3];
    for (int i = 0; i < 3; ++i) {
      c[i] = -(m[0 * 4 + i] * m[3] + m[1 * 4 + i] * m[7] + m[2 * 4 + i] * m[11]);
      d[i] = m[2 * 4 + i];  // camera z axis in world coordinates
    }
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        const double p = (i == j) - d[i] * d[j];
        A[i * 3 + j] += p;
        b[i] += p * c[j];
      }
  }
  // Solve the 3x3 system by Cramer's rule.
  auto det3 = [](const double* M) {
    return M[0] * (M[4] * M[8] - M[5] * M[7]) - M[1] * (M[3] * M[8] - M[5] * M[6]) + M[2] * (M[3] * M[7] - M[4] * M[6]);
  };
  const double D = det3(A);
  std::array<double, 3> x{0, 0, 0};
  if (std::abs(D) < 1e-12) return x;
  for (int k = 0; k < 3; ++k) {
    double M[9];
    std::copy(A, A + 9, M);
    for (int i = 0; i < 3; ++i) M[i * 3 + k] = b[i];
    x[k] = det3(M) / D;
  }
  return x;
}

double psnr(const std::vector<float>& a, const std::vector<float>& b) {
  double mse = 0;
  for (std::size_t i = 0; i < a.size(); ++i) mse += double(a[i] - b[i]) * (a[i] - b[i]);
  mse /= double(a.size());
  return 10.0 * std::log10(1.0 / std::max(mse, 1e-12));
}

// SSIM with an 11x11 Gaussian window (sigma 1.5), averaged over channels and valid pixels.
double ssim(const std::vector<float>& a, const std::vector<float>& b, int W, int H) {
  const int r = 5;
  double w[11], ws = 0;
  for (int i = -r; i <= r; ++i) ws += w[i + r] = std::exp(-i * i / (2 * 1.5 * 1.5));
  for (double& x : w) x /= ws;
  auto blur = [&](const std::vector<double>& in) {
    std::vector<double> tmp(in.size(), 0), out(in.size(), 0);
    for (int y = 0; y < H; ++y)
      for (int x = r; x < W - r; ++x) {
        double s = 0;
        for (int k = -r; k <= r; ++k) s += w[k + r] * in[y * W + x + k];
        tmp[y * W + x] = s;
      }
    for (int y = r; y < H - r; ++y)
      for (int x = r; x < W - r; ++x) {
        double s = 0;
        for (int k = -r; k <= r; ++k) s += w[k + r] * tmp[(y + k) * W + x];
        out[y * W + x] = s;
      }
    return out;
  };
  const double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;
  double total = 0;
  long count = 0;
  for (int c = 0; c < 3; ++c) {
    std::vector<double> x(std::size_t(W) * H), y(x.size()), xx(x.size()), yy(x.size()), xy(x.size());
    for (int i = 0; i < W * H; ++i) {
      x[i] = a[i * 3 + c], y[i] = b[i * 3 + c];
      xx[i] = x[i] * x[i], yy[i] = y[i] * y[i], xy[i] = x[i] * y[i];
    }
    const auto mx = blur(x), my = blur(y), sxx = blur(xx), syy = blur(yy), sxy = blur(xy);
    for (int py = r; py < H - r; ++py)
      for (int px = r; px < W - r; ++px) {
        const int i = py * W + px;
        const double vx = sxx[i] - mx[i] * mx[i], vy = syy[i] - my[i] * my[i], cxy = sxy[i] - mx[i] * my[i];
        total += ((2 * mx[i] * my[i] + C1) * (2 * cxy + C2)) / ((mx[i] * mx[i] + my[i] * my[i] + C1) * (vx + vy + C2));
        ++count;
      }
  }
  return total / double(count);
}

struct Adam {
  std::vector<float> m, v;
  float lr;
  explicit Adam(std::size_t n, float lr_) : m(n, 0.f), v(n, 0.f), lr(lr_) {}
  void step(float* param, const float* grad, std::size_t n, int t) {
    const float b1 = 0.9f, b2 = 0.999f, eps = 1e-15f;
    const float c1 = 1.f - std::pow(b1, float(t)), c2 = 1.f - std::pow(b2, float(t));
    for (std::size_t i = 0; i < n; ++i) {
      m[i] = b1 * m[i] + (1 - b1) * grad[i];
      v[i] = b2 * v[i] + (1 - b2) * grad[i] * grad[i];
      param[i] -= lr * (m[i] / c1) / (std::sqrt(v[i] / c2) + eps);
    }
  }
};

}  // namespace

int main(int argc, char** argv) {
  try {
    std::string dir = "../shared/data/objects/spot", out_png = "fit_object.png", export_path;
    index_t n = 20000;
    int iters = 1000000, sh_degree_max = 1, densify_every = 100;
    double seconds = 600, half_extent = 1.0, sh_warmup = 0.2, densify_from = 0.03, densify_until = 0.7;
    float prune_opacity = 0.01f, split_scale = 0.01f;
    for (int i = 1; i < argc; ++i) {
      const std::string a = argv[i];
      auto next = [&]() -> std::string {
        require(i + 1 < argc, "fit_object: option ", a, " needs a value");
        return argv[++i];
      };
      if (a == "--gaussians") n = std::stoll(next());
      else if (a == "--iters") iters = std::stoi(next());
      else if (a == "--seconds") seconds = std::stod(next());
      else if (a == "--out") out_png = next();
      else if (a == "--export") export_path = next();
      else if (a == "--half-extent") half_extent = std::stod(next());
      else if (a == "--sh-degree") sh_degree_max = std::stoi(next());
      else if (a == "--densify-every") densify_every = std::stoi(next());
      else dir = a;
    }
    auto views = load_views(dir);
    std::vector<int> train, test;
    for (int i = 0; i < int(views.size()); ++i) (i % 4 == 3 ? test : train).push_back(i);
    const auto centre = look_at_point(views);
    std::fprintf(stderr, "%s: %zu views (%zu train, %zu held out), look-at point (%.3f, %.3f, %.3f), %lld Gaussians\n",
                 dir.c_str(), views.size(), train.size(), test.size(), centre[0], centre[1], centre[2], (long long)n);

    // Parameters in flat blocks: means, quats, log-scales, opacity logits, SH DC colours and SH band 1.
    std::mt19937 rng(1);
    std::uniform_real_distribution<float> uni(-1.f, 1.f), u01(0.f, 1.f);
    std::normal_distribution<float> normal;
    const index_t K = sh_coeff_count(std::max(sh_degree_max, 0));
    Tensor<float, 2> means({n, 3}), quats({n, 4}), log_scales({n, 3}), sh_dc({n, 3}), sh_rest({n, std::max<index_t>(K - 1, 1) * 3});
    Tensor<float, 1> logits({n});
    Tensor<float, 3> sh({n, K, 3});
    const float init_scale = float(half_extent * 0.5 * std::cbrt(1.0 / double(n)));  // a quarter of the mean spacing: few overlaps at the start
    for (index_t i = 0; i < n; ++i) {
      for (int k = 0; k < 3; ++k) means.data()[i * 3 + k] = float(centre[k] + half_extent * uni(rng));
      quats.data()[i * 4] = 1.f;
      for (int k = 1; k < 4; ++k) quats.data()[i * 4 + k] = 0.f;
      for (int k = 0; k < 3; ++k) log_scales.data()[i * 3 + k] = std::log(init_scale);
      logits.data()[i] = std::log(0.1f / 0.9f);
      for (int k = 0; k < 3; ++k) sh_dc.data()[i * 3 + k] = 0.1f * normal(rng);
    }
    sh_rest.fill(0);
    sh.fill(0);
    Tensor<float, 2> scales({n, 3}), g_means({n, 3}), g_quats({n, 4}), g_scales({n, 3}), g_dc({n, 3}),
        g_rest({n, sh_rest.shape(1)});
    Tensor<float, 1> opacities({n}), g_opac({n});
    Tensor<float, 3> g_sh({n, K, 3});
    const float extent = float(half_extent);
    const float means_lr_start = 1.6e-3f * extent, means_lr_end = 1.6e-5f * extent;
    Adam opt_means(std::size_t(n * 3), means_lr_start), opt_quats(std::size_t(n * 4), 1e-3f),
        opt_scales(std::size_t(n * 3), 5e-3f), opt_logits(std::size_t(n), 5e-2f), opt_dc(std::size_t(n * 3), 2.5e-3f),
        opt_rest(std::size_t(sh_rest.size()), 2.5e-3f / 20.f);
    RenderOptions ro;
    ro.background = {1, 1, 1};  // the views are composited on white
    ro.sh_degree = 0;
    RenderWorkspace<float> ws;
    RenderOutputs<float> out;
    auto activate = [&] {
      for (index_t i = 0; i < n * 3; ++i) scales.data()[i] = std::exp(log_scales.data()[i]);
      for (index_t i = 0; i < n; ++i) opacities.data()[i] = 1.f / (1.f + std::exp(-logits.data()[i]));
      for (index_t i = 0; i < n; ++i) {
        float* dst = sh.data() + i * K * 3;
        for (int c = 0; c < 3; ++c) dst[c] = sh_dc.data()[i * 3 + c];
        for (index_t k = 0; k < (K - 1) * 3; ++k) dst[3 + k] = sh_rest.data()[i * sh_rest.shape(1) + k];
      }
    };
    auto inputs = [&] {
      return GaussianInputs<float>{means.view(), quats.view(), scales.view(), opacities.view(), sh.view(), {}};
    };
    // Budget-preserving densification: accumulated positional gradient norm and visibility per Gaussian.
    std::vector<double> grad_accum(std::size_t(n), 0.0);
    std::vector<int> grad_count(std::size_t(n), 0);
    auto reset_adam = [](Adam& a, index_t i, int width) {
      for (int k = 0; k < width; ++k) a.m[std::size_t(i * width + k)] = a.v[std::size_t(i * width + k)] = 0.f;
    };
    int replaced_total = 0;
    auto densify = [&] {
      // Dead: nearly transparent Gaussians. Sources: the largest mean positional gradients (under-reconstructed).
      std::vector<index_t> dead, sources;
      for (index_t i = 0; i < n; ++i)
        if (opacities.data()[i] < prune_opacity) dead.push_back(i);
      std::vector<std::pair<double, index_t>> ranked;
      for (index_t i = 0; i < n; ++i)
        if (grad_count[std::size_t(i)] > 0 && opacities.data()[i] >= prune_opacity)
          ranked.push_back({grad_accum[std::size_t(i)] / grad_count[std::size_t(i)], i});
      const std::size_t budget = std::min({dead.size(), ranked.size() / 4, std::size_t(n / 20)});
      std::partial_sort(ranked.begin(), ranked.begin() + std::ptrdiff_t(budget), ranked.end(),
                        [](const auto& a, const auto& b) { return a.first > b.first; });
      std::shuffle(dead.begin(), dead.end(), rng);
      for (std::size_t j = 0; j < budget; ++j) {
        const index_t src = ranked[j].second, dst = dead[j];
        float* ms = means.data() + src * 3;
        float* md = means.data() + dst * 3;
        const float* ls = log_scales.data() + src * 3;
        const float max_scale = std::exp(std::max({ls[0], ls[1], ls[2]}));
        // Large Gaussians split into two smaller ones sampled from the original; small ones are cloned.
        const bool split = max_scale > split_scale * extent;
        float R[9];
        {
          const float* q = quats.data() + src * 4;
          const float len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
          const float qn[4] = {q[0] / len, q[1] / len, q[2] / len, q[3] / len};
          quat_to_rotmat(qn, R);
        }
        for (int k = 0; k < 4; ++k) quats.data()[dst * 4 + k] = quats.data()[src * 4 + k];
        for (int k = 0; k < 3; ++k) sh_dc.data()[dst * 3 + k] = sh_dc.data()[src * 3 + k];
        for (index_t k = 0; k < sh_rest.shape(1); ++k)
          sh_rest.data()[dst * sh_rest.shape(1) + k] = sh_rest.data()[src * sh_rest.shape(1) + k];
        logits.data()[dst] = logits.data()[src];
        const float jitter = split ? 1.f : 0.1f;
        const float base[3] = {ms[0], ms[1], ms[2]};
        for (float* m : {md, ms}) {
          if (m == ms && !split) continue;  // a clone leaves its source in place
          float local[3];
          for (int k = 0; k < 3; ++k) local[k] = jitter * std::exp(ls[k]) * normal(rng);
          for (int r = 0; r < 3; ++r) m[r] = base[r] + R[r * 3] * local[0] + R[r * 3 + 1] * local[1] + R[r * 3 + 2] * local[2];
        }
        for (int k = 0; k < 3; ++k)
          log_scales.data()[dst * 3 + k] = ls[k] - (split ? std::log(1.6f) : 0.f);
        if (split)
          for (int k = 0; k < 3; ++k) log_scales.data()[src * 3 + k] -= std::log(1.6f);
        for (index_t i : {src, dst}) {
          reset_adam(opt_means, i, 3), reset_adam(opt_quats, i, 4), reset_adam(opt_scales, i, 3);
          reset_adam(opt_logits, i, 1), reset_adam(opt_dc, i, 3);
          reset_adam(opt_rest, i, int(sh_rest.shape(1)));
        }
      }
      replaced_total += int(budget);
      std::fill(grad_accum.begin(), grad_accum.end(), 0.0);
      std::fill(grad_count.begin(), grad_count.end(), 0);
      return budget;
    };
    const auto start = std::chrono::steady_clock::now();
    auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); };
    Tensor<float, 3> d_image;
    double loss_avg = 0;
    int it = 0;
    std::vector<int> view_order;
    std::size_t view_cursor = 0;
    for (it = 1; it <= iters && elapsed() < seconds; ++it) {
      // Progress by time or by iterations, whichever is further: schedules fit the budget either way.
      const double progress = std::min(1.0, std::max(elapsed() / seconds, double(it) / iters));
      if (view_cursor == view_order.size()) {  // random view order, every view once per epoch
        view_order = train;
        std::shuffle(view_order.begin(), view_order.end(), rng);
        view_cursor = 0;
      }
      const View& v = views[std::size_t(view_order[view_cursor++])];
      if (sh_degree_max > 0 && ro.sh_degree == 0 && progress >= sh_warmup) ro.sh_degree = std::min(sh_degree_max, 3);
      opt_means.lr = float(means_lr_start * std::pow(double(means_lr_end) / means_lr_start, progress));
      activate();
      render_forward(inputs(), v.camera, ro, ws, out);
      const index_t H = v.camera.height, W = v.camera.width;
      d_image.resize({H, W, 3});
      double loss = 0;
      const float inv = 1.f / float(H * W * 3);
      for (index_t i = 0; i < H * W * 3; ++i) {  // L1 loss
        const float d = out.image.data()[i] - v.rgb[std::size_t(i)];
        loss += std::abs(d);
        d_image.data()[i] = (d > 0 ? inv : d < 0 ? -inv : 0.f);
      }
      loss_avg = it == 1 ? loss * inv : 0.98 * loss_avg + 0.02 * loss * inv;
      for (auto* t : {&g_means, &g_quats, &g_scales}) t->fill(0);
      g_opac.fill(0);
      g_sh.fill(0);
      GaussianGrads<float> g{g_means.view(), g_quats.view(), g_scales.view(), g_opac.view(), g_sh.view(), {}, nullptr};
      render_backward(inputs(), v.camera, ro, ws, RenderOutputGrads<float>{d_image.view(), {}, {}, {}}, g);
      // Chain through the activations: scale = exp(log_scale), opacity = sigmoid(logit); split the SH bands.
      for (index_t i = 0; i < n * 3; ++i) g_scales.data()[i] *= scales.data()[i];
      for (index_t i = 0; i < n; ++i) g_opac.data()[i] *= opacities.data()[i] * (1.f - opacities.data()[i]);
      for (index_t i = 0; i < n; ++i) {
        const float* src = g_sh.data() + i * K * 3;
        for (int c = 0; c < 3; ++c) g_dc.data()[i * 3 + c] = src[c];
        for (index_t k = 0; k < (K - 1) * 3; ++k) g_rest.data()[i * g_rest.shape(1) + k] = src[3 + k];
        const float* gm = g_means.data() + i * 3;
        const double norm = std::sqrt(double(gm[0]) * gm[0] + double(gm[1]) * gm[1] + double(gm[2]) * gm[2]);
        if (norm > 0) grad_accum[std::size_t(i)] += norm, ++grad_count[std::size_t(i)];
      }
      opt_means.step(means.data(), g_means.data(), std::size_t(n * 3), it);
      opt_quats.step(quats.data(), g_quats.data(), std::size_t(n * 4), it);
      opt_scales.step(log_scales.data(), g_scales.data(), std::size_t(n * 3), it);
      opt_logits.step(logits.data(), g_opac.data(), std::size_t(n), it);
      opt_dc.step(sh_dc.data(), g_dc.data(), std::size_t(n * 3), it);
      if (ro.sh_degree > 0) opt_rest.step(sh_rest.data(), g_rest.data(), std::size_t(sh_rest.size()), it);
      for (index_t i = 0; i < n; ++i) {  // keep quaternions away from zero length
        float* q = quats.data() + i * 4;
        const float len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (len < 1e-6f) q[0] = 1.f, q[1] = q[2] = q[3] = 0.f;
      }
      if (densify_every > 0 && it % densify_every == 0 && progress >= densify_from && progress <= densify_until) {
        activate();
        densify();
      }
      if (it % 10 == 0 || it == iters) {
        std::fprintf(stderr, "\r%6d it  L1 %.4f  SH %d  replaced %d  %.0f s   ", it, loss_avg, ro.sh_degree,
                     replaced_total, elapsed());
      }
    }
    std::fprintf(stderr, "\n");
    const int done_iters = it - 1;
    // Held-out evaluation.
    activate();
    double psnr_sum = 0, ssim_sum = 0;
    std::vector<unsigned char> panel;
    for (std::size_t k = 0; k < test.size(); ++k) {
      const View& v = views[test[k]];
      render_forward(inputs(), v.camera, ro, ws, out);
      std::vector<float> img(out.image.data(), out.image.data() + out.image.size());
      for (auto& x : img) x = std::clamp(x, 0.f, 1.f);
      const double p = psnr(img, v.rgb), s = ssim(img, v.rgb, v.camera.width, v.camera.height);
      psnr_sum += p, ssim_sum += s;
      std::printf("held-out view %2d: PSNR %.2f dB  SSIM %.4f\n", test[k], p, s);
      if (k == 0) {
        const int W = v.camera.width, H = v.camera.height;
        panel.assign(std::size_t(W) * 3 * H * 3, 0);
        for (int y = 0; y < H; ++y)
          for (int x = 0; x < W; ++x) {
            const int i = y * W + x;
            float err = 0;
            for (int c = 0; c < 3; ++c) err += std::abs(img[i * 3 + c] - v.rgb[i * 3 + c]) / 3.f;
            const float e = std::min(1.f, err * 4.f);
            const float cols[3][3] = {{v.rgb[i * 3], v.rgb[i * 3 + 1], v.rgb[i * 3 + 2]},
                                      {img[i * 3], img[i * 3 + 1], img[i * 3 + 2]},
                                      {e, e * 0.3f, 1.f - e}};
            for (int p2 = 0; p2 < 3; ++p2)
              for (int c = 0; c < 3; ++c)
                panel[(std::size_t(y) * W * 3 + std::size_t(p2) * W + x) * 3 + c] =
                    (unsigned char)std::lround(std::clamp(cols[p2][c], 0.f, 1.f) * 255.f);
          }
        image::write_png(out_png, TensorView<const std::uint8_t, 3>(panel.data(), {H, 3 * W, 3}));
      }
    }
    std::printf("%s: %d iterations in %.1f s, %lld Gaussians (SH degree %d, %d replaced by densification): held-out "
                "mean PSNR %.2f dB, SSIM %.4f (%zu views); wrote %s\n",
                dir.c_str(), done_iters, elapsed(), (long long)n, ro.sh_degree, replaced_total,
                psnr_sum / double(test.size()), ssim_sum / double(test.size()), test.size(), out_png.c_str());
    if (!export_path.empty()) {
      auto set = gaussians::make_gaussian_set<float>(n, sh_degree_max);
      std::copy(means.data(), means.data() + means.size(), set.positions.data());
      std::copy(quats.data(), quats.data() + quats.size(), set.rotations.data());
      std::copy(scales.data(), scales.data() + scales.size(), set.scales.data());
      std::copy(opacities.data(), opacities.data() + opacities.size(), set.opacities.data());
      std::copy(sh.data(), sh.data() + sh.size(), set.sh.data());
      for (int i : train) set.cameras.push_back(views[i].source);
      const auto report = gaussians::write_gaussians(set, export_path);  // normalises quaternions (reported)
      std::printf("wrote %s: %lld Gaussians, SH degree %d, %zu cameras, %llu bytes (%lld quaternions renormalised)\n",
                  export_path.c_str(), (long long)n, sh_degree_max, set.cameras.size(),
                  (unsigned long long)report.bytes, (long long)report.repairs.rotations_renormalised);
    }
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fit_object: %s\n", e.what());
    return 1;
  }
}
