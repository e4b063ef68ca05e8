#pragma once
// Cameras from the dense outputs (the DUSt3R / PF-LRM idea): view v's point map holds each pixel's surface point in the
// first frame's camera frame, its depth map the same pixel in its own camera frame, so the world-to-camera [R | t] of
// view v is the weighted rigid (Kabsch) fit that maps the first onto the second. Pixels weigh by the point head's
// confidence above its floor of 1 (background, trained towards the floor, drops out). Closed form; no gradient.
#include <algorithm>
#include <cmath>
#include <vector>

#include <Eigen/Dense>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

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
  std::vector<double> cam(static_cast<std::size_t>(3 * px)), wts(static_cast<std::size_t>(px));
  for (index_t f = 0; f < frames; ++f) {
    const T* K = intrinsics + 9 * f;
    const double fx = static_cast<double>(K[0]), fy = static_cast<double>(K[4]);
    const double cx = static_cast<double>(K[2]), cy = static_cast<double>(K[5]);
    require(std::isfinite(fx) && std::isfinite(fy) && fx != 0 && fy != 0, "cameras_from_points: frame ", f,
            " has focal lengths ", fx, ", ", fy);
    for (index_t y = 0; y < height; ++y)
      for (index_t x = 0; x < width; ++x) {
        const index_t p = y * width + x;
        const double d = static_cast<double>(depth[f * px + p]);
        double* c = cam.data() + 3 * p;
        c[0] = (static_cast<double>(x) - cx) / fx * d, c[1] = (static_cast<double>(y) - cy) / fy * d, c[2] = d;
        wts[static_cast<std::size_t>(p)] = d > 0 ? static_cast<double>(points_conf[f * px + p]) - 1.0 : 0.0;
      }
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

// Each view's world-to-camera from descriptor matches with the first view (the world): pixels whose object
// probability is at least `min_foreground` are matched by mutual nearest neighbours of unit-length descriptors, both
// ends unprojected with their own depth and intrinsics (pixel (u, v) at integer coordinates), and the rigid fit from the
// first view's points to view v's is refined by iteratively reweighted least squares (Cauchy weights at 1.5 x the
// median residual, 5 rounds) so that wrong matches drop out. View 0 gets [I | 0]; a view with fewer than 3 matches
// [I | 0] and solved false. extrinsics [S, 3, 4] out; descriptors [S, H, W, D]; foreground, depth [S, H, W];
// intrinsics [S, 3, 3]; matches_out (may be null, [S]): mutual matches found per view.
template <class T>
void cameras_from_matches(T* extrinsics, const T* descriptors, const T* foreground, const T* depth, const T* intrinsics,
                          index_t frames, index_t height, index_t width, index_t D, bool* solved = nullptr,
                          index_t* matches_out = nullptr, double min_foreground = 0.5) {
  require(frames >= 1 && height >= 1 && width >= 1 && D >= 1, "cameras_from_matches: empty maps (", frames, " x ",
          height, " x ", width, " x ", D, ")");
  const index_t px = height * width;
  auto set_camera = [&](index_t f, const double* R, const double* t) {
    T* E = extrinsics + 12 * f;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) E[4 * r + c] = static_cast<T>(R[3 * r + c]);
      E[4 * r + 3] = static_cast<T>(t[r]);
    }
  };
  const double I[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, zero[3] = {0, 0, 0};
  // Foreground pixels of a view: their indices, unit descriptors and camera-frame points.
  struct ViewSet {
    std::vector<index_t> pixel;
    std::vector<double> unit, point;
  };
  auto gather = [&](index_t f) {
    ViewSet v;
    const T* K = intrinsics + 9 * f;
    const double fx = static_cast<double>(K[0]), fy = static_cast<double>(K[4]);
    const double cx = static_cast<double>(K[2]), cy = static_cast<double>(K[5]);
    require(std::isfinite(fx) && std::isfinite(fy) && fx != 0 && fy != 0, "cameras_from_matches: frame ", f,
            " has focal lengths ", fx, ", ", fy);
    for (index_t p = 0; p < px; ++p) {
      const double fg = static_cast<double>(foreground[f * px + p]), z = static_cast<double>(depth[f * px + p]);
      if (!(fg >= min_foreground) || !(z > 0) || !std::isfinite(z)) continue;
      const T* d = descriptors + (f * px + p) * D;
      double n2 = 0;
      for (index_t k = 0; k < D; ++k) n2 += static_cast<double>(d[k]) * static_cast<double>(d[k]);
      if (!(n2 > 0) || !std::isfinite(n2)) continue;
      const double inv = 1 / std::sqrt(n2);
      v.pixel.push_back(p);
      for (index_t k = 0; k < D; ++k) v.unit.push_back(static_cast<double>(d[k]) * inv);
      const double x = static_cast<double>(p % width), y = static_cast<double>(p / width);
      v.point.insert(v.point.end(), {(x - cx) / fx * z, (y - cy) / fy * z, z});
    }
    return v;
  };
  auto best = [&](const ViewSet& from, const ViewSet& to, std::vector<index_t>& out) {
    const index_t n = static_cast<index_t>(from.pixel.size()), m = static_cast<index_t>(to.pixel.size());
    out.assign(static_cast<std::size_t>(n), -1);
    for (index_t i = 0; i < n; ++i) {
      double top = -2;
      for (index_t j = 0; j < m; ++j) {
        double dot = 0;
        for (index_t k = 0; k < D; ++k) dot += from.unit[static_cast<std::size_t>(i * D + k)] * to.unit[static_cast<std::size_t>(j * D + k)];
        if (dot > top) top = dot, out[static_cast<std::size_t>(i)] = j;
      }
    }
  };
  set_camera(0, I, zero);
  if (solved) solved[0] = true;
  if (matches_out) matches_out[0] = 0;
  if (frames == 1) return;
  const ViewSet first = gather(0);
  std::vector<index_t> ab, ba;
  for (index_t f = 1; f < frames; ++f) {
    const ViewSet other = gather(f);
    best(first, other, ab);
    best(other, first, ba);
    std::vector<double> src, dst;
    for (std::size_t i = 0; i < ab.size(); ++i) {
      const index_t j = ab[i];
      if (j < 0 || ba[static_cast<std::size_t>(j)] != static_cast<index_t>(i)) continue;
      src.insert(src.end(), first.point.begin() + static_cast<std::ptrdiff_t>(3 * i), first.point.begin() + static_cast<std::ptrdiff_t>(3 * i + 3));
      dst.insert(dst.end(), other.point.begin() + 3 * j, other.point.begin() + 3 * j + 3);
    }
    const index_t n = static_cast<index_t>(src.size() / 3);
    if (matches_out) matches_out[f] = n;
    double R[9], t[3];
    std::vector<double> wts(static_cast<std::size_t>(n), 1.0), res(static_cast<std::size_t>(n));
    bool ok = rigid_fit(src.data(), dst.data(), wts.data(), n, R, t);
    for (int round = 0; ok && round < 5; ++round) {
      for (index_t i = 0; i < n; ++i) {
        double r2 = 0;
        for (int r = 0; r < 3; ++r) {
          double y = t[r];
          for (int k = 0; k < 3; ++k) y += R[3 * r + k] * src[static_cast<std::size_t>(3 * i + k)];
          r2 += (y - dst[static_cast<std::size_t>(3 * i + r)]) * (y - dst[static_cast<std::size_t>(3 * i + r)]);
        }
        res[static_cast<std::size_t>(i)] = std::sqrt(r2);
      }
      std::vector<double> sorted(res);
      std::nth_element(sorted.begin(), sorted.begin() + n / 2, sorted.end());
      const double scale = std::max(1.5 * sorted[static_cast<std::size_t>(n / 2)], 1e-9);
      for (index_t i = 0; i < n; ++i) {
        const double u = res[static_cast<std::size_t>(i)] / scale;
        wts[static_cast<std::size_t>(i)] = 1 / (1 + u * u);
      }
      ok = rigid_fit(src.data(), dst.data(), wts.data(), n, R, t);
    }
    if (solved) solved[f] = ok;
    if (ok) set_camera(f, R, t);
    else set_camera(f, I, zero);
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
