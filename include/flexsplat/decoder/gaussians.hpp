#pragma once
// From the 24-value running estimate of every query to renderable world-space Gaussians. Centres follow the
// depth-guided back-projection of FlexSplat's eq. 2 in the query's reference view:
//   mu_cam = [u1 * d + dx, u2 * d + dy, d + dz],  d = D_ref(anchor) + depth value,  mu_world = R^T (mu_cam - t),
// with (u1, u2) = ((a_x - cx) / fx, (a_y - cy) / fy) the normalised image coordinates of the query's anchor
// (a = pixel-edge coordinates, so pixel u has its centre at a = u + 0.5). Backward reaches the depth maps and cameras.
#include <algorithm>
#include <cmath>
#include <span>
#include <vector>

#include "flexsplat/core/gaussians.hpp"
#include "flexsplat/decoder/constants.hpp"
#include "flexsplat/decoder/splat_head.hpp"
#include "flexsplat/nn/activations.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// Per-view inputs from the geometry stage, all contiguous: K [V,3,3], world_to_camera [V,3,4] (OpenCV),
// depth [V, depth_h, depth_w]; image_w/h is the resolution K refers to.
template <class T>
struct ViewGeometry {
  index_t views = 0, image_w = 0, image_h = 0, depth_w = 0, depth_h = 0;
  const T* K = nullptr;
  const T* world_to_camera = nullptr;
  const T* depth = nullptr;
};

template <class T>
struct ViewGeometryGrad {
  T* K = nullptr;                // [V,3,3]; only fx, fy, cx, cy receive gradients
  T* world_to_camera = nullptr;  // [V,3,4]
  T* depth = nullptr;            // [V, depth_h, depth_w]
};

template <class T>
void validate_geometry(const ViewGeometry<T>& g) {
  require(g.views >= 1, "decoder: need at least one view, got ", g.views);
  require(g.image_w >= 1 && g.image_h >= 1, "decoder: image size ", g.image_w, "x", g.image_h, " is zero-size");
  require(g.depth_w >= 1 && g.depth_h >= 1, "decoder: depth map ", g.depth_w, "x", g.depth_h, " is zero-size");
  require(g.K && g.world_to_camera && g.depth, "decoder: view geometry has null K, world_to_camera or depth");
  for (index_t v = 0; v < g.views; ++v) {
    const T* K = g.K + 9 * v;
    require(std::isfinite(K[0]) && std::isfinite(K[4]) && K[0] != T(0) && K[4] != T(0), "decoder: view ", v,
            " has focal lengths fx ", K[0], ", fy ", K[4], " (must be finite and non-zero)");
    for (int i = 0; i < 12; ++i)
      require(std::isfinite(g.world_to_camera[12 * v + i]), "decoder: view ", v, " world_to_camera[", i / 4, ",", i % 4,
              "] = ", g.world_to_camera[12 * v + i], " is not finite");
  }
}

// Each query's reference view and anchor: queries go round-robin over the views (query i -> view i mod V); the j-th
// query of a view sits at the centre of cell j of a ceil(sqrt(n_v)) x ceil(sqrt(n_v)) grid over the image.
struct Anchors {
  std::vector<index_t> view;   // [N]
  std::vector<double> pixel;   // [N, 2] pixel-edge coordinates (a_x, a_y) in the image K refers to
};

// The side of view v's square anchor grid: queries v, v + views, ... fill it row by row.
inline index_t anchor_grid(index_t n_queries, index_t views, index_t v) {
  const index_t n_v = (n_queries - v + views - 1) / views;
  index_t g = static_cast<index_t>(std::ceil(std::sqrt(static_cast<double>(n_v))));
  while (g * g < n_v) ++g;
  return g;
}

// Fills a in place (its vectors keep their capacity, so a reused Anchors does not allocate).
inline void make_anchors(Anchors& a, index_t n_queries, index_t views, index_t image_w, index_t image_h) {
  require(n_queries >= 1, "decoder: the Gaussian budget must be positive, got ", n_queries);
  require(views >= 1, "decoder: need at least one view, got ", views);
  a.view.resize(static_cast<std::size_t>(n_queries));
  a.pixel.resize(static_cast<std::size_t>(2 * n_queries));
  for (index_t v = 0; v < views; ++v) {
    const index_t n_v = (n_queries - v + views - 1) / views, g = anchor_grid(n_queries, views, v);
    for (index_t j = 0; j < n_v; ++j) {
      const index_t i = j * views + v;
      a.view[i] = v;
      a.pixel[2 * i] = (static_cast<double>(j % g) + 0.5) / static_cast<double>(g) * static_cast<double>(image_w);
      a.pixel[2 * i + 1] = (static_cast<double>(j / g) + 0.5) / static_cast<double>(g) * static_cast<double>(image_h);
    }
  }
}

inline Anchors make_anchors(index_t n_queries, index_t views, index_t image_w, index_t image_h) {
  Anchors a;
  make_anchors(a, n_queries, views, image_w, image_h);
  return a;
}

// The queries of a budget of n_queries whose anchors lie on the object: outline [views, image_h, image_w] (the
// photos' alpha or an object probability, at the anchors' image size) above 0.5 within `cells` anchor spacings of the
// anchor, so the object's edge keeps its queries. Ascending query indices (DecoderWorkspace::subset); the others
// would place Gaussians on the background.
template <class T>
std::vector<index_t> queries_on_outline(index_t n_queries, index_t views, index_t image_w, index_t image_h,
                                        const T* outline, double cells) {
  require(outline, "decoder: null outline");
  require(cells >= 0, "decoder: outline margin ", cells, " anchor spacings is negative");
  const Anchors a = make_anchors(n_queries, views, image_w, image_h);
  std::vector<index_t> grid(static_cast<std::size_t>(views));
  for (index_t v = 0; v < views; ++v) grid[static_cast<std::size_t>(v)] = anchor_grid(n_queries, views, v);
  std::vector<index_t> keep;
  for (index_t i = 0; i < n_queries; ++i) {
    const index_t v = a.view[static_cast<std::size_t>(i)], g = grid[static_cast<std::size_t>(v)];
    const double rx = cells * static_cast<double>(image_w) / static_cast<double>(g);
    const double ry = cells * static_cast<double>(image_h) / static_cast<double>(g);
    const double ax = a.pixel[2 * static_cast<std::size_t>(i)], ay = a.pixel[2 * static_cast<std::size_t>(i) + 1];
    const index_t x0 = std::max<index_t>(0, static_cast<index_t>(std::floor(ax - rx)));
    const index_t x1 = std::min<index_t>(image_w - 1, static_cast<index_t>(std::floor(ax + rx)));
    const index_t y0 = std::max<index_t>(0, static_cast<index_t>(std::floor(ay - ry)));
    const index_t y1 = std::min<index_t>(image_h - 1, static_cast<index_t>(std::floor(ay + ry)));
    const T* o = outline + v * image_h * image_w;
    bool on = false;
    for (index_t y = y0; y <= y1 && !on; ++y)
      for (index_t x = x0; x <= x1 && !on; ++x) on = o[y * image_w + x] > T(0.5);
    if (on) keep.push_back(i);
  }
  return keep;
}

// Bilinear depth lookup at pixel-edge coordinates of the image, clamped to the border (align_corners=False).
template <class T>
struct DepthTap {
  index_t index[4];
  T weight[4];
};

template <class T>
DepthTap<T> depth_tap(const ViewGeometry<T>& g, index_t view, double ax, double ay) {
  const double px = std::clamp(ax / static_cast<double>(g.image_w) * static_cast<double>(g.depth_w) - 0.5, 0.0,
                               static_cast<double>(g.depth_w - 1));
  const double py = std::clamp(ay / static_cast<double>(g.image_h) * static_cast<double>(g.depth_h) - 0.5, 0.0,
                               static_cast<double>(g.depth_h - 1));
  const index_t x0 = static_cast<index_t>(px), y0 = static_cast<index_t>(py);
  const index_t x1 = std::min(x0 + 1, g.depth_w - 1), y1 = std::min(y0 + 1, g.depth_h - 1);
  const T fx = static_cast<T>(px - static_cast<double>(x0)), fy = static_cast<T>(py - static_cast<double>(y0));
  const index_t base = view * g.depth_w * g.depth_h;
  return {{base + y0 * g.depth_w + x0, base + y0 * g.depth_w + x1, base + y1 * g.depth_w + x0, base + y1 * g.depth_w + x1},
          {(T(1) - fx) * (T(1) - fy), fx * (T(1) - fy), (T(1) - fx) * fy, fx * fy}};
}

// Base depth of every query: the predicted depth at its anchor; where that is not a usable depth (non-finite or
// nearer than near_depth) the depth of the scene centre in that view, or 1 if that is not usable either. used_map[i]
// records whether the predicted depth was used (only then does the depth map receive gradient).
template <class T>
void anchor_depths(T* base_depth, unsigned char* used_map, const ViewGeometry<T>& g, const Anchors& a,
                   const T* scene_centre) {
  const index_t n = static_cast<index_t>(a.view.size());
  for (index_t i = 0; i < n; ++i) {
    const index_t v = a.view[i];
    const DepthTap<T> tap = depth_tap(g, v, a.pixel[2 * i], a.pixel[2 * i + 1]);
    T d = 0;
    for (int c = 0; c < 4; ++c) d += tap.weight[c] * g.depth[tap.index[c]];
    used_map[i] = std::isfinite(d) && d > static_cast<T>(near_depth);
    if (!used_map[i]) {
      const T* E = g.world_to_camera + 12 * v;
      const T z = E[8] * scene_centre[0] + E[9] * scene_centre[1] + E[10] * scene_centre[2] + E[11];
      d = std::isfinite(z) && z > static_cast<T>(near_depth) ? z : T(1);
    }
    base_depth[i] = d;
  }
}

namespace detail {
// Raw pointers of a gradient set (null where a field is empty).
template <class T>
struct GaussianGradPointers {
  const T* means = nullptr;
  const T* quats = nullptr;
  const T* scales = nullptr;
  const T* opacities = nullptr;
  const T* sh = nullptr;
};

template <class T>
GaussianGradPointers<T> grad_pointers(const GaussianSetGrad<T>& d, index_t n) {
  auto ptr = [&](const auto& t, auto shape, const char* name) -> const T* {
    if (t.empty()) return nullptr;
    if (t.shape() != shape)
      fail("decoder: gradient '", name, "' has shape ", shape_string(t.shape()), ", expected ", shape_string(shape),
           " or empty");
    return t.data();
  };
  if (!d.features.empty())
    fail("decoder: its Gaussians have no features, but a features gradient of shape ", shape_string(d.features.shape()),
         " was given");
  return {ptr(d.means, Shape<2>{n, 3}, "means"), ptr(d.quats, Shape<2>{n, 4}, "quats"),
          ptr(d.scales, Shape<2>{n, 3}, "scales"), ptr(d.opacities, Shape<1>{n}, "opacities"),
          ptr(d.sh, Shape<3>{n, 4, 3}, "sh")};
}
}  // namespace detail

// state [N, 24] -> world-space Gaussians (eq. 2 centres, Splatter Image activations), SH degree 1 ([N, 4, 3]).
template <class T>
void gaussians_forward(GaussianSet<T>& out, const T* state, const T* base_depth, const Anchors& a,
                       const ViewGeometry<T>& g) {
  const index_t n = static_cast<index_t>(a.view.size());
  resize_gaussian_set(out, n, 1);
  T* means = out.means.data();
  T* quats = out.quats.data();
  T* scales = out.scales.data();
  T* opacities = out.opacities.data();
  T* sh = out.sh.data();
  for (index_t i = 0; i < n; ++i) {
    const T* s = state + i * splat_values;
    const index_t v = a.view[i];
    const T* K = g.K + 9 * v;
    const T* E = g.world_to_camera + 12 * v;
    const T u1 = (static_cast<T>(a.pixel[2 * i]) - K[2]) / K[0], u2 = (static_cast<T>(a.pixel[2 * i + 1]) - K[5]) / K[4];
    const T d = base_depth[i] + s[splat_depth];
    const T cam[3] = {u1 * d + s[splat_offset], u2 * d + s[splat_offset + 1], d + s[splat_offset + 2]};
    const T rel[3] = {cam[0] - E[3], cam[1] - E[7], cam[2] - E[11]};
    for (int j = 0; j < 3; ++j) means[3 * i + j] = E[j] * rel[0] + E[4 + j] * rel[1] + E[8 + j] * rel[2];
    quat_normalize(s + splat_quat, quats + 4 * i);
    for (int j = 0; j < 3; ++j) scales[3 * i + j] = scale_activation(s[splat_log_scale + j]);
    opacities[i] = nn::sigmoid(s[splat_opacity]);
    for (int j = 0; j < 12; ++j) sh[12 * i + j] = s[splat_sh + j];
  }
}

namespace detail {
template <class T>
void gaussians_backward(T* d_state, const ViewGeometryGrad<T>& d_geometry, const GaussianGradPointers<T>& d_out,
                        const T* state, const T* base_depth, const unsigned char* used_map, const Anchors& a,
                        const ViewGeometry<T>& g) {
  const index_t n = static_cast<index_t>(a.view.size());
  for (index_t i = 0; i < n; ++i) {
    const T* s = state + i * splat_values;
    T* ds = d_state + i * splat_values;
    if (d_out.quats) quat_normalize_vjp(s + splat_quat, d_out.quats + 4 * i, ds + splat_quat);
    for (int j = 0; j < 3 && d_out.scales; ++j)
      ds[splat_log_scale + j] += scale_activation_vjp(s[splat_log_scale + j], d_out.scales[3 * i + j]);
    if (d_out.opacities) ds[splat_opacity] += nn::sigmoid_vjp(s[splat_opacity], d_out.opacities[i]);
    for (int j = 0; j < 12 && d_out.sh; ++j) ds[splat_sh + j] += d_out.sh[12 * i + j];
    if (!d_out.means) continue;
    const index_t v = a.view[i];
    const T* K = g.K + 9 * v;
    const T* E = g.world_to_camera + 12 * v;
    const T ax = static_cast<T>(a.pixel[2 * i]), ay = static_cast<T>(a.pixel[2 * i + 1]);
    const T u1 = (ax - K[2]) / K[0], u2 = (ay - K[5]) / K[4];
    const T d = base_depth[i] + s[splat_depth];
    const T cam[3] = {u1 * d + s[splat_offset], u2 * d + s[splat_offset + 1], d + s[splat_offset + 2]};
    const T* dm = d_out.means + 3 * i;
    T d_cam[3];
    for (int r = 0; r < 3; ++r) d_cam[r] = E[4 * r] * dm[0] + E[4 * r + 1] * dm[1] + E[4 * r + 2] * dm[2];
    if (d_geometry.world_to_camera) {
      T* dE = d_geometry.world_to_camera + 12 * v;
      for (int r = 0; r < 3; ++r) {
        const T rel = cam[r] - E[4 * r + 3];
        for (int j = 0; j < 3; ++j) dE[4 * r + j] += rel * dm[j];
        dE[4 * r + 3] -= d_cam[r];
      }
    }
    for (int r = 0; r < 3; ++r) ds[splat_offset + r] += d_cam[r];
    const T d_d = u1 * d_cam[0] + u2 * d_cam[1] + d_cam[2];
    ds[splat_depth] += d_d;
    if (d_geometry.K) {
      T* dK = d_geometry.K + 9 * v;
      const T d_u1 = d * d_cam[0], d_u2 = d * d_cam[1];
      dK[0] -= d_u1 * u1 / K[0];
      dK[2] -= d_u1 / K[0];
      dK[4] -= d_u2 * u2 / K[4];
      dK[5] -= d_u2 / K[4];
    }
    if (d_geometry.depth && used_map[i]) {
      const DepthTap<T> tap = depth_tap(g, v, a.pixel[2 * i], a.pixel[2 * i + 1]);
      for (int c = 0; c < 4; ++c) d_geometry.depth[tap.index[c]] += tap.weight[c] * d_d;
    }
  }
}
}  // namespace detail

// Adds into d_state [N, 24] and the geometry gradients (null members are skipped); empty fields of d_out count as
// zero. Serial: the camera and depth gradients are shared by many queries and a fixed order keeps the sums
// deterministic.
template <class T>
void gaussians_backward(T* d_state, const ViewGeometryGrad<T>& d_geometry, const GaussianSetGrad<T>& d_out,
                        const T* state, const T* base_depth, const unsigned char* used_map, const Anchors& a,
                        const ViewGeometry<T>& g) {
  detail::gaussians_backward(d_state, d_geometry, detail::grad_pointers(d_out, static_cast<index_t>(a.view.size())),
                             state, base_depth, used_map, a, g);
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
