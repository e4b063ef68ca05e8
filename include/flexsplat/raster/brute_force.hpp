#pragma once
// Reference path without any skip: every projected Gaussian is evaluated at every pixel (no tiles, no extent, no
// early exit), scalar code, sorted with std::stable_sort. Tests compare the tiled renderer with it; it is slow by
// design. Projection and colour are the renderer's own (project_forward_one and sh_forward, whose SIMD lanes are
// bit-identical), so pixel counts compare exactly.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/raster/render.hpp"

namespace flexsplat {
inline namespace v0 {
namespace raster {

template <class T>
void render_brute_force(const GaussianSet<T>& in, const View<T>& camera, const RenderOptions& opt,
                        RenderOutputs<T>& out) {
  const int degree = detail::validate_inputs(in, camera, opt);
  const index_t n = in.means.shape(0), K = in.sh.shape(1);
  const int F = in.features.empty() ? 0 : int(in.features.shape(1));
  const ViewParams<T> cam = detail::view_params(camera);
  T campos[3];
  for (int i = 0; i < 3; ++i) campos[i] = -(cam.R[i] * cam.t[0] + cam.R[3 + i] * cam.t[1] + cam.R[6 + i] * cam.t[2]);
  struct Splat {
    T u, v, z, qa, qb, qc, o;
    std::vector<T> ch;
  };
  std::vector<Splat> splats;
  ProjectSettings<T> set;
  set.eps2d = T(opt.eps2d), set.near_plane = T(opt.near_plane), set.far_plane = T(opt.far_plane);
  set.antialiased = opt.antialiased;
  for (index_t g = 0; g < n; ++g) {
    const T* m = in.means.data() + g * 3;
    Projection<T> p;
    if (!project_forward_one(m, in.quats.data() + g * 4, in.scales.data() + g * 3, in.opacities.data()[g], cam, set, p))
      continue;
    Splat s;
    s.u = p.u, s.v = p.v, s.z = p.z;
    s.qa = p.conic[0], s.qb = p.conic[1], s.qc = p.conic[2];
    s.o = p.opacity;
    const T dir[3] = {m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]};
    T rgb[3];
    sh_forward(degree, 3, in.sh.data() + g * K * 3, dir, rgb);
    for (int c2 = 0; c2 < 3; ++c2) s.ch.push_back(std::max(T(0), rgb[c2] + T(sh_color_offset)));
    for (int f = 0; f < F; ++f) s.ch.push_back(in.features.data()[g * F + f]);
    splats.push_back(std::move(s));
  }
  std::stable_sort(splats.begin(), splats.end(), [](const Splat& a, const Splat& b) { return a.z < b.z; });
  const index_t H = camera.height, W = camera.width;
  out.image.resize({H, W, 3});
  out.alpha.resize({H, W});
  out.depth.resize({H, W});
  out.n_contrib.resize({H, W});
  out.features.resize({H, W, F});
  std::vector<T> acc(std::size_t(3 + F));
  for (index_t y = 0; y < H; ++y)
    for (index_t x = 0; x < W; ++x) {
      const T px = T(x) + T(pixel_centre_offset), py = T(y) + T(pixel_centre_offset);
      T trans = 1, depth = 0;
      std::int32_t count = 0;
      std::fill(acc.begin(), acc.end(), T(0));
      for (const Splat& s : splats) {
        const T dx = s.u - px, dy = s.v - py;
        const T sigma = T(0.5) * (s.qa * dx * dx + s.qc * dy * dy) + s.qb * dx * dy;
        const T alpha = std::min(T(max_alpha), s.o * std::exp(-sigma));
        if (!(sigma >= T(0)) || !(alpha >= T(alpha_threshold))) continue;
        const T next = trans * (T(1) - alpha);
        if (next <= T(transmittance_stop)) break;
        const T w = alpha * trans;
        for (std::size_t c = 0; c < acc.size(); ++c) acc[c] += w * s.ch[c];
        depth += w * s.z;
        trans = next;
        ++count;
      }
      for (int c = 0; c < 3; ++c) out.image(y, x, c) = acc[c] + trans * T(opt.background[c]);
      for (int f = 0; f < F; ++f) out.features(y, x, f) = acc[3 + f];
      out.alpha(y, x) = T(1) - trans;
      out.depth(y, x) = opt.expected_depth ? (trans < T(1) ? depth / (T(1) - trans) : T(0)) : depth;
      out.n_contrib(y, x) = count;
    }
}

}  // namespace raster
}  // namespace v0
}  // namespace flexsplat
