// Per-scene fit of one object with the library's training pieces: Gaussians drawn at random in a cube around the point
// the cameras look at are optimised through the rasterizer's adjoints on 3 of every 4 views (loss: L1, plus
// --ssim-weight x (1 - SSIM) as 3DGS; AdamW without weight decay, 3DGS's learning rate per tensor, the position rate
// decaying 100x over the budget; SH degree 0 for the first 20%, then 1; budget-preserving densification), then the
// held-out views are evaluated (PSNR, SSIM) and the first is written as a panel: held-out view | render | error.
// Usage: fit_object [object_dir] [--gaussians N] [--iters N] [--seconds S] [--half-extent H] [--ssim-weight W]
//                   [--out panel.png] [--export set.glb|.ply]
// Schedules follow the fraction of the time or iteration budget used, whichever is larger.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/decoder/init.hpp"
#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/export/render_set.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/loss/ssim.hpp"
#include "flexsplat/raster/project.hpp"
#include "flexsplat/raster/render.hpp"
#include "flexsplat/optim/optimizer.hpp"

using namespace flexsplat;

namespace {

// Budget-preserving densification: nearly transparent Gaussians (opacity < 0.01) are re-used for copies of those with
// the largest mean positional gradient (at most N/20 per call and a quarter of the candidates). A copy of a Gaussian
// larger than 1% of the extent splits it (both sampled from it, scales / 1.6); a smaller one is cloned with a small
// jitter. Both rows' Adam moments restart from zero. Returns the number of Gaussians moved.
int densify(const GaussianSet<float>& set, train::ParamStore<float>& store, std::vector<double>& accum,
            std::vector<int>& count, std::mt19937& rng, double extent) {
  const index_t n = set.size();
  std::vector<index_t> dead;
  std::vector<std::pair<double, index_t>> ranked;
  for (index_t i = 0; i < n; ++i) {
    if (set.opacities(i) < 0.01f) dead.push_back(i);
    else if (count[std::size_t(i)] > 0) ranked.push_back({accum[std::size_t(i)] / count[std::size_t(i)], i});
  }
  const std::size_t budget = std::min({dead.size(), ranked.size() / 4, std::size_t(n / 20)});
  std::partial_sort(ranked.begin(), ranked.begin() + std::ptrdiff_t(budget), ranked.end(),
                    [](const auto& a, const auto& b) { return a.first > b.first; });
  std::shuffle(dead.begin(), dead.end(), rng);
  std::normal_distribution<float> normal;
  for (std::size_t j = 0; j < budget; ++j) {
    const index_t src = ranked[j].second, dst = dead[j];
    for (const auto& t : store.tensors()) {  // every tensor holds one row per Gaussian
      const index_t w = t.numel / n;
      std::copy_n(store.params() + t.offset + src * w, w, store.params() + t.offset + dst * w);
      for (index_t i : {src, dst}) {
        std::fill_n(store.adam_m() + t.offset + i * w, w, 0.f);
        std::fill_n(store.adam_v() + t.offset + i * w, w, 0.f);
      }
    }
    const float* scale = &set.scales(src, 0);
    const bool split = std::max({scale[0], scale[1], scale[2]}) > 0.01f * float(extent);
    float q[4], R[9];
    const float len = std::sqrt(set.quats(src, 0) * set.quats(src, 0) + set.quats(src, 1) * set.quats(src, 1) +
                                set.quats(src, 2) * set.quats(src, 2) + set.quats(src, 3) * set.quats(src, 3));
    for (int k = 0; k < 4; ++k) q[k] = set.quats(src, k) / len;
    raster::quat_to_rotmat(q, R);
    for (index_t i : {dst, src}) {
      if (i == src && !split) continue;  // a clone leaves its source in place
      float local[3];
      for (int k = 0; k < 3; ++k) local[k] = (split ? 1.f : 0.1f) * scale[k] * normal(rng);
      for (int r = 0; r < 3; ++r)
        store.param("means")[i * 3 + r] = set.means(src, r) + R[r * 3] * local[0] + R[r * 3 + 1] * local[1] + R[r * 3 + 2] * local[2];
      if (split)
        for (int k = 0; k < 3; ++k) store.param("log_scales")[i * 3 + k] = std::log(scale[k] / 1.6f);
    }
  }
  std::fill(accum.begin(), accum.end(), 0.0);
  std::fill(count.begin(), count.end(), 0);
  return int(budget);
}

}  // namespace

int main(int argc, char** argv) {
  try {
    std::string dir = "../shared/data/objects/spot", out_png = "fit_object.png", export_path;
    index_t n = 20000;
    std::uint64_t iters = 1000000;
    double seconds = 600, half_extent = 1.0, ssim_weight = 0.0;
    for (int i = 1; i < argc; ++i) {
      const std::string a = argv[i];
      auto next = [&]() -> std::string {
        require(i + 1 < argc, "fit_object: option ", a, " needs a value");
        return argv[++i];
      };
      if (a == "--gaussians") n = std::stoll(next());
      else if (a == "--iters") iters = std::stoull(next());
      else if (a == "--seconds") seconds = std::stod(next());
      else if (a == "--half-extent") half_extent = std::stod(next());
      else if (a == "--ssim-weight") ssim_weight = std::stod(next());
      else if (a == "--out") out_png = next();
      else if (a == "--export") export_path = next();
      else dir = a;
    }
    require(n >= 1 && iters >= 1 && seconds > 0 && half_extent > 0 && ssim_weight >= 0 && ssim_weight <= 1,
            "fit_object: --gaussians, --iters, --seconds and --half-extent must be positive, --ssim-weight in [0, 1]");

    // Views composited on white; every fourth is held out.
    const auto cameras = io::load_cameras_json(dir + "/cameras.json");
    std::vector<raster::View<float>> cams;
    std::vector<Tensor<float, 3>> images;
    std::vector<int> train, test;
    for (const auto& c : cameras) {
      (cams.size() % 4 == 3 ? test : train).push_back(int(cams.size()));
      cams.push_back(raster::camera_view<float>(c));
      images.push_back(image::read_rgb<float>(dir + "/" + c.name));
      require(images.back().shape(0) == c.height && images.back().shape(1) == c.width, "fit_object: '", c.name,
              "' does not have the size cameras.json gives");
    }
    require(!train.empty() && !test.empty(), "fit_object: need at least 4 views in ", dir);

    // Where the optical axes meet (one-pixel unit "depth" maps only serve the parallel-axes fallback).
    const index_t V = index_t(cameras.size());
    std::vector<double> K(9 * V), E(12 * V), depth(V, 1.0);
    for (index_t v = 0; v < V; ++v) camera_arrays(cameras[v], K.data() + 9 * v, E.data() + 12 * v);
    const decoder::ViewGeometry<double> geometry{V, cameras[0].width, cameras[0].height, 1, 1, K.data(), E.data(), depth.data()};
    const decoder::SceneCentre scene = decoder::scene_centre_from_axes(geometry);

    // Trainable tensors in one store, each with its own learning rate (3DGS's values, positions scaled to the cube).
    const int degree = 1;
    const index_t rest = sh_coefficients(degree) - 1;
    train::ParamStore<float> store;
    store.add_segment("gaussians", {{"means", {n, 3}}, {"quats", {n, 4}}, {"log_scales", {n, 3}},
                                    {"opacity_logits", {n}}, {"sh_dc", {n, 1, 3}}, {"sh_rest", {n, rest, 3}}});
    store.allocate();
    for (auto [name, lr] : {std::pair{"means", 1.6e-3 * half_extent}, {"quats", 1e-3}, {"log_scales", 5e-3},
                            {"opacity_logits", 5e-2}, {"sh_dc", 2.5e-3}, {"sh_rest", 2.5e-3 / 20}})
      store.set_lr_scale(name, lr);
    std::mt19937 rng(1);
    std::uniform_real_distribution<float> uni(-1.f, 1.f);
    std::normal_distribution<float> normal;
    const float init_scale = float(std::log(half_extent * 0.5 * std::cbrt(1.0 / double(n))));
    for (index_t i = 0; i < n; ++i) {
      for (int k = 0; k < 3; ++k) store.param("means")[i * 3 + k] = float(scene.centre[k] + half_extent * uni(rng));
      store.param("quats")[i * 4] = 1.f;
      for (int k = 0; k < 3; ++k) store.param("log_scales")[i * 3 + k] = init_scale;
      store.param("opacity_logits")[i] = std::log(0.1f / 0.9f);
      for (int k = 0; k < 3; ++k) store.param("sh_dc")[i * 3 + k] = 0.1f * normal(rng);
    }

    // The renderable set from the parameters: exp scales, sigmoid opacities, SH bands joined.
    GaussianSet<float> set = make_gaussian_set<float>(n, degree);
    auto activate = [&] {
      std::copy_n(store.param("means").data(), n * 3, set.means.data());
      std::copy_n(store.param("quats").data(), n * 4, set.quats.data());
      for (index_t i = 0; i < n * 3; ++i) set.scales.data()[i] = std::exp(store.param("log_scales")[i]);
      for (index_t i = 0; i < n; ++i) set.opacities.data()[i] = 1.f / (1.f + std::exp(-store.param("opacity_logits")[i]));
      for (index_t i = 0; i < n; ++i) {
        std::copy_n(store.param("sh_dc").data() + i * 3, 3, set.sh.data() + i * (rest + 1) * 3);
        std::copy_n(store.param("sh_rest").data() + i * rest * 3, rest * 3, set.sh.data() + (i * (rest + 1) + 1) * 3);
      }
    };
    raster::RenderOptions ro;
    ro.background = {1, 1, 1};
    raster::RenderWorkspace<float> ws;
    raster::RenderOutputs<float> out;
    loss::SsimWorkspace ssim_ws;
    GaussianSetGrad<float> grad = make_gaussian_grad(set);
    Tensor<float, 3> d_image;
    const train::AdamWConfig adam{0.9, 0.999, 1e-15, 0.0};
    std::vector<double> grad_accum(std::size_t(n), 0.0);     // mean positional gradient norm: densification sources
    std::vector<int> grad_count(std::size_t(n), 0);
    int replaced = 0;
    std::vector<int> order;
    double loss_avg = 0;
    const auto start = std::chrono::steady_clock::now();
    auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); };
    std::uint64_t it = 0;
    while (it < iters && elapsed() < seconds) {
      ++it;
      const double progress = std::min(1.0, std::max(elapsed() / seconds, double(it) / double(iters)));
      if (order.empty()) {
        order = train;
        std::shuffle(order.begin(), order.end(), rng);
      }
      const int v = order.back();
      order.pop_back();
      ro.sh_degree = progress < 0.2 ? 0 : degree;
      activate();
      raster::render_forward(set, cams[v], ro, ws, out);
      const loss::ImageShape shape{1, 3, cams[v].height, cams[v].width, loss::Layout::nhwc};
      const float* target = images[v].data();
      const float* no_mask = nullptr;
      const double l1 = loss::l1_forward(out.image.data(), target, no_mask, shape);
      loss_avg = it == 1 ? l1 : 0.98 * loss_avg + 0.02 * l1;
      d_image.resize(out.image.shape());
      d_image.fill(0.f);
      loss::l1_backward(d_image.data(), static_cast<float*>(nullptr), 1.0 - ssim_weight, out.image.data(), target, no_mask, shape);
      if (ssim_weight > 0)
        loss::ssim_backward(d_image.data(), static_cast<float*>(nullptr), -ssim_weight, out.image.data(), target, shape, {},
                            ssim_ws);
      grad.zero();
      raster::render_backward(set, cams[v], ro, ws, raster::RenderOutputGrads<float>{d_image.view(), {}, {}, {}}, grad);
      // Chain rule through the activations into the store's gradient block.
      store.zero_grads();
      std::copy_n(grad.means.data(), n * 3, store.grad("means").data());
      std::copy_n(grad.quats.data(), n * 4, store.grad("quats").data());
      for (index_t i = 0; i < n * 3; ++i) store.grad("log_scales")[i] = grad.scales.data()[i] * set.scales.data()[i];
      for (index_t i = 0; i < n; ++i) {
        const float o = set.opacities.data()[i];
        store.grad("opacity_logits")[i] = grad.opacities.data()[i] * o * (1.f - o);
        std::copy_n(grad.sh.data() + i * (rest + 1) * 3, 3, store.grad("sh_dc").data() + i * 3);
        std::copy_n(grad.sh.data() + (i * (rest + 1) + 1) * 3, rest * 3, store.grad("sh_rest").data() + i * rest * 3);
        const float* gm = grad.means.data() + i * 3;
        const double norm = std::sqrt(double(gm[0]) * gm[0] + double(gm[1]) * gm[1] + double(gm[2]) * gm[2]);
        if (norm > 0) grad_accum[std::size_t(i)] += norm, ++grad_count[std::size_t(i)];
      }
      store.set_lr_scale("means", 1.6e-3 * half_extent * std::pow(0.01, progress));  // 3DGS's position decay
      train::adamw_step(store, adam, 1.0, it);
      for (index_t i = 0; i < n; ++i) {  // keep quaternions away from zero length
        float* q = store.param("quats").data() + i * 4;
        if (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < 1e-12f) q[0] = 1.f, q[1] = q[2] = q[3] = 0.f;
      }
      if (it % 100 == 0 && progress >= 0.03 && progress <= 0.7) {
        activate();
        replaced += densify(set, store, grad_accum, grad_count, rng, half_extent);
      }
      if (it % 50 == 0)
        std::fprintf(stderr, "\r%6llu it  L1 %.4f  replaced %d  %.0f s   ", (unsigned long long)it, loss_avg, replaced, elapsed());
    }
    std::fprintf(stderr, "\n");

    activate();
    double psnr_sum = 0, ssim_sum = 0;
    for (std::size_t k = 0; k < test.size(); ++k) {
      const int v = test[k];
      raster::render_forward(set, cams[v], ro, ws, out);
      for (index_t i = 0; i < out.image.size(); ++i) out.image.data()[i] = std::clamp(out.image.data()[i], 0.f, 1.f);
      const index_t H = cams[v].height, W = cams[v].width;
      const double p = loss::psnr(out.image.data(), images[v].data(), out.image.size());
      const double s = loss::ssim_forward(out.image.data(), images[v].data(), {1, 3, H, W, loss::Layout::nhwc}, {}, ssim_ws);
      psnr_sum += p, ssim_sum += s;
      std::printf("held-out view %2d: PSNR %.2f dB  SSIM %.4f\n", v, p, s);
      if (k == 0) {
        Tensor<float, 3> panel({H, 3 * W, 3});
        for (index_t y = 0; y < H; ++y)
          for (index_t x = 0; x < W; ++x) {
            float err = 0;
            for (int c = 0; c < 3; ++c) {
              panel(y, x, c) = images[v](y, x, c);
              panel(y, W + x, c) = out.image(y, x, c);
              err += std::abs(out.image(y, x, c) - images[v](y, x, c)) / 3.f;
            }
            const float e = std::min(1.f, 4.f * err);
            panel(y, 2 * W + x, 0) = e, panel(y, 2 * W + x, 1) = 0.3f * e, panel(y, 2 * W + x, 2) = 1.f - e;
          }
        image::write_png(out_png, TensorView<const float, 3>(panel.data(), panel.shape()));
      }
    }
    std::printf("%s: %llu iterations in %.1f s, %lld Gaussians (%d replaced): held-out mean PSNR %.2f dB, SSIM %.4f "
                "(%zu views); wrote %s\n",
                dir.c_str(), (unsigned long long)it, elapsed(), (long long)n, replaced, psnr_sum / double(test.size()),
                ssim_sum / double(test.size()), test.size(), out_png.c_str());
    if (!export_path.empty()) {
      gltf::WriteOptions options;
      if (gaussians::format_of(export_path) == gaussians::FileFormat::Glb)
        for (int v : train) options.cameras.push_back(cameras[v]);
      gaussians::write_gaussians(set, export_path, options);
      std::printf("wrote %s\n", export_path.c_str());
    }
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fit_object: %s\n", e.what());
    return 1;
  }
}
