#pragma once
// Checker for reference bundles of kind `raster`: every case<k> is rendered in float32 and its outputs and
// gradients are compared with the bundle's float64 autograd values at the tolerances of the reference README.
#include <algorithm>
#include <cstdint>
#include <set>
#include <string>
#include <vector>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

// Case prefixes ("case0.", ...) of a bundle: every tensor name ending in ".params".
inline std::vector<std::string> raster_bundle_cases(const safetensors::File& file) {
  std::vector<std::string> cases;
  for (const auto& t : file.tensors()) {
    const std::string suffix = ".params";
    if (t.name.size() > suffix.size() && t.name.compare(t.name.size() - suffix.size(), suffix.size(), suffix) == 0)
      cases.push_back(t.name.substr(0, t.name.size() - suffix.size() + 1));
  }
  std::sort(cases.begin(), cases.end());
  return cases;
}

template <class T>
void check_raster_case(const safetensors::File& file, const std::string& prefix, ReferenceReport& report) {
  auto get2 = [&](const char* name) { return file.get<T, 2>(prefix + name); };
  const auto params = file.get<std::int64_t, 1>(prefix + "params");
  require(params.size() == 4, "raster bundle '", file.path(), "': ", prefix, "params must hold [W, H, sh_degree, antialiased]");
  GaussianSet<T> in;
  in.means = get2("means"), in.quats = get2("quats"), in.scales = get2("scales");
  in.opacities = file.get<T, 1>(prefix + "opacities");
  in.sh = file.get<T, 3>(prefix + "sh");
  const auto viewmat = get2("viewmat"), K = get2("K");
  const auto background = file.get<T, 1>(prefix + "background");
  require(viewmat.shape(0) == 4 && viewmat.shape(1) == 4, "raster bundle: ", prefix, "viewmat must be [4, 4]");
  require(K.shape(0) == 3 && K.shape(1) == 3, "raster bundle: ", prefix, "K must be [3, 3]");
  require(background.size() == 3, "raster bundle: ", prefix, "background must be [3]");
  View<T> cam;
  for (int i = 0; i < 16; ++i) cam.world_to_camera[i] = viewmat.data()[i];
  cam.fx = K(0, 0), cam.fy = K(1, 1), cam.cx = K(0, 2), cam.cy = K(1, 2);
  cam.width = int(params(0)), cam.height = int(params(1));
  RenderOptions opt;
  opt.sh_degree = int(params(2));
  opt.antialiased = params(3) != 0;
  for (int c = 0; c < 3; ++c) opt.background[c] = double(background(c));
  RenderWorkspace<T> ws;
  RenderOutputs<T> out;
  render_forward(in, cam, opt, ws, out);

  auto expected_flat = [&](const std::string& name) {
    const auto& info = file.info(prefix + name);
    std::vector<double> v(std::size_t(info.numel()));
    switch (info.shape.size()) {
      case 1: { auto t = file.get<double, 1>(prefix + name); std::copy(t.data(), t.data() + t.size(), v.begin()); break; }
      case 2: { auto t = file.get<double, 2>(prefix + name); std::copy(t.data(), t.data() + t.size(), v.begin()); break; }
      case 3: { auto t = file.get<double, 3>(prefix + name); std::copy(t.data(), t.data() + t.size(), v.begin()); break; }
      default: fail("raster bundle: ", prefix, name, " has an unexpected rank");
    }
    return v;
  };
  auto row = [&](const std::string& name, std::span<const T> actual, Tolerance tol) {
    const auto expected = expected_flat(name);
    report.compare(prefix + name, actual, std::span<const double>(expected), tol);
  };
  const Tolerance abs_tol{ToleranceKind::absolute, 2e-5};
  row("image", out.image.span(), abs_tol);
  row("alpha", out.alpha.span(), abs_tol);
  row("depth", out.depth.span(), {ToleranceKind::relative_to_max_abs, 2e-5});
  {
    const auto expected = expected_flat("n_contrib");
    report.compare(prefix + "n_contrib", std::span<const std::int32_t>(out.n_contrib.span()),
                   std::span<const double>(expected), {ToleranceKind::exact, 0});
  }
  const auto d_image = file.get<T, 3>(prefix + "d_image");
  const auto d_alpha = file.get<T, 2>(prefix + "d_alpha");
  const auto d_depth = file.get<T, 2>(prefix + "d_depth");
  GaussianSetGrad<T> grads = make_gaussian_grad(in);
  ViewGrad<T> g_cam;
  render_backward(in, cam, opt, ws, RenderOutputGrads<T>{d_image.view(), d_alpha.view(), d_depth.view(), {}}, grads,
                  &g_cam);
  const Tolerance grad_tol{ToleranceKind::relative_to_max_abs, 1e-4};
  row("d_means", grads.means.span(), grad_tol);
  row("d_quats", grads.quats.span(), grad_tol);
  row("d_scales", grads.scales.span(), grad_tol);
  row("d_opacities", grads.opacities.span(), grad_tol);
  row("d_sh", grads.sh.span(), grad_tol);
  row("d_viewmat", std::span<const T>(g_cam.world_to_camera.data(), 16), grad_tol);
}

// Registered as the `raster` checker of `flexsplat check-reference`.
inline void check_raster_bundle(const safetensors::File& file, ReferenceReport& report) {
  const auto cases = raster_bundle_cases(file);
  require(!cases.empty(), "raster bundle '", file.path(), "' has no case<k>.params tensor");
  for (const auto& prefix : cases) check_raster_case<float>(file, prefix, report);
  std::vector<std::string> names;
  for (const auto& t : file.tensors()) names.push_back(t.name);
  report.fail_unknown(names, [&](const std::string& name) {
    for (const auto& prefix : cases)
      for (const char* input : {"params", "means", "quats", "scales", "opacities", "sh", "viewmat", "K", "background",
                                "d_image", "d_alpha", "d_depth"})
        if (name == prefix + input) return true;
    return false;
  }, "raster");
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
