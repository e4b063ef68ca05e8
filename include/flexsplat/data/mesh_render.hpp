#pragma once
// CPU triangle rasterizer for training data: perspective-correct attributes, a z-buffer, s x s supersampled
// anti-aliasing, Lambert + ambient shading with one directional light. Outputs straight-alpha RGBA (alpha =
// coverage), metric camera-space z at the pixel centre (0 where the centre ray hits nothing) and optionally world
// normals, for any OpenCV K (last row 0 0 1) and world-to-camera. Each pixel's result depends only on the mesh and
// the camera, so any row partition across threads gives identical bytes.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/data/cameras.hpp"
#include "flexsplat/data/mesh.hpp"

namespace flexsplat {
inline namespace v0 {
namespace data {

struct RenderOptions {
  int supersample = 2;                  // s x s shading samples per pixel (regular grid)
  bool normals = false;                 // also fill RenderOutput::normals
  glm::vec3 light_direction{0, 0, 1};   // world frame, towards the light
  float ambient = 0.4f;                 // colour = albedo * (ambient + (1 - ambient) * max(0, n . l))
  double near = 1e-3;                   // triangles are clipped against camera z = near
};

struct RenderOutput {
  Tensor<float, 3> rgba;     // [H, W, 4] straight alpha
  Tensor<float, 2> depth;    // [H, W] camera-space z, 0 for background
  Tensor<float, 3> normals;  // [H, W, 3] world-frame unit normals facing the camera, 0 for background (if asked)
};

struct RenderWorkspace {
  struct Edge {
    double bx, by, dx, dy, sign;  // w(p) = sign * (dx * (p.y - by) - dy * (p.x - bx)), canonical base point
    bool owns_zero;               // tie rule: samples exactly on the edge belong to exactly one of its two triangles
  };
  struct ScreenTriangle {
    std::array<Edge, 3> edges;          // edges[k] is opposite vertex k
    std::array<double, 3> inv_z;
    std::array<glm::dvec3, 3> weights;  // vertex k = sum_j weights[k][j] * source vertex j (near clipping)
    std::uint32_t source = 0;
    bool flip = false;                  // the camera sees the back side: shading normals are negated
    int x0 = 0, x1 = 0, y0 = 0, y1 = 0;  // inclusive pixel bounds
  };
  std::vector<ScreenTriangle> triangles;
  std::vector<float> zbuffer;
  std::vector<std::int32_t> ids;
  std::vector<glm::dvec2> sample_offsets;
};

namespace detail {

inline RenderWorkspace::Edge make_edge(glm::dvec2 a, glm::dvec2 b) {
  const bool forward = a.x < b.x || (a.x == b.x && a.y < b.y);
  const glm::dvec2 base = forward ? a : b, tip = forward ? b : a;
  const glm::dvec2 d = b - a;
  return {base.x, base.y, tip.x - base.x, tip.y - base.y, forward ? 1.0 : -1.0,
          d.y > 0 || (d.y == 0 && d.x < 0)};
}

inline double edge_value(const RenderWorkspace::Edge& e, double px, double py) {
  return e.sign * (e.dx * (py - e.by) - e.dy * (px - e.bx));
}

inline bool inside(const RenderWorkspace::Edge& e, double w) { return w > 0 || (w == 0 && e.owns_zero); }

// Perspective-correct weights of the screen triangle's vertices at (px, py); returns camera z.
inline double perspective_weights(const RenderWorkspace::ScreenTriangle& tri, double px, double py, glm::dvec3& w) {
  const double l0 = edge_value(tri.edges[0], px, py), l1 = edge_value(tri.edges[1], px, py),
               l2 = edge_value(tri.edges[2], px, py);
  const double inv_area = 1.0 / (l0 + l1 + l2);
  const glm::dvec3 l(l0 * tri.inv_z[0] * inv_area, l1 * tri.inv_z[1] * inv_area, l2 * tri.inv_z[2] * inv_area);
  const double z = 1.0 / (l.x + l.y + l.z);
  w = l * z;
  return z;
}

}  // namespace detail

inline void check_camera(const Camera& cam, const char* context) {
  require(cam.width >= 1 && cam.height >= 1 && cam.width <= 16384 && cam.height <= 16384, context, ": image size ",
          cam.width, "x", cam.height, " outside [1, 16384]");
  require(cam.K[0][2] == 0 && cam.K[1][2] == 0 && cam.K[2][2] == 1 && cam.K[0][1] == 0, context,
          ": K must be upper triangular with last row (0, 0, 1)");
  require(cam.K[0][0] > 0 && cam.K[1][1] > 0, context, ": focal lengths (", cam.K[0][0], ", ", cam.K[1][1],
          ") must be positive");
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r)
      require(std::isfinite(cam.K[c][r]) && std::isfinite(cam.R[c][r]) && std::isfinite(cam.t[r]), context,
              ": camera has non-finite entries");
  const glm::dmat3 should_be_identity = glm::transpose(cam.R) * cam.R;
  double err = std::abs(glm::determinant(cam.R) - 1);
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) err = std::max(err, std::abs(should_be_identity[c][r] - (c == r ? 1.0 : 0.0)));
  require(err < 1e-4, context, ": world-to-camera R is not a rotation (orthonormality / determinant error ", err, ")");
}

// Long (about 170 lines): setup, visibility and resolve share the clipped triangles and one row-parallel loop.
inline void render_mesh(const Mesh& mesh, const Camera& cam, const RenderOptions& options, RenderOutput& out,
                        RenderWorkspace& ws, ThreadPool& pool = global_pool()) {
  check_camera(cam, "render_mesh");
  validate_mesh(mesh, "render_mesh");
  const int s = options.supersample;
  require(s >= 1 && s <= 8, "render_mesh: supersample ", s, " outside [1, 8]");
  require(options.near > 0 && std::isfinite(options.near), "render_mesh: near ", options.near, " must be positive");
  require(options.ambient >= 0 && options.ambient <= 1, "render_mesh: ambient ", options.ambient, " outside [0, 1]");
  const float light_len = glm::length(options.light_direction);
  require(light_len > 0 && std::isfinite(light_len), "render_mesh: light direction has length ", light_len);
  const glm::vec3 light = options.light_direction / light_len;
  const int W = cam.width, H = cam.height;
  const int S = s * s + 1;  // shading samples, then the pixel centre (depth and normal)

  ws.sample_offsets.clear();
  for (int j = 0; j < s; ++j)
    for (int i = 0; i < s; ++i) ws.sample_offsets.push_back({(i + 0.5) / s, (j + 0.5) / s});
  ws.sample_offsets.push_back({0.5, 0.5});

  // Setup: camera space, near clipping, projection, edge functions and pixel bounds of every triangle.
  ws.triangles.clear();
  const glm::dvec3 eye = cam.centre();
  for (std::uint32_t t = 0; t < mesh.triangles.size(); ++t) {
    const glm::uvec3 idx = mesh.triangles[t];
    const std::array<glm::dvec3, 3> world = {glm::dvec3(mesh.positions[idx.x]), glm::dvec3(mesh.positions[idx.y]),
                                             glm::dvec3(mesh.positions[idx.z])};
    std::array<glm::dvec3, 3> c;
    for (int k = 0; k < 3; ++k) c[k] = cam.to_camera(world[k]);
    if (c[0].z < options.near && c[1].z < options.near && c[2].z < options.near) continue;
    glm::dvec3 g = glm::cross(world[1] - world[0], world[2] - world[0]);
    const glm::dvec3 n_sum = glm::dvec3(mesh.normals[idx.x] + mesh.normals[idx.y] + mesh.normals[idx.z]);
    if (glm::dot(g, n_sum) < 0) g = -g;
    const bool flip = glm::dot(g, eye - world[0]) < 0;
    // Sutherland-Hodgman against z >= near; each polygon vertex carries its weights on the source vertices.
    std::array<glm::dvec3, 4> poly, poly_w;
    int count = 0;
    const std::array<glm::dvec3, 3> unit = {glm::dvec3(1, 0, 0), glm::dvec3(0, 1, 0), glm::dvec3(0, 0, 1)};
    for (int k = 0; k < 3; ++k) {
      const int k2 = (k + 1) % 3;
      const bool in_a = c[k].z >= options.near, in_b = c[k2].z >= options.near;
      if (in_a) {
        poly[count] = c[k];
        poly_w[count++] = unit[k];
      }
      if (in_a != in_b) {
        const double u = (options.near - c[k].z) / (c[k2].z - c[k].z);
        poly[count] = c[k] + u * (c[k2] - c[k]);
        poly_w[count++] = unit[k] + u * (unit[k2] - unit[k]);
      }
    }
    for (int f = 1; f + 1 < count; ++f) {
      std::array<int, 3> v = {0, f, f + 1};
      std::array<glm::dvec2, 3> p;
      for (int k = 0; k < 3; ++k) p[k] = cam.project(poly[v[k]]);
      const double area = (p[1].x - p[0].x) * (p[2].y - p[0].y) - (p[1].y - p[0].y) * (p[2].x - p[0].x);
      if (!(std::abs(area) > 1e-12)) continue;  // degenerate or edge-on (also rejects NaN)
      if (area < 0) {
        std::swap(v[1], v[2]);
        std::swap(p[1], p[2]);
      }
      RenderWorkspace::ScreenTriangle tri;
      for (int k = 0; k < 3; ++k) {
        tri.edges[k] = detail::make_edge(p[(k + 1) % 3], p[(k + 2) % 3]);
        tri.inv_z[k] = 1.0 / poly[v[k]].z;
        tri.weights[k] = poly_w[v[k]];
      }
      tri.source = t;
      tri.flip = flip;
      const double xmin = std::min({p[0].x, p[1].x, p[2].x}), xmax = std::max({p[0].x, p[1].x, p[2].x});
      const double ymin = std::min({p[0].y, p[1].y, p[2].y}), ymax = std::max({p[0].y, p[1].y, p[2].y});
      if (xmax < 0 || ymax < 0 || xmin > W || ymin > H) continue;
      tri.x0 = std::max(0, static_cast<int>(std::floor(xmin)));
      tri.x1 = std::min(W - 1, static_cast<int>(std::floor(xmax)));
      tri.y0 = std::max(0, static_cast<int>(std::floor(ymin)));
      tri.y1 = std::min(H - 1, static_cast<int>(std::floor(ymax)));
      ws.triangles.push_back(tri);
    }
  }

  const std::size_t pixels = static_cast<std::size_t>(W) * static_cast<std::size_t>(H);
  ws.zbuffer.assign(pixels * S, std::numeric_limits<float>::infinity());
  ws.ids.assign(pixels * S, -1);
  // Reuse the caller's buffers when the size matches: fresh multi-megabyte allocations cost more in page faults
  // than the rendering itself.
  auto reset = [](auto& tensor, const auto& shape) {
    if (tensor.shape() == shape) tensor.fill(0.0f);
    else tensor = std::remove_reference_t<decltype(tensor)>(shape);
  };
  reset(out.rgba, Shape<3>{H, W, 4});
  reset(out.depth, Shape<2>{H, W});
  if (options.normals) reset(out.normals, Shape<3>{H, W, 3});
  const float inv_samples = 1.0f / static_cast<float>(s * s);

  parallel_for(H, [&](index_t row_begin, index_t row_end, int) {
    // Visibility: triangles in index order, strict z test, so ties keep the lower index on any row partition.
    for (std::size_t ti = 0; ti < ws.triangles.size(); ++ti) {
      const auto& tri = ws.triangles[ti];
      const int y0 = std::max<int>(tri.y0, static_cast<int>(row_begin));
      const int y1 = std::min<int>(tri.y1, static_cast<int>(row_end) - 1);
      for (int py = y0; py <= y1; ++py) {
        // Conservative column span of the triangle in this pixel row (one pixel of margin against rounding): the
        // exact per-sample tests below decide coverage, the span only skips pixels no edge test could accept.
        double lo = tri.x0, hi = tri.x1;
        for (const auto& e : tri.edges) {
          const double a = -e.sign * e.dy, b = e.sign * e.dx, c = e.sign * (e.dy * e.bx - e.dx * e.by);
          const double rest = (b > 0 ? b * (py + 1) : b * py) + c;  // max over the row of b * y + c
          if (a > 0) lo = std::max(lo, std::floor(-rest / a) - 2);
          else if (a < 0) hi = std::min(hi, std::floor(rest / -a) + 1);
          else if (rest < 0) hi = lo - 1;
        }
        if (!(lo <= hi)) continue;
        for (int px = static_cast<int>(lo); px <= static_cast<int>(hi); ++px) {
          const std::size_t base = (static_cast<std::size_t>(py) * W + px) * S;
          for (int k = 0; k < S; ++k) {
            const double sx = px + ws.sample_offsets[k].x, sy = py + ws.sample_offsets[k].y;
            const double w0 = detail::edge_value(tri.edges[0], sx, sy);
            if (!detail::inside(tri.edges[0], w0)) continue;
            const double w1 = detail::edge_value(tri.edges[1], sx, sy);
            if (!detail::inside(tri.edges[1], w1)) continue;
            const double w2 = detail::edge_value(tri.edges[2], sx, sy);
            if (!detail::inside(tri.edges[2], w2)) continue;
            const double inv_z = (w0 * tri.inv_z[0] + w1 * tri.inv_z[1] + w2 * tri.inv_z[2]) / (w0 + w1 + w2);
            const auto z = static_cast<float>(1.0 / inv_z);
            if (z < ws.zbuffer[base + k]) {
              ws.zbuffer[base + k] = z;
              ws.ids[base + k] = static_cast<std::int32_t>(ti);
            }
          }
        }
      }
    }
    // Resolve: shade each covered sample, average; depth and normal from the centre sample.
    for (index_t py = row_begin; py < row_end; ++py)
      for (int px = 0; px < W; ++px) {
        const std::size_t base = (static_cast<std::size_t>(py) * W + px) * S;
        glm::vec3 sum(0.0f);
        int covered = 0;
        for (int k = 0; k < S; ++k) {
          const std::int32_t id = ws.ids[base + k];
          const bool centre = k == S - 1;
          if (id < 0) continue;
          const auto& tri = ws.triangles[static_cast<std::size_t>(id)];
          const double sx = px + ws.sample_offsets[k].x, sy = static_cast<double>(py) + ws.sample_offsets[k].y;
          glm::dvec3 w;
          const double z = detail::perspective_weights(tri, sx, sy, w);
          const glm::dvec3 b = w.x * tri.weights[0] + w.y * tri.weights[1] + w.z * tri.weights[2];
          const glm::uvec3 idx = mesh.triangles[tri.source];
          glm::vec3 n = glm::normalize(static_cast<float>(b.x) * mesh.normals[idx.x] +
                                       static_cast<float>(b.y) * mesh.normals[idx.y] +
                                       static_cast<float>(b.z) * mesh.normals[idx.z]);
          if (tri.flip) n = -n;
          if (centre) {
            out.depth(py, px) = static_cast<float>(z);
            if (options.normals)
              for (int c = 0; c < 3; ++c) out.normals(py, px, c) = n[c];
            continue;
          }
          const glm::vec3 tex = static_cast<float>(b.x) * mesh.texcoords[idx.x] +
                                static_cast<float>(b.y) * mesh.texcoords[idx.y] +
                                static_cast<float>(b.z) * mesh.texcoords[idx.z];
          const glm::vec3 a = albedo(mesh.materials[mesh.triangle_material[tri.source]], tex);
          sum += a * (options.ambient + (1.0f - options.ambient) * std::max(0.0f, glm::dot(n, light)));
          ++covered;
        }
        if (covered > 0) {
          const glm::vec3 rgb = glm::clamp(sum / static_cast<float>(covered), 0.0f, 1.0f);
          for (int c = 0; c < 3; ++c) out.rgba(py, px, c) = rgb[c];
          out.rgba(py, px, 3) = static_cast<float>(covered) * inv_samples;
        }
      }
  }, pool);
}

}  // namespace data
}  // namespace v0
}  // namespace flexsplat
