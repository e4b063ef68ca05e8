#pragma once
// Cameras from the dense outputs (the DUSt3R / PF-LRM idea): view v's point map holds each pixel's surface point in the
// first frame's camera frame, its depth map the same pixel in its own camera frame, so the world-to-camera [R | t] of
// view v is the weighted rigid (Kabsch) fit that maps the first onto the second. Pixels weigh by the point head's
// confidence above its floor of 1 (background, trained towards the floor, drops out). Closed form; no gradient.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <span>
#include <vector>

#include <Eigen/Dense>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/solvers/descriptor.hpp"
#include "flexsplat/geometry/unproject.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

// The proper rotation R and translation t minimising sum_i w_i |R src_i + t - dst_i|^2 over n weighted 3-D pairs
// (src, dst [n, 3]; w [n], entries <= 0 or non-finite pairs ignored). Returns false (R = I, t = 0) when fewer than 3
// pairs carry weight or they are collinear: the rotation is then undetermined.
template <class T>
bool rigid_fit(const T* src, const T* dst, const T* w, index_t n, double* R, double* t) {
  Eigen::Map<Eigen::Matrix<double, 3, 3, Eigen::RowMajor>> Rm(R);
  Eigen::Map<Eigen::Vector3d> tm(t);
  Rm.setIdentity();
  tm.setZero();
  auto usable = [&](index_t i) {
    const double wi = static_cast<double>(w[i]);
    if (!(std::isfinite(wi) && wi > 0)) return false;
    for (int k = 0; k < 3; ++k)
      if (!std::isfinite(static_cast<double>(src[3 * i + k])) || !std::isfinite(static_cast<double>(dst[3 * i + k])))
        return false;
    return true;
  };
  double sum = 0;
  index_t count = 0;
  Eigen::Vector3d cs = Eigen::Vector3d::Zero(), cd = Eigen::Vector3d::Zero();
  for (index_t i = 0; i < n; ++i) {
    if (!usable(i)) continue;
    const double wi = static_cast<double>(w[i]);
    for (int k = 0; k < 3; ++k) cs(k) += wi * static_cast<double>(src[3 * i + k]), cd(k) += wi * static_cast<double>(dst[3 * i + k]);
    sum += wi, ++count;
  }
  if (count < 3) return false;
  cs /= sum, cd /= sum;
  Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
  for (index_t i = 0; i < n; ++i) {
    if (!usable(i)) continue;
    Eigen::Vector3d a, b;
    for (int k = 0; k < 3; ++k) a(k) = static_cast<double>(src[3 * i + k]) - cs(k), b(k) = static_cast<double>(dst[3 * i + k]) - cd(k);
    H += static_cast<double>(w[i]) * b * a.transpose();
  }
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d sv = svd.singularValues();
  if (!(sv(1) > 1e-12 * std::max(sv(0), 1e-300))) return false;  // rank < 2: rotation about a line is free
  Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
  D(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1.0 : 1.0;
  const Eigen::Matrix3d rot = svd.matrixU() * D * svd.matrixV().transpose();
  Rm = rot;
  tm = cd - rot * cs;
  return true;
}

// Solves each view's world-to-camera from its point map. extrinsics [S, 3, 4] out; points [S, H, W, 3];
// points_conf [S, H, W] (weights conf - 1); depth [S, H, W]; intrinsics [S, 3, 3] with pixel (u, v) at integer
// coordinates (VGGT's convention, as geometry/unproject.hpp). A view whose fit is undetermined gets [I | 0] and a
// false entry in `solved` (may be null, [S]).
template <class T>
void cameras_from_points(T* extrinsics, const T* points, const T* points_conf, const T* depth, const T* intrinsics,
                         index_t frames, index_t height, index_t width, bool* solved = nullptr) {
  require(frames >= 1 && height >= 1 && width >= 1, "cameras_from_points: empty maps (", frames, " x ", height, " x ",
          width, ")");
  const index_t px = height * width;
  std::vector<double> wts(static_cast<std::size_t>(px));
  for (index_t f = 0; f < frames; ++f) {
    const std::vector<double> cam = camera_frame_points(depth, intrinsics, f, height, width);
    for (index_t p = 0; p < px; ++p)
      wts[static_cast<std::size_t>(p)] = depth[f * px + p] > T(0) ? static_cast<double>(points_conf[f * px + p]) - 1.0 : 0.0;
    std::vector<double> src(points + 3 * f * px, points + 3 * (f + 1) * px);
    double R[9], t[3];
    const bool ok = rigid_fit(src.data(), cam.data(), wts.data(), px, R, t);
    if (solved) solved[f] = ok;
    T* E = extrinsics + 12 * f;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) E[4 * r + c] = static_cast<T>(R[3 * r + c]);
      E[4 * r + 3] = static_cast<T>(t[r]);
    }
  }
}

// Settings of cameras_from_matches.
struct MatchFitConfig {
  double min_foreground = 0.5;  // pixels below this object probability are not matched
  double inlier_rel = 0.05;     // an inlier lies within this fraction of the median depth of the pair's matched pixels
  int ransac_rounds = 256;      // minimal (3-match) hypotheses per pair
  index_t min_inliers = 6;      // a pair with fewer inliers does not link its views
  unsigned seed = 1;            // every pair draws hypotheses from this fixed sequence: the same maps, the same cameras
};

// The rigid fit of dst ~ R src + t from n pairs [n, 3] by RANSAC over 3-pair samples, then least squares on the inliers
// (three rounds of re-selection). Returns the inlier count (0 when nothing fits); R, t hold the fit.
inline index_t robust_rigid_fit(const double* src, const double* dst, index_t n, double tau, int rounds,
                                unsigned seed, double* R, double* t) {
  if (n < 3) return 0;
  std::vector<double> ones(3, 1.0), w(static_cast<std::size_t>(n));
  std::vector<double> s3(9), d3(9);
  auto count = [&](const double* Rc, const double* tc, double* weights) {
    index_t c = 0;
    for (index_t i = 0; i < n; ++i) {
      double r2 = 0;
      for (int r = 0; r < 3; ++r) {
        double y = tc[r] - dst[3 * i + r];
        for (int k = 0; k < 3; ++k) y += Rc[3 * r + k] * src[3 * i + k];
        r2 += y * y;
      }
      const bool in = r2 < tau * tau;
      if (weights) weights[i] = in ? 1.0 : 0.0;
      c += in;
    }
    return c;
  };
  std::uint64_t state = 0x9E3779B97F4A7C15ull ^ seed;
  auto draw = [&]() {  // splitmix64: a fixed, platform-independent sequence
    std::uint64_t z = (state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return static_cast<index_t>((z ^ (z >> 31)) % static_cast<std::uint64_t>(n));
  };
  index_t best = 0;
  double Rh[9], th[3];
  for (int it = 0; it < rounds; ++it) {
    const index_t a = draw(), b = draw(), c = draw();
    if (a == b || b == c || a == c) continue;
    const index_t pick[3] = {a, b, c};
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k) s3[3 * j + k] = src[3 * pick[j] + k], d3[3 * j + k] = dst[3 * pick[j] + k];
    if (!rigid_fit(s3.data(), d3.data(), ones.data(), 3, Rh, th)) continue;
    if (const index_t c2 = count(Rh, th, nullptr); c2 > best) {
      best = c2;
      std::copy(Rh, Rh + 9, R), std::copy(th, th + 3, t);
    }
  }
  for (int round = 0; best >= 3 && round < 3; ++round) {
    count(R, t, w.data());
    if (!rigid_fit(src, dst, w.data(), n, Rh, th)) break;
    const index_t c2 = count(Rh, th, nullptr);
    if (c2 < best) break;
    best = c2;
    std::copy(Rh, Rh + 9, R), std::copy(th, th + 3, t);
  }
  return best;
}

// One view pair's relative pose a -> b (x_b = R x_a + t, R row-major) and its inlier count (0: not fitted).
struct PairFit {
  index_t inliers = 0;
  double R[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, t[3] = {0, 0, 0};
};

namespace procrustes_detail {

// Fits the pair from matched camera-frame points src (view a) and dst (view b), [n, 3] each; the inlier radius is
// cfg.inlier_rel of the median depth of the matched points.
inline PairFit fit_pair(const std::vector<double>& src, const std::vector<double>& dst, const MatchFitConfig& cfg) {
  PairFit e;
  const index_t n = static_cast<index_t>(src.size() / 3);
  if (n < 3) return e;
  std::vector<double> depths;
  depths.reserve(static_cast<std::size_t>(2 * n));
  for (index_t i = 0; i < n; ++i) depths.push_back(src[static_cast<std::size_t>(3 * i + 2)]), depths.push_back(dst[static_cast<std::size_t>(3 * i + 2)]);
  std::nth_element(depths.begin(), depths.begin() + n, depths.end());
  const double tau = cfg.inlier_rel * depths[static_cast<std::size_t>(n)];
  e.inliers = robust_rigid_fit(src.data(), dst.data(), n, tau, cfg.ransac_rounds, cfg.seed, e.R, e.t);
  return e;
}

// Places the views from the first along the pairs with the most inliers (Prim's maximum spanning tree), each view's
// camera its edge composed with its parent's. edge [frames, frames] holds a -> b at a * frames + b (both directions
// filled). extrinsics, solved and matches_out as cameras_from_matches.
template <class T>
void place_views(T* extrinsics, const std::vector<PairFit>& edge, index_t frames, index_t min_inliers, bool* solved,
                 index_t* matches_out) {
  std::vector<double> cam(static_cast<std::size_t>(12 * frames), 0.0);
  std::vector<char> placed(static_cast<std::size_t>(frames), 0);
  std::vector<index_t> by(static_cast<std::size_t>(frames), 0);
  std::copy_n(identity_w2c, 12, cam.begin());
  placed[0] = 1;
  for (;;) {
    index_t best = min_inliers - 1, from = -1, to = -1;
    for (index_t a = 0; a < frames; ++a)
      for (index_t b = 0; b < frames; ++b)
        if (placed[static_cast<std::size_t>(a)] && !placed[static_cast<std::size_t>(b)] &&
            edge[static_cast<std::size_t>(a * frames + b)].inliers > best)
          best = edge[static_cast<std::size_t>(a * frames + b)].inliers, from = a, to = b;
    if (to < 0) break;
    const PairFit& e = edge[static_cast<std::size_t>(from * frames + to)];
    const double* P = cam.data() + 12 * from;  // [R_a | t_a]; view b: R_e R_a, R_e t_a + t_e
    double* Q = cam.data() + 12 * to;
    for (int r = 0; r < 3; ++r) {
      Q[4 * r + 3] = e.t[r];
      for (int c = 0; c < 4; ++c) {
        double acc = c == 3 ? Q[4 * r + 3] : 0.0;
        for (int k = 0; k < 3; ++k) acc += e.R[3 * r + k] * P[4 * k + c];
        Q[4 * r + c] = acc;
      }
    }
    placed[static_cast<std::size_t>(to)] = 1;
    by[static_cast<std::size_t>(to)] = best;
  }
  for (index_t f = 0; f < frames; ++f) {
    const bool ok = placed[static_cast<std::size_t>(f)] != 0;
    if (solved) solved[f] = ok;
    if (matches_out) matches_out[f] = by[static_cast<std::size_t>(f)];
    for (int i = 0; i < 12; ++i)
      extrinsics[12 * f + i] = static_cast<T>(ok ? cam[static_cast<std::size_t>(12 * f + i)] : identity_w2c[i]);
  }
}

// Stores the fit of pair (a, b) and its reverse b -> a (R^T, -R^T t).
inline void set_edge(std::vector<PairFit>& edge, index_t frames, index_t a, index_t b, const PairFit& e) {
  edge[static_cast<std::size_t>(a * frames + b)] = e;
  PairFit& r = edge[static_cast<std::size_t>(b * frames + a)];
  r.inliers = e.inliers;
  for (int i = 0; i < 3; ++i) {
    r.t[i] = 0;
    for (int k = 0; k < 3; ++k) r.R[3 * i + k] = e.R[3 * k + i], r.t[i] -= e.R[3 * k + i] * e.t[k];
  }
}
}  // namespace procrustes_detail

// Each view's world-to-camera from descriptor matches, the first view's camera being the world: pixels whose object
// probability is at least `min_foreground` are matched between every pair of views by mutual nearest neighbours of
// unit-length descriptors, both ends unprojected with their own depth and intrinsics (pixel (u, v) at integer
// coordinates), and each pair's relative pose is fitted robustly (robust_rigid_fit). The views are then linked from
// the first along the pairs with the most inliers (a maximum spanning tree), so a view that shares nothing with the
// first is still placed through one that does. View 0 gets [I | 0]; a view no pair links gets [I | 0] and solved
// false. extrinsics [S, 3, 4] out; descriptors [S, H, W, D]; foreground, depth [S, H, W]; intrinsics [S, 3, 3];
// matches_out (may be null, [S]): the inliers of the pair that placed each view (0 for view 0 and unplaced views);
// pairs_out (may be null): every pair's own fit, [S * S], a -> b at a * S + b.
template <class T>
void cameras_from_matches(T* extrinsics, const T* descriptors, const T* foreground, const T* depth, const T* intrinsics,
                          index_t frames, index_t height, index_t width, index_t D, bool* solved = nullptr,
                          index_t* matches_out = nullptr, const MatchFitConfig& cfg = {},
                          std::vector<PairFit>* pairs_out = nullptr) {
  require(frames >= 1 && height >= 1 && width >= 1 && D >= 1, "cameras_from_matches: empty maps (", frames, " x ",
          height, " x ", width, " x ", D, ")");
  const index_t px = height * width;
  // Foreground pixels of a view: their unit descriptors (rows) and camera-frame points.
  struct ViewSet {
    Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> unit;
    std::vector<double> point;
    std::vector<index_t> pixel;
  };
  std::vector<ViewSet> views(static_cast<std::size_t>(frames));
  for (index_t f = 0; f < frames; ++f) {
    const std::vector<double> cam = camera_frame_points(depth, intrinsics, f, height, width);
    std::vector<float> unit;
    ViewSet& v = views[static_cast<std::size_t>(f)];
    for (index_t p = 0; p < px; ++p) {
      const double fg = static_cast<double>(foreground[f * px + p]), z = static_cast<double>(depth[f * px + p]);
      if (!(fg >= cfg.min_foreground) || !(z > 0) || !std::isfinite(z)) continue;
      unit.resize(unit.size() + static_cast<std::size_t>(D));
      if (!unit_descriptor(descriptors + (f * px + p) * D, D, unit.data() + unit.size() - static_cast<std::size_t>(D))) {
        unit.resize(unit.size() - static_cast<std::size_t>(D));
        continue;
      }
      v.point.insert(v.point.end(), cam.begin() + 3 * p, cam.begin() + 3 * p + 3);
      v.pixel.push_back(p);
    }
    v.unit = Eigen::Map<Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
        unit.data(), static_cast<Eigen::Index>(v.point.size() / 3), static_cast<Eigen::Index>(D));
  }
  std::vector<PairFit> edge(static_cast<std::size_t>(frames * frames));
  for (index_t a = 0; a < frames; ++a)
    for (index_t b = a + 1; b < frames; ++b) {
      const ViewSet &A = views[static_cast<std::size_t>(a)], &B = views[static_cast<std::size_t>(b)];
      if (A.unit.rows() < 3 || B.unit.rows() < 3) continue;
      // Nearest neighbours both ways, the similarities in blocks of rows (memory stays bounded at any image size).
      const Eigen::Index na = A.unit.rows(), nb = B.unit.rows(), block = 1024;
      std::vector<Eigen::Index> row_best(static_cast<std::size_t>(na)), col_best(static_cast<std::size_t>(nb), -1);
      std::vector<float> col_top(static_cast<std::size_t>(nb), -std::numeric_limits<float>::infinity());
      Eigen::MatrixXf sim;
      for (Eigen::Index r0 = 0; r0 < na; r0 += block) {
        const Eigen::Index rows = std::min(block, na - r0);
        sim.noalias() = A.unit.middleRows(r0, rows) * B.unit.transpose();
        for (Eigen::Index i = 0; i < rows; ++i) sim.row(i).maxCoeff(&row_best[static_cast<std::size_t>(r0 + i)]);
        for (Eigen::Index j = 0; j < nb; ++j) {
          Eigen::Index i;
          const float top = sim.col(j).maxCoeff(&i);
          if (top > col_top[static_cast<std::size_t>(j)]) col_top[static_cast<std::size_t>(j)] = top, col_best[static_cast<std::size_t>(j)] = r0 + i;
        }
      }
      // Mutual nearest neighbours, in an order that does not depend on which view is a (so that reordering the
      // input views reorders the cameras): by (smaller, larger) of the two pixel indices.
      struct Pair {
        index_t lo, hi, i, j;
      };
      std::vector<Pair> mutual;
      for (Eigen::Index i = 0; i < na; ++i) {
        const Eigen::Index j = row_best[static_cast<std::size_t>(i)];
        if (col_best[static_cast<std::size_t>(j)] != i) continue;
        const index_t pa = A.pixel[static_cast<std::size_t>(i)], pb = B.pixel[static_cast<std::size_t>(j)];
        mutual.push_back({std::min(pa, pb), std::max(pa, pb), static_cast<index_t>(i), static_cast<index_t>(j)});
      }
      std::sort(mutual.begin(), mutual.end(), [](const Pair& x, const Pair& y) { return x.lo != y.lo ? x.lo < y.lo : x.hi < y.hi; });
      std::vector<double> src, dst;
      for (const Pair& m : mutual) {
        src.insert(src.end(), A.point.begin() + 3 * m.i, A.point.begin() + 3 * m.i + 3);
        dst.insert(dst.end(), B.point.begin() + 3 * m.j, B.point.begin() + 3 * m.j + 3);
      }
      procrustes_detail::set_edge(edge, frames, a, b, procrustes_detail::fit_pair(src, dst, cfg));
    }
  procrustes_detail::place_views(extrinsics, edge, frames, cfg.min_inliers, solved, matches_out);
  if (pairs_out) *pairs_out = std::move(edge);
}

// The same solver on given correspondences instead of descriptor matches (e.g. the renderer's, as the ceiling of
// what matching can give): Match has view_a, pixel_a, view_b, pixel_b (pixels as y * width + x); a correspondence
// with a pixel of no positive finite depth is skipped. extrinsics, depth, intrinsics, solved, matches_out and cfg
// (min_foreground unused) as cameras_from_matches.
template <class T, class Match>
void cameras_from_correspondences(T* extrinsics, std::span<const Match> matches, const T* depth, const T* intrinsics,
                                  index_t frames, index_t height, index_t width, bool* solved = nullptr,
                                  index_t* matches_out = nullptr, const MatchFitConfig& cfg = {}) {
  require(frames >= 1 && height >= 1 && width >= 1, "cameras_from_correspondences: empty maps (", frames, " x ",
          height, " x ", width, ")");
  const index_t px = height * width;
  std::vector<std::vector<double>> cam(static_cast<std::size_t>(frames));
  for (index_t f = 0; f < frames; ++f) cam[static_cast<std::size_t>(f)] = camera_frame_points(depth, intrinsics, f, height, width);
  std::vector<std::vector<double>> src(static_cast<std::size_t>(frames * frames)), dst(src.size());
  for (const Match& m : matches) {
    require(m.view_a >= 0 && m.view_a < frames && m.view_b >= 0 && m.view_b < frames && m.view_a != m.view_b &&
                m.pixel_a >= 0 && m.pixel_a < px && m.pixel_b >= 0 && m.pixel_b < px,
            "cameras_from_correspondences: correspondence (view ", m.view_a, " pixel ", m.pixel_a, ", view ", m.view_b,
            " pixel ", m.pixel_b, ") is outside ", frames, " views of ", height, " x ", width);
    const double za = static_cast<double>(depth[m.view_a * px + m.pixel_a]), zb = static_cast<double>(depth[m.view_b * px + m.pixel_b]);
    if (!(za > 0) || !(zb > 0) || !std::isfinite(za) || !std::isfinite(zb)) continue;
    // Stored with the smaller view first, so both orders of a pair feed one fit.
    const bool swap = m.view_a > m.view_b;
    const index_t a = swap ? m.view_b : m.view_a, b = swap ? m.view_a : m.view_b;
    const index_t pa = swap ? m.pixel_b : m.pixel_a, pb = swap ? m.pixel_a : m.pixel_b;
    const auto& A = cam[static_cast<std::size_t>(a)];
    const auto& B = cam[static_cast<std::size_t>(b)];
    auto& s = src[static_cast<std::size_t>(a * frames + b)];
    auto& d = dst[static_cast<std::size_t>(a * frames + b)];
    s.insert(s.end(), A.begin() + 3 * pa, A.begin() + 3 * pa + 3);
    d.insert(d.end(), B.begin() + 3 * pb, B.begin() + 3 * pb + 3);
  }
  std::vector<PairFit> edge(static_cast<std::size_t>(frames * frames));
  for (index_t a = 0; a < frames; ++a)
    for (index_t b = a + 1; b < frames; ++b)
      procrustes_detail::set_edge(edge, frames, a, b,
                                  procrustes_detail::fit_pair(src[static_cast<std::size_t>(a * frames + b)],
                                                              dst[static_cast<std::size_t>(a * frames + b)], cfg));
  procrustes_detail::place_views(extrinsics, edge, frames, cfg.min_inliers, solved, matches_out);
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
