// Run time against error of geometry::cameras_from_orbit_search on object folders: random input view sets of each
// count, median and mean relative rotation error, the sets within 15 degrees, seconds per set, and the sets whose true
// cameras the search's own objective (geometry::orbit_search_cost) scores below the found ones: where that happens
// the search missed its minimum, where not the objective is what is wrong. Without --model the
// inputs are the renderer's silhouettes, depth and intrinsics (the ceiling of the search: what it finds when the
// model's predictions are exact). With --model the model's own predictions, then each of them swapped for the
// renderer's in turn (which prediction limits the search), and the predictions' errors.
// Usage: orbit_search [--size 56] [--sets 2] [--seed 7] [--counts 2,3,4,8] [--model M.safetensors]
//                     [--inputs mmm,rrr,...] [--depth-tolerance 0.03] [--silhouette-px 2] [--colour-weight 0.5]
//                     [--descriptor-weight 0 (with --model: its match head's descriptors)]
//                     [--descriptor-temperature 0.1] [--occluded-cost 0.1] [--samples 256] [--depth-range 0] [--depth-candidates 5]
//                     [--depth-blend 0 | --depth-grid N] [--depth-waves 0] [--depth-inflate 0]
//                     [--descriptors model|image|both|oracle] [--patch 5] [--patch-spacing 2] [--order-ensemble]
//                     [--oracle-wrong 0] [--oracle-jitter 0] [--refine-depth-grid G] [--cost-parts] OBJECT_DIR...
//   e.g. `build/experiments/orbit_search ../shared/data/objects/*`
// --inputs keeps only those input codes (silhouettes, depth, intrinsics from the renderer r or the model m); the other
// options set the search's OrbitSearchConfig fields of the same names (how tolerant it is of the predictions' errors).
// --depth-blend A (with --model, in [0, 1]): the renderer's depth given to the search is truth^(1-A) (s pred)^A, s each
// view's scale, so that the inputs with true depth measure the rotation error against the depth's error.
// --depth-grid N (with --model): the renderer's depth given to the search is its log averaged over each of N x N cells
// of the view (object pixels), then bilinear between the cells' centres: the depth an N x N token grid could carry.
// --depth-waves A: the renderer's depth given to the search is then multiplied by 1 + A sin(9.4 x + v) cos(7.5 y + 2 v)
// (x, y in [0, 1) across view v): smooth relative errors of up to A, as a learned depth's shape errors, known exactly.
// --depth-inflate k: the renderer's depth given to the search is each silhouette inflated into a shell (inflated_depth).
// --descriptors image|both: the search's descriptors are patch correlations of the photos at their own resolution
// (patch_descriptors, P = --patch samples --patch-spacing photo pixels apart), alone or beside the model's; oracle:
// features of each pixel's true world point (oracle_descriptors), what descriptors that find every correspondence give;
// --oracle-wrong q: a share q of them moved to other object pixels; --oracle-jitter R: each taken from an object pixel
// within R pixels (right only to within R; before the wrong share).
// --refine-depth-grid G (G >= 2): one more column, the sets whose true cameras cost less than the found ones once each
// view's depth is corrected by a G x G grid fitted to the search's objective at either placement (depth_refined_cost).
// --cost-parts: a table of the objective's parts (geometry::OrbitCostParts) at the found and the true cameras.
// With descriptors (the model's or --descriptors ...), a table of their accuracy on the renderer's correspondences
// (loss::match_accuracy within 1 and 4 pixels, validation's match_accuracy and match_accuracy_4px).
// --order-ensemble (with --model): the model's depth, object probability and descriptors averaged over the V cyclic
// orders of the views.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <numeric>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/solvers/orbit_search.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/layout.hpp"
#include "flexsplat/loss/geometry.hpp"
#include "flexsplat/loss/match.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/model/frames.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/model/weights.hpp"

using namespace flexsplat;

namespace {

struct Maps {
  std::vector<float> foreground, depth, K;  // [n, size, size], [n, size, size], [n, 3, 3] (VGGT integer-pixel)
};

// The renderer's maps at size x size: nearest source pixel of each view pixel's centre (the views are square).
Maps renderer_maps(const data::ObjectRecord& rec, const std::vector<int>& in, const model::PosedViews& pv, int size) {
  const int n = static_cast<int>(in.size());
  const std::size_t px = static_cast<std::size_t>(size) * static_cast<std::size_t>(size);
  Maps m;
  m.depth.resize(static_cast<std::size_t>(n) * px), m.foreground.resize(m.depth.size()), m.K.resize(9 * static_cast<std::size_t>(n));
  for (int v = 0; v < n; ++v) {
    const Tensor<double, 2> d = image::read_depth_png<double>(rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])].depth, rec.depth_scale);
    const index_t H = d.shape(0), W = d.shape(1);
    for (int y = 0; y < size; ++y)
      for (int x = 0; x < size; ++x) {
        const index_t sy = std::min<index_t>(H - 1, static_cast<index_t>((y + 0.5) * static_cast<double>(H) / size));
        const index_t sx = std::min<index_t>(W - 1, static_cast<index_t>((x + 0.5) * static_cast<double>(W) / size));
        m.depth[static_cast<std::size_t>(v) * px + static_cast<std::size_t>(y * size + x)] = static_cast<float>(d(sy, sx));
      }
  }
  for (std::size_t i = 0; i < m.foreground.size(); ++i) m.foreground[i] = m.depth[i] > 0 && pv.photos.alpha[i] > 0.5f ? 1.f : 0.f;
  model::intrinsics_to_vggt(m.K.data(), pv.photos.K.data(), n);
  return m;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

// Inside each view's true silhouette, depth becomes exp of the log depth averaged over each of g x g cells (object
// pixels; a cell without any takes the view's mean), interpolated bilinearly between the cells' centres.
void grid_depth(std::vector<float>& depth, const Maps& truth, int n, int size, int g) {
  const std::size_t px = static_cast<std::size_t>(size) * static_cast<std::size_t>(size);
  const double cell = static_cast<double>(size) / g;
  for (int v = 0; v < n; ++v) {
    const float* d = truth.depth.data() + v * px;
    const float* fg = truth.foreground.data() + v * px;
    std::vector<double> sum(static_cast<std::size_t>(g * g), 0), cnt(sum.size(), 0);
    double all = 0, all_n = 0;
    for (int y = 0; y < size; ++y)
      for (int x = 0; x < size; ++x) {
        const std::size_t i = static_cast<std::size_t>(y * size + x);
        if (!(fg[i] > 0.5f)) continue;
        const std::size_t c = static_cast<std::size_t>(std::min(g - 1, static_cast<int>(y / cell)) * g +
                                                       std::min(g - 1, static_cast<int>(x / cell)));
        sum[c] += std::log(static_cast<double>(d[i])), cnt[c] += 1, all += std::log(static_cast<double>(d[i])), all_n += 1;
      }
    if (all_n == 0) continue;
    for (std::size_t c = 0; c < sum.size(); ++c) sum[c] = cnt[c] > 0 ? sum[c] / cnt[c] : all / all_n;
    auto at = [&](int cy, int cx) { return sum[static_cast<std::size_t>(std::clamp(cy, 0, g - 1) * g + std::clamp(cx, 0, g - 1))]; };
    for (int y = 0; y < size; ++y)
      for (int x = 0; x < size; ++x) {
        const std::size_t i = static_cast<std::size_t>(y * size + x);
        if (!(fg[i] > 0.5f)) continue;
        const double fy = (y + 0.5) / cell - 0.5, fx = (x + 0.5) / cell - 0.5;
        const int y0 = static_cast<int>(std::floor(fy)), x0 = static_cast<int>(std::floor(fx));
        const double ty = fy - y0, tx = fx - x0;
        const double l = (1 - ty) * ((1 - tx) * at(y0, x0) + tx * at(y0, x0 + 1)) + ty * ((1 - tx) * at(y0 + 1, x0) + tx * at(y0 + 1, x0 + 1));
        depth[v * px + i] = static_cast<float>(std::exp(l));
      }
  }
}

// Inside each view's true silhouette, depth becomes the silhouette inflated into a round shell: at t pixels from the
// rim, z0 (1 - k sqrt(2 R t - t^2) / f), R the view's largest t and f its focal length in pixels (a sphere's front for
// k = 1), z0 chosen so that its median ratio to the renderer's depth is 1: the shape a silhouette alone implies.
void inflated_depth(Maps& truth, int n, int size, double k) {
  const std::size_t px = static_cast<std::size_t>(size) * static_cast<std::size_t>(size);
  for (int v = 0; v < n; ++v) {
    geometry::orbit_detail::View view;
    view.h = view.w = size;
    view.mask.resize(px);
    for (std::size_t i = 0; i < px; ++i) view.mask[i] = !(truth.foreground[v * px + i] > 0.5f);
    geometry::orbit_detail::chamfer_outside(view);
    double R = 0;
    for (std::size_t i = 0; i < px; ++i) if (!view.mask[i]) R = std::max(R, static_cast<double>(view.outside[i]));
    const double f = truth.K[9 * static_cast<std::size_t>(v)];
    std::vector<double> shell(px, 0), ratio;
    for (std::size_t i = 0; i < px; ++i) {
      if (view.mask[i]) continue;
      const double t = view.outside[i];
      shell[i] = 1 - k * std::sqrt(std::max(0.0, 2 * R * t - t * t)) / f;
      ratio.push_back(truth.depth[v * px + i] / shell[i]);
    }
    if (ratio.empty()) continue;
    const double z0 = median(ratio);
    for (std::size_t i = 0; i < px; ++i) if (!view.mask[i]) truth.depth[v * px + i] = static_cast<float>(z0 * shell[i]);
  }
}

// Each view pixel's descriptor from its photo at the photo's own resolution: a P x P grid of RGB samples (over white,
// bilinear) `spacing` photo pixels apart around the pixel's centre, each channel's mean removed (NCC-like once the
// search normalises it); zero where the patch is flat. [n, size, size, 3 P^2].
std::vector<float> patch_descriptors(const data::ObjectRecord& rec, const std::vector<int>& in, int size, int P, double spacing) {
  const int n = static_cast<int>(in.size()), dim = 3 * P * P;
  std::vector<float> out(static_cast<std::size_t>(n) * size * size * dim, 0.f);
  for (int v = 0; v < n; ++v) {
    const Tensor<float, 3> im = image::read_rgb<float>(rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])].image);
    const index_t H = im.shape(0), W = im.shape(1);
    auto px = [&](index_t y, index_t x, int c) {
      return double(im(std::clamp<index_t>(y, 0, H - 1), std::clamp<index_t>(x, 0, W - 1), c));
    };
    auto sample = [&](double y, double x, int c) {
      const double fy = std::floor(y), fx = std::floor(x), ty = y - fy, tx = x - fx;
      const index_t y0 = static_cast<index_t>(fy), x0 = static_cast<index_t>(fx);
      return (1 - ty) * ((1 - tx) * px(y0, x0, c) + tx * px(y0, x0 + 1, c)) + ty * ((1 - tx) * px(y0 + 1, x0, c) + tx * px(y0 + 1, x0 + 1, c));
    };
    std::vector<double> d(static_cast<std::size_t>(dim));
    for (int y = 0; y < size; ++y)
      for (int x = 0; x < size; ++x) {
        const double cy = (y + 0.5) * static_cast<double>(H) / size - 0.5, cx = (x + 0.5) * static_cast<double>(W) / size - 0.5;
        for (int c = 0; c < 3; ++c) {
          double mean = 0;
          for (int j = 0; j < P * P; ++j) {
            const double oy = (j / P - (P - 1) / 2.0) * spacing, ox = (j % P - (P - 1) / 2.0) * spacing;
            mean += d[static_cast<std::size_t>(c * P * P + j)] = sample(cy + oy, cx + ox, c);
          }
          mean /= P * P;
          for (int j = 0; j < P * P; ++j) d[static_cast<std::size_t>(c * P * P + j)] -= mean;
        }
        double norm = 0;
        for (double e : d) norm += e * e;
        if (std::sqrt(norm) < 1e-2) continue;
        float* o = out.data() + ((static_cast<std::size_t>(v) * size + y) * size + x) * dim;
        for (int j = 0; j < dim; ++j) o[j] = static_cast<float>(d[static_cast<std::size_t>(j)] / std::sqrt(norm));
      }
  }
  return out;
}

// 1 / the length of a descriptor, 0 for a zero or broken one (which the search treats as no descriptor).
double inverse_length(const float* d, index_t dim) {
  double sq = 0;
  for (index_t j = 0; j < dim; ++j) sq += double(d[j]) * d[j];
  return sq > 0 && std::isfinite(sq) ? 1 / std::sqrt(sq) : 0;
}

// --descriptors oracle: random Fourier features of each pixel's true world point (the renderer's depth and cameras),
// so that two pixels' cosine is about exp(-|x - y|^2 / (2 s^2)), s 3 % of the median depth: descriptors that find
// every true correspondence and nothing else; zero off the true silhouette.
std::vector<float> oracle_descriptors(index_t& dim, const Maps& truth, const model::PosedViews& pv, int n, int size,
                                      double wrong, double jitter) {
  constexpr index_t D = 64;
  dim = D;
  const std::size_t px = static_cast<std::size_t>(size) * static_cast<std::size_t>(size);
  std::vector<double> z;
  for (std::size_t i = 0; i < truth.depth.size(); ++i)
    if (truth.foreground[i] > 0.5f) z.push_back(truth.depth[i]);
  require(!z.empty(), "orbit_search: --descriptors oracle: no object pixels in the renderer's views");
  const double sigma = 0.03 * median(z);
  std::mt19937 rng(1234);
  std::normal_distribution<double> normal(0.0, 1.0 / sigma);
  std::uniform_real_distribution<double> phase(0.0, 2 * std::numbers::pi);
  std::vector<glm::dvec3> w(D);
  std::vector<double> b(D);
  for (index_t k = 0; k < D; ++k) w[static_cast<std::size_t>(k)] = glm::dvec3(normal(rng), normal(rng), normal(rng)), b[static_cast<std::size_t>(k)] = phase(rng);
  std::vector<float> out(static_cast<std::size_t>(n) * px * D, 0.f);
  for (int v = 0; v < n; ++v) {
    const std::vector<double> cam = geometry::camera_frame_points(truth.depth.data(), truth.K.data(), v, size, size);
    const float* E = pv.w2c.data() + 12 * v;
    for (std::size_t p = 0; p < px; ++p) {
      if (!(truth.foreground[static_cast<std::size_t>(v) * px + p] > 0.5f)) continue;
      glm::dvec3 X(cam[3 * p], cam[3 * p + 1], cam[3 * p + 2]), Y(0.0);
      for (int r = 0; r < 3; ++r) X[r] -= E[4 * r + 3];
      for (int c = 0; c < 3; ++c)
        for (int r = 0; r < 3; ++r) Y[c] += static_cast<double>(E[4 * r + c]) * X[r];  // R^T (x - t)
      float* o = out.data() + (static_cast<std::size_t>(v) * px + p) * D;
      for (index_t k = 0; k < D; ++k) o[k] = static_cast<float>(std::cos(glm::dot(w[static_cast<std::size_t>(k)], Y) + b[static_cast<std::size_t>(k)]));
    }
  }
  // Each object pixel p of view v takes the descriptor that view had at pixel source(v, p) (p: its own).
  auto remap = [&](auto&& source) {
    for (int v = 0; v < n; ++v) {
      const std::size_t base = static_cast<std::size_t>(v) * px;
      const std::vector<float> kept(out.begin() + static_cast<std::ptrdiff_t>(base * D),
                                    out.begin() + static_cast<std::ptrdiff_t>((base + px) * D));
      for (std::size_t p = 0; p < px; ++p) {
        if (!(truth.foreground[base + p] > 0.5f)) continue;
        const std::size_t q = source(v, p);
        std::copy(kept.begin() + static_cast<std::ptrdiff_t>(q * D), kept.begin() + static_cast<std::ptrdiff_t>((q + 1) * D),
                  out.begin() + static_cast<std::ptrdiff_t>((base + p) * D));
      }
    }
  };
  // An object pixel drawn uniformly within `jitter` pixels: a matcher that finds every correspondence only to within
  // that radius.
  if (jitter > 0) {
    const int r = static_cast<int>(std::floor(jitter)), s = size;
    std::uniform_int_distribution<int> offset(-r, r);
    remap([&](int v, std::size_t p) {
      const int x = static_cast<int>(p % static_cast<std::size_t>(s)), y = static_cast<int>(p / static_cast<std::size_t>(s));
      for (int tries = 0; tries < 64; ++tries) {  // rejection: within the disc and on the object
        const int dx = offset(rng), dy = offset(rng), qx = x + dx, qy = y + dy;
        if (dx * dx + dy * dy > jitter * jitter || qx < 0 || qy < 0 || qx >= s || qy >= s) continue;
        const std::size_t q = static_cast<std::size_t>(qy) * static_cast<std::size_t>(s) + static_cast<std::size_t>(qx);
        if (truth.foreground[static_cast<std::size_t>(v) * px + q] > 0.5f) return q;
      }
      return p;
    });
  }
  // A fraction `wrong` of each view's object pixels takes another object pixel's descriptor: a matcher that finds that
  // share of the correspondences elsewhere on the object.
  if (wrong > 0) {
    std::vector<std::vector<std::size_t>> object(static_cast<std::size_t>(n));
    for (int v = 0; v < n; ++v)
      for (std::size_t p = 0; p < px; ++p)
        if (truth.foreground[static_cast<std::size_t>(v) * px + p] > 0.5f) object[static_cast<std::size_t>(v)].push_back(p);
    std::uniform_real_distribution<double> coin(0.0, 1.0);
    remap([&](int v, std::size_t p) {
      if (coin(rng) >= wrong) return p;
      const std::vector<std::size_t>& on = object[static_cast<std::size_t>(v)];
      return on[std::uniform_int_distribution<std::size_t>(0, on.size() - 1)(rng)];
    });
  }
  return out;
}

// The descriptors the search reads, --descriptors image|both: the patch descriptors alone, or beside the model's
// [pixels, md] ones with each half of unit length over 2^0.5, so that the cosine is the mean of the two (zero where
// the patch is flat).
std::vector<float> image_descriptors(index_t& dim, const data::ObjectRecord& rec, const std::vector<int>& in, int size,
                                     int patch, double spacing, const std::vector<float>& model, index_t md) {
  std::vector<float> image = patch_descriptors(rec, in, size, patch, spacing);
  const index_t pd = 3 * patch * patch;
  dim = pd;
  if (md == 0) return image;
  const std::size_t pixels = image.size() / static_cast<std::size_t>(pd);
  std::vector<float> joint(pixels * static_cast<std::size_t>(md + pd), 0.f);
  for (std::size_t i = 0; i < pixels; ++i) {
    const double im = inverse_length(image.data() + i * pd, pd), mm = inverse_length(model.data() + i * md, md);
    if (im == 0) continue;
    float* o = joint.data() + i * static_cast<std::size_t>(md + pd);
    for (index_t j = 0; j < md; ++j) o[j] = static_cast<float>(model[i * md + j] * mm / std::sqrt(2.0));
    for (index_t j = 0; j < pd; ++j) o[md + j] = static_cast<float>(image[i * pd + j] * im / std::sqrt(2.0));
  }
  dim = md + pd;
  return joint;
}

struct Errors {
  std::vector<double> rotation;
  double seconds = 0;
  int truth_cheaper = 0, off = 0, off_truth_cheaper = 0;  // sets whose true cameras cost less than the found ones
  int grid_truth_cheaper = 0, grid_off_truth_cheaper = 0;  // the same with depth grids fitted (--refine-depth-grid)
  geometry::OrbitCostParts found_parts, truth_parts, off_found_parts, off_truth_parts;  // summed over the sets (--cost-parts)
};


// The search's objective at fixed cameras E once each view's depth is multiplied by exp of a G x G grid (bilinear
// between the cells' centres, within +-0.3), the grids fitted to that objective by coordinate descent: whether depth
// corrected by the views themselves would make the true cameras the cheaper placement.
template <class T>
double depth_refined_cost(const T* E, const T* images, const T* fg, const T* depth, const T* K, index_t n, index_t size,
                          const geometry::OrbitSearchConfig& cfg, const geometry::OrbitDescriptors<T>& desc, int G) {
  using namespace geometry::orbit_detail;
  std::vector<View> act;
  std::vector<index_t> active;
  prepare_views(act, active, images, fg, depth, K, n, size, size, cfg, desc);
  const std::size_t A = act.size();
  if (A < 2) return 0;
  const std::vector<Placed> placed = placed_cameras(E, K, active, size, size);
  std::vector<std::vector<float>> base_depth(A);
  std::vector<std::vector<double>> base_point(A), point_x(A), point_y(A);
  std::vector<std::vector<double>> grid(A, std::vector<double>(static_cast<std::size_t>(G * G), 0.0));
  for (std::size_t a = 0; a < A; ++a) {
    base_depth[a] = act[a].depth, base_point[a] = act[a].point;
    for (std::size_t i = 0; i < act[a].point.size() / 3; ++i) {
      const double X = act[a].point[3 * i], Y = act[a].point[3 * i + 1], Z = act[a].point[3 * i + 2];
      point_x[a].push_back(act[a].fx * X / Z + act[a].cx), point_y[a].push_back(act[a].fy * Y / Z + act[a].cy);
    }
  }
  const double cell = static_cast<double>(size) / G;
  auto factor = [&](std::size_t a, double x, double y) {
    const double gx = std::clamp((x + 0.5) / cell - 0.5, 0.0, G - 1.0), gy = std::clamp((y + 0.5) / cell - 0.5, 0.0, G - 1.0);
    const int x0 = std::min(static_cast<int>(gx), G - 2), y0 = std::min(static_cast<int>(gy), G - 2);
    const double ax = gx - x0, ay = gy - y0;
    const auto& g = grid[a];
    const double l = (1 - ax) * (1 - ay) * g[static_cast<std::size_t>(y0 * G + x0)] + ax * (1 - ay) * g[static_cast<std::size_t>(y0 * G + x0 + 1)] +
                     (1 - ax) * ay * g[static_cast<std::size_t>((y0 + 1) * G + x0)] + ax * ay * g[static_cast<std::size_t>((y0 + 1) * G + x0 + 1)];
    return std::exp(l);
  };
  auto apply = [&](std::size_t a) {
    View& v = act[a];
    for (index_t y = 0; y < size; ++y)
      for (index_t x = 0; x < size; ++x) {
        const std::size_t p = static_cast<std::size_t>(y * size + x);
        v.depth[p] = static_cast<float>(base_depth[a][p] * factor(a, static_cast<double>(x), static_cast<double>(y)));
      }
    for (std::size_t i = 0; i < point_x[a].size(); ++i) {
      const double f = factor(a, point_x[a][i], point_y[a][i]);
      for (int k = 0; k < 3; ++k) v.point[3 * i + static_cast<std::size_t>(k)] = base_point[a][3 * i + static_cast<std::size_t>(k)] * f;
    }
  };
  // Grid nodes next to an object pixel.
  std::vector<std::vector<int>> nodes(A);
  for (std::size_t a = 0; a < A; ++a)
    for (int gy = 0; gy < G; ++gy)
      for (int gx = 0; gx < G; ++gx) {
        bool near = false;
        for (index_t y = 0; y < size && !near; ++y)
          for (index_t x = 0; x < size && !near; ++x)
            near = act[a].mask[static_cast<std::size_t>(y * size + x)] && std::abs((x + 0.5) / cell - 0.5 - gx) < 1 &&
                   std::abs((y + 0.5) / cell - 0.5 - gy) < 1;
        if (near) nodes[a].push_back(gy * G + gx);
      }
  for (const double step : {0.08, 0.04, 0.02, 0.01})
    for (int sweep = 0; sweep < 2; ++sweep)
      for (std::size_t a = 0; a < A; ++a)
        for (const int node : nodes[a]) {
          double& g = grid[a][static_cast<std::size_t>(node)];
          const double keep = g, cur = view_cost(act, placed, static_cast<index_t>(a), placed[a], cfg);
          double best = cur, best_g = keep;
          for (const double sign : {1.0, -1.0}) {
            g = std::clamp(keep + sign * step, -0.3, 0.3);
            apply(a);
            const double c = view_cost(act, placed, static_cast<index_t>(a), placed[a], cfg);
            if (c < best) best = c, best_g = g;
          }
          g = best_g;
          apply(a);
        }
  return total_cost(act, placed, cfg);
}

}  // namespace

int main(int argc, char** argv) try {
  int size = 56, sets = 2;
  unsigned seed = 7;
  std::vector<int> counts{2, 3, 4, 8};
  std::vector<std::string> dirs;
  std::string model_path, keep;
  geometry::OrbitSearchConfig search;
  int refine_grid = 0;  // --refine-depth-grid G
  bool cost_parts = false;
  double oracle_wrong = 0;  // --oracle-wrong q
  double oracle_jitter = 0;  // --oracle-jitter R
  double blend = 0;
  int grid = 0;
  double waves = 0, inflate = 0, patch_spacing = 2;
  std::string descriptor_source = "model";
  int patch = 5;
  bool ensemble = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const bool more = i + 1 < argc;
    if (a == "--size" && more) size = std::stoi(argv[++i]);
    else if (a == "--sets" && more) sets = std::stoi(argv[++i]);
    else if (a == "--seed" && more) seed = static_cast<unsigned>(std::stoul(argv[++i]));
    else if (a == "--model" && more) model_path = argv[++i];
    else if (a == "--inputs" && more) keep = argv[++i];
    else if (a == "--depth-tolerance" && more) search.depth_tolerance = std::stod(argv[++i]);
    else if (a == "--depth-range" && more) search.depth_range = std::stod(argv[++i]);
    else if (a == "--depth-candidates" && more) search.depth_candidates = std::stoll(argv[++i]);
    else if (a == "--silhouette-px" && more) search.silhouette_px = std::stod(argv[++i]);
    else if (a == "--colour-weight" && more) search.colour_weight = std::stod(argv[++i]);
    else if (a == "--descriptor-weight" && more) search.descriptor_weight = std::stod(argv[++i]);
    else if (a == "--descriptor-temperature" && more) search.descriptor_temperature = std::stod(argv[++i]);
    else if (a == "--occluded-cost" && more) search.occluded_cost = std::stod(argv[++i]);
    else if (a == "--samples" && more) search.samples = std::stoll(argv[++i]);
    else if (a == "--refine-depth-grid" && more) refine_grid = std::stoi(argv[++i]);
    else if (a == "--cost-parts") cost_parts = true;
    else if (a == "--oracle-wrong" && more) oracle_wrong = std::stod(argv[++i]);
    else if (a == "--oracle-jitter" && more) oracle_jitter = std::stod(argv[++i]);
    else if (a == "--depth-blend" && more) blend = std::stod(argv[++i]);
    else if (a == "--depth-grid" && more) grid = std::stoi(argv[++i]);
    else if (a == "--depth-waves" && more) waves = std::stod(argv[++i]);
    else if (a == "--depth-inflate" && more) inflate = std::stod(argv[++i]);
    else if (a == "--order-ensemble") ensemble = true;
    else if (a == "--descriptors" && more) descriptor_source = argv[++i];
    else if (a == "--patch" && more) patch = std::stoi(argv[++i]);
    else if (a == "--patch-spacing" && more) patch_spacing = std::stod(argv[++i]);
    else if (a == "--counts" && more) {
      counts.clear();
      std::string s = argv[++i];
      for (std::size_t p = 0; p < s.size();) {
        const std::size_t q = s.find(',', p);
        counts.push_back(std::stoi(s.substr(p, q - p)));
        p = q == std::string::npos ? s.size() : q + 1;
      }
    } else dirs.push_back(a);
  }
  require(!dirs.empty() && size >= 8 && sets >= 1,
          "usage: orbit_search [--size N] [--sets N] [--seed N] [--counts 2,3,4,8] [--model M.safetensors] "
          "[--inputs mmm,rrr,...] [--depth-tolerance X] [--silhouette-px X] [--colour-weight X] [--descriptor-weight X] "
          "[--descriptor-temperature X] [--occluded-cost X] [--samples N] [--depth-range X] "
          "[--depth-candidates N] [--depth-blend A | --depth-grid N] [--depth-waves A] [--depth-inflate k] "
          "[--descriptors model|image|both|oracle] [--patch P] [--patch-spacing S] [--order-ensemble] "
          "[--oracle-wrong Q] [--oracle-jitter R] [--refine-depth-grid G] [--cost-parts] OBJECT_DIR...");
  require(blend >= 0 && blend <= 1 && (blend == 0 || !model_path.empty()), "orbit_search: --depth-blend ", blend,
          " must be in [0, 1] and needs --model");
  require(grid >= 0 && (grid == 0 || (!model_path.empty() && blend == 0)), "orbit_search: --depth-grid ", grid,
          " must be >= 0, needs --model and excludes --depth-blend");
  require(waves >= 0 && waves < 1, "orbit_search: --depth-waves ", waves, " must be in [0, 1)");
  require(inflate >= 0 && inflate <= 2 && (inflate == 0 || grid == 0), "orbit_search: --depth-inflate ", inflate,
          " must be in [0, 2] and excludes --depth-grid");
  require(descriptor_source == "model" || descriptor_source == "image" || descriptor_source == "oracle" ||
              (descriptor_source == "both" && !model_path.empty()),
          "orbit_search: --descriptors '", descriptor_source, "' must be model, image, both or oracle (both needs --model)");
  require(!ensemble || !model_path.empty(), "orbit_search: --order-ensemble needs --model");
  require(oracle_wrong >= 0 && oracle_wrong <= 1 && (oracle_wrong == 0 || descriptor_source == "oracle"),
          "orbit_search: --oracle-wrong ", oracle_wrong, " must be in [0, 1] and needs --descriptors oracle");
  require(oracle_jitter >= 0 && oracle_jitter <= 16 && (oracle_jitter == 0 || descriptor_source == "oracle"),
          "orbit_search: --oracle-jitter ", oracle_jitter, " must be in [0, 16] and needs --descriptors oracle");
  require(refine_grid == 0 || (refine_grid >= 2 && refine_grid <= 64), "orbit_search: --refine-depth-grid ", refine_grid,
          " must be in [2, 64]");
  require(patch >= 1 && patch <= 15 && patch_spacing > 0 && patch_spacing <= 16, "orbit_search: --patch ", patch,
          " must be in [1, 15] and --patch-spacing ", patch_spacing, " in (0, 16]");
  std::unique_ptr<model::FlexSplatWeights<float>> w;
  if (!model_path.empty()) {
    w = model::load_flexsplat<float>(model_path);
    require(w->config().geometry.match_dim > 0, "orbit_search: model '", model_path,
            "' has no match head (the search needs its object probability)");
    require(w->config().image_h == w->config().image_w, "orbit_search: the model's views are not square");
    size = static_cast<int>(w->config().image_h);
  }
  std::vector<data::ObjectRecord> objects;
  for (const auto& d : dirs) objects.push_back(data::load_object(d));
  // Input sources: which maps come from the renderer (r) and which from the model (m): silhouettes, depth, intrinsics.
  std::vector<std::pair<std::string, std::string>> sources =
      w ? std::vector<std::pair<std::string, std::string>>{{"model", "mmm"}, {"model, true silhouettes", "rmm"},
                                                            {"model, true depth", "mrm"}, {"model, true intrinsics", "mmr"},
                                                            {"renderer", "rrr"}}
        : std::vector<std::pair<std::string, std::string>>{{"renderer", "rrr"}};
  if (!keep.empty()) {
    std::erase_if(sources, [&](const auto& s) { return ("," + keep + ",").find("," + s.second + ",") == std::string::npos; });
    require(!sources.empty(), "orbit_search: --inputs '", keep, "' names none of ", w ? "mmm, rmm, mrm, mmr, rrr" : "rrr",
            " (the model's codes need --model)");
  }
  std::mt19937 rng(seed);
  const bool altered = blend > 0 || grid > 0 || waves > 0 || inflate > 0;  // the renderer's depth searched is not the renderer's own
  std::printf("| views | inputs | sets | median error | mean error | within 15° | seconds per set | true cameras cost less: all "
              "sets, sets off by > 15° |%s\n|---|---|---|---|---|---|---|---|%s\n",
              refine_grid > 0 ? " the same with depth grids fitted |" : "", refine_grid > 0 ? "---|" : "");
  std::vector<std::string> quality, parts_rows, accuracy_rows;
  for (const int n : counts) {
    std::map<std::string, Errors> errors;
    double iou = 0, shape = 0, flat = 0, focal = 0, searched = 0;
    double correspondences = 0, hits1 = 0, hits4 = 0;  // the search's descriptors on the renderer's correspondences
    int measured = 0;
    for (const auto& rec : objects) {
      const int frames = static_cast<int>(rec.frames.size());
      require(n >= 2 && n <= frames, "orbit_search: ", n, " views asked of ", rec.dir.string(), " (", frames, " frames)");
      for (int s = 0; s < sets; ++s) {
        std::vector<int> all(static_cast<std::size_t>(frames));
        std::iota(all.begin(), all.end(), 0);
        std::shuffle(all.begin(), all.end(), rng);
        const std::vector<int> in(all.begin(), all.begin() + n);
        const model::PosedViews pv = model::posed_views(rec, in, size, size);
        const std::size_t px = static_cast<std::size_t>(size) * static_cast<std::size_t>(size);
        const Maps truth = renderer_maps(rec, in, pv, size);
        Maps prior = truth;  // the renderer's maps with the depth searched in place of its own
        if (inflate > 0) inflated_depth(prior, n, size, inflate);
        // The search takes [n, 3, size, size]; the photos are [n, size, size, 3].
        std::vector<float> images(static_cast<std::size_t>(n) * 3 * px);
        for (std::size_t v = 0; v < static_cast<std::size_t>(n); ++v)
          image::hwc_to_chw(images.data() + v * 3 * px, pv.photos.images.data() + v * 3 * px, size, size);
        Maps pred;
        std::vector<float> descriptors;  // the search's [n, size, size, dim]: the model's, or --descriptors image|both
        std::vector<double> sp;     // each view's predicted depth scale to the renderer's
        std::vector<float> filled = prior.depth;  // the renderer's depth where it has one, else the prediction's scaled
        std::vector<float> gt(truth.depth.size());  // the renderer's depth inside its silhouettes
        for (std::size_t i = 0; i < gt.size(); ++i) gt[i] = truth.foreground[i] > 0.5f ? truth.depth[i] : 0.f;
        if (w) {
          std::vector<Tensor<float, 3>> rgba;
          for (int v : in) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
          const Tensor<float, 4> x = model::model_input<float>(rgba, w->config());
          images.assign(x.data(), x.data() + x.size());
          model::PredictWorkspace<float> ws;
          model::predict<float>(ws, *w, TensorView<const float, 4>(x.view()));
          const auto& o = ws.geometry.outputs;
          pred.foreground.assign(o.foreground.data(), o.foreground.data() + o.foreground.size());
          pred.depth.assign(o.depth.data(), o.depth.data() + o.depth.size());
          pred.K.assign(o.intrinsics.data(), o.intrinsics.data() + o.intrinsics.size());
          descriptors.assign(o.descriptors.data(), o.descriptors.data() + o.descriptors.size());
          if (ensemble) {
            // The same photos with each view first in turn (cyclic orders): each view's depth scaled to the first order's
            // (median ratio on its object pixels) and averaged in log, its object probability and unit descriptors
            // averaged.
            const index_t md = w->config().geometry.match_dim;
            std::vector<double> logd(pred.depth.size()), fgsum(pred.foreground.begin(), pred.foreground.end());
            std::vector<double> dsum(descriptors.size(), 0);
            auto add_desc = [&](const float* src, std::size_t dst_px) {
              const double inv = inverse_length(src, md);
              if (inv > 0) for (index_t j = 0; j < md; ++j) dsum[dst_px * md + j] += src[j] * inv;
            };
            for (std::size_t i = 0; i < logd.size(); ++i) logd[i] = std::log(std::max(1e-6f, pred.depth[i]));
            for (std::size_t i = 0; i < logd.size(); ++i) add_desc(descriptors.data() + i * md, i);
            for (int r = 1; r < n; ++r) {
              std::vector<Tensor<float, 3>> turned;
              for (int j = 0; j < n; ++j) turned.push_back(rgba[static_cast<std::size_t>((j + r) % n)]);
              const Tensor<float, 4> xr = model::model_input<float>(turned, w->config());
              model::PredictWorkspace<float> wr;
              model::predict<float>(wr, *w, TensorView<const float, 4>(xr.view()));
              const auto& orr = wr.geometry.outputs;
              for (int j = 0; j < n; ++j) {
                const std::size_t v = static_cast<std::size_t>((j + r) % n), a = v * px, b = static_cast<std::size_t>(j) * px;
                std::vector<double> ratio;
                for (std::size_t i = 0; i < px; ++i)
                  if (pred.foreground[a + i] >= 0.5f) ratio.push_back(double(pred.depth[a + i]) / orr.depth.data()[b + i]);
                const double sc = ratio.empty() ? 1.0 : median(ratio);
                for (std::size_t i = 0; i < px; ++i) {
                  logd[a + i] += std::log(std::max(1e-6, sc * orr.depth.data()[b + i]));
                  fgsum[a + i] += orr.foreground.data()[b + i];
                  add_desc(orr.descriptors.data() + (b + i) * md, a + i);
                }
              }
            }
            for (std::size_t i = 0; i < logd.size(); ++i) {
              pred.depth[i] = static_cast<float>(std::exp(logd[i] / n));
              pred.foreground[i] = static_cast<float>(fgsum[i] / n);
            }
            for (std::size_t i = 0; i < dsum.size(); ++i) descriptors[i] = static_cast<float>(dsum[i]);
          }
          // The predictions' errors: silhouette IoU, depth after each view's median scale (its shape), the same for a
          // constant depth per view (no shape at all), focal length.
          std::vector<float> constant(truth.depth.size(), 1.f);
          sp.resize(static_cast<std::size_t>(n));
          shape += n * loss::depth_scaled_error(pred.depth.data(), gt.data(), n, static_cast<index_t>(px), sp.data());
          flat += n * loss::depth_scaled_error(constant.data(), gt.data(), n, static_cast<index_t>(px));
          for (int v = 0; v < n; ++v) {
            double inter = 0, uni = 0;
            for (std::size_t i = v * px; i < (v + 1) * px; ++i) {
              const bool p = pred.foreground[i] >= 0.5f, g = truth.foreground[i] > 0.5f;
              inter += p && g, uni += p || g;
            }
            iou += uni > 0 ? inter / uni : 1;
            focal += std::abs(pred.K[9 * static_cast<std::size_t>(v)] / truth.K[9 * static_cast<std::size_t>(v)] - 1);
            ++measured;
          }
          // Renderer depth next to predicted silhouettes, whose pixels may have no true depth (the search reads depth only
          // inside a silhouette, so the renderer's silhouettes see the renderer's depth alone).
          for (int v = 0; v < n; ++v)
            for (std::size_t i = v * px; i < (v + 1) * px; ++i)
              filled[i] = static_cast<float>(
                  truth.foreground[i] > 0.5f
                      ? std::pow(static_cast<double>(prior.depth[i]), 1 - blend) *
                            std::pow(sp[static_cast<std::size_t>(v)] * pred.depth[i], blend)
                      : sp[static_cast<std::size_t>(v)] * pred.depth[i]);
          if (grid > 0) grid_depth(filled, truth, n, size, grid);
        }
        if (waves > 0)
          for (int v = 0; v < n; ++v)
            for (std::size_t i = v * px; i < (v + 1) * px; ++i) {
              const double x = static_cast<double>((i - v * px) % static_cast<std::size_t>(size)) / size;
              const double y = static_cast<double>((i - v * px) / static_cast<std::size_t>(size)) / size;
              filled[i] *= static_cast<float>(1 + waves * std::sin(9.4 * x + v) * std::cos(7.5 * y + 2 * v));
            }
        if (w || altered) searched += n * loss::depth_scaled_error(filled.data(), gt.data(), n, static_cast<index_t>(px));
        index_t desc_dim = w ? w->config().geometry.match_dim : 0;
        if (descriptor_source == "oracle")
          descriptors = oracle_descriptors(desc_dim, truth, pv, n, size, oracle_wrong, oracle_jitter);
        else if (descriptor_source != "model")
          descriptors = image_descriptors(desc_dim, rec, in, size, patch, patch_spacing, descriptors,
                                          descriptor_source == "both" ? desc_dim : 0);
        const geometry::OrbitDescriptors<float> desc{descriptors.empty() ? nullptr : descriptors.data(), desc_dim};
        if (!descriptors.empty()) {  // as validation's match_accuracy: nearest descriptor within 1 and 4 pixels
          const std::vector<loss::PixelMatch> truth_matches =
              loss::ground_truth_matches(truth.depth.data(), pv.photos.K.data(), pv.w2c.data(), n, size, size, 256);
          const double m = static_cast<double>(truth_matches.size());
          correspondences += m;
          const std::span<const loss::PixelMatch> matches(truth_matches);
          const std::vector<index_t> nearest = loss::nearest_descriptor_pixels(descriptors.data(), matches, n, size, size, desc_dim);
          hits1 += loss::match_hits(nearest, matches, size, 1);
          hits4 += loss::match_hits(nearest, matches, size, 4);
        }
        for (const auto& source : sources) {
          const std::string &name = source.first, &from = source.second;  // a lambda cannot capture a binding (clang 14)
          auto pick = [&](int k) -> const Maps& { return from[static_cast<std::size_t>(k)] == 'r' ? truth : pred; };
          std::vector<float> E(12 * static_cast<std::size_t>(n));
          const auto t0 = std::chrono::steady_clock::now();
          const float* depth = from[1] == 'r' ? filled.data() : pred.depth.data();
          double found_cost = 0;
          geometry::cameras_from_orbit_search<float>(E.data(), images.data(), pick(0).foreground.data(), depth,
                                                     pick(2).K.data(), n, size, size, search, nullptr, &found_cost, desc);
          errors[name].seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
          const std::vector<double> p(E.begin(), E.end()), gt(pv.w2c.begin(), pv.w2c.end());
          double e = 0;
          for (int v = 1; v < n; ++v) e += model::relative_rotation_error_deg(p.data(), p.data() + 12 * v, gt.data(), gt.data() + 12 * v);
          errors[name].rotation.push_back(e / (n - 1));
          // The true cameras scored by the same objective, each view's translation in its searched depth's units
          // (the predicted depth's: divided by that view's scale to the renderer's), as the search's per-view distance
          // would place it.
          std::vector<float> truth_E(gt.size());
          for (std::size_t i = 0; i < gt.size(); ++i)
            truth_E[i] = static_cast<float>(i % 4 == 3 && from[1] == 'm' ? gt[i] / sp[i / 12] : gt[i]);
          geometry::OrbitCostParts f, t;
          const bool cheaper = geometry::orbit_search_cost<float>(truth_E.data(), images.data(), pick(0).foreground.data(),
                                                                  depth, pick(2).K.data(), n, size, size, search, desc,
                                                                  cost_parts ? &t : nullptr) < found_cost;
          if (cost_parts) {  // the found placement's parts: the search reports its cost only
            geometry::orbit_search_cost<float>(E.data(), images.data(), pick(0).foreground.data(), depth, pick(2).K.data(),
                                               n, size, size, search, desc, &f);
            Errors& er = errors[name];
            er.found_parts += f, er.truth_parts += t;
            if (e / (n - 1) > 15) er.off_found_parts += f, er.off_truth_parts += t;
          }
          if (refine_grid > 0) {
            auto refined = [&](const float* X) {
              return depth_refined_cost<float>(X, images.data(), pick(0).foreground.data(), depth, pick(2).K.data(), n,
                                               size, search, desc, refine_grid);
            };
            const bool grid_cheaper = refined(truth_E.data()) < refined(E.data());
            errors[name].grid_truth_cheaper += grid_cheaper;
            if (e / (n - 1) > 15) errors[name].grid_off_truth_cheaper += grid_cheaper;
          }
          errors[name].truth_cheaper += cheaper;
          if (e / (n - 1) > 15) ++errors[name].off, errors[name].off_truth_cheaper += cheaper;
        }
      }
    }
    for (const auto& [name, from] : sources) {
      const Errors& e = errors[name];
      const double mean = std::accumulate(e.rotation.begin(), e.rotation.end(), 0.0) / static_cast<double>(e.rotation.size());
      const auto within = std::count_if(e.rotation.begin(), e.rotation.end(), [](double x) { return x <= 15; });
      std::printf("| %d | %s | %zu | %.1f° | %.1f° | %lld / %zu | %.2f | %d / %zu, %d / %d |", n, name.c_str(),
                  e.rotation.size(), median(e.rotation), mean, static_cast<long long>(within), e.rotation.size(),
                  e.seconds / static_cast<double>(e.rotation.size()), e.truth_cheaper, e.rotation.size(),
                  e.off_truth_cheaper, e.off);
      if (refine_grid > 0)
        std::printf(" %d / %zu, %d / %d |", e.grid_truth_cheaper, e.rotation.size(), e.grid_off_truth_cheaper, e.off);
      std::printf("\n");
      if (cost_parts) {
        const std::string& inputs = name;  // a lambda cannot capture a binding (clang 14)
        auto row = [&](const char* what, const geometry::OrbitCostParts& x, double sets) {
          char line[320];
          std::snprintf(line, sizeof line, "| %d | %s | %s | %.0f | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f |", n,
                        inputs.c_str(), what, sets, x.off_image / sets, x.silhouette / sets, x.free_space / sets,
                        x.occluded / sets, x.colour / sets, x.descriptor / sets, x.total() / sets);
          parts_rows.push_back(line);
        };
        const double all = static_cast<double>(e.rotation.size());
        row("found", e.found_parts, all), row("truth", e.truth_parts, all);
        if (e.off > 0) row("found, sets off by > 15°", e.off_found_parts, e.off), row("truth, sets off by > 15°", e.off_truth_parts, e.off);
      }
    }
    if (!w && altered)
      std::printf("| %d | depth error of the depth searched (each view scaled): %.3f |\n", n,
                  searched / (static_cast<double>(n) * sets * static_cast<double>(objects.size())));
    std::fflush(stdout);
    if (correspondences > 0) {
      char line[160];
      std::snprintf(line, sizeof line, "| %d | %.0f | %.3f | %.3f |", n, correspondences, hits1 / correspondences,
                    hits4 / correspondences);
      accuracy_rows.push_back(line);
    }
    if (measured > 0) {
      char line[256], searched_cell[32] = "";
      if (altered) std::snprintf(searched_cell, sizeof searched_cell, " %.3f |", searched / measured);
      std::snprintf(line, sizeof line, "| %d | %.3f | %.3f | %.3f |%s %.3f |", n, iou / measured, shape / measured,
                    flat / measured, searched_cell, focal / measured);
      quality.push_back(line);
    }
  }
  if (!quality.empty()) {
    std::printf("\n| views | silhouette IoU | depth error (each view scaled) | same for a constant depth |%s focal error "
                "|\n|---|---|---|---|%s---|\n", altered ? " same for the renderer's depth searched |" : "", altered ? "---|" : "");
    for (const auto& l : quality) std::printf("%s\n", l.c_str());
  }
  if (!accuracy_rows.empty()) {
    std::printf("\nThe search's descriptors on the renderer's correspondences (loss::match_accuracy, up to 256 per ordered "
                "pair):\n\n| views | correspondences | within 1 px | within 4 px |\n|---|---|---|---|\n");
    for (const auto& l : accuracy_rows) std::printf("%s\n", l.c_str());
  }
  if (!parts_rows.empty()) {
    std::printf("\nThe objective's parts, mean per set (geometry::OrbitCostParts):\n\n| views | inputs | cameras | sets | off image "
                "| silhouette | free space | occluded | colour | descriptor | total |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
    for (const auto& l : parts_rows) std::printf("%s\n", l.c_str());
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "%s\n", e.what());  // the messages name the program or the function that failed
  return 1;
}
