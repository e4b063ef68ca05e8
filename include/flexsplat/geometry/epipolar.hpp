#pragma once
// Cameras refined by epipolar geometry alone: mutual nearest neighbours of the match head's descriptors between every
// pair of views, and each view's rotation and centre moved (Levenberg-Marquardt on reweighted least squares, the first
// view fixed) to lower the robust Sampson error of those matches, its scale annealed from wide to narrow (graduated
// non-convexity). Unlike the
// orbit search it reads no depth, so a depth whose shape is off does not move its minimum; it needs cameras near the
// answer to start from (a wrong-match majority is only outvoted within the wide scale's basin).
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <vector>

#include <Eigen/Dense>
#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/geometry/descriptor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

struct EpipolarRefineConfig {
  double min_foreground = 0.5;  // pixels at or above this object probability are matched
  double min_cosine = 0.5;      // mutual nearest neighbours below this descriptor cosine are dropped
  // Geman-McClure scales of the Sampson error in pixels, one minimisation each, widest first.
  std::vector<double> scales_px{8, 4, 2, 1};
  int iterations = 30;          // Levenberg-Marquardt steps per scale at most
};

// One pair's matches: normalised image coordinates ((u - cx) / fx, (v - cy) / fy) in views a and b.
struct EpipolarPair {
  index_t a = 0, b = 0;
  std::vector<glm::dvec2> xa, xb;
  double focal = 1;  // the two views' mean focal length in pixels: Sampson errors are reported in pixels
};

// Mutual nearest neighbours (descriptor cosine) between the object pixels of every pair a < b. foreground [S, H, W],
// descriptors [S, H, W, dim], intrinsics [S, 3, 3] with pixel (u, v) at integer coordinates.
template <class T>
std::vector<EpipolarPair> epipolar_matches(const T* foreground, const T* descriptors, index_t dim, const T* intrinsics,
                                           index_t frames, index_t height, index_t width,
                                           const EpipolarRefineConfig& cfg = {}) {
  require(frames >= 1 && height >= 1 && width >= 1 && dim >= 1, "epipolar_matches: empty maps (", frames, " x ", height,
          " x ", width, ", descriptor width ", dim, ")");
  const index_t px = height * width;
  const std::size_t D = static_cast<std::size_t>(dim);
  struct ViewPixels {
    std::vector<index_t> pixel;
    std::vector<float> desc;  // [n, dim] unit
    double fx = 1, fy = 1, cx = 0, cy = 0;
  };
  std::vector<ViewPixels> views(static_cast<std::size_t>(frames));
  for (index_t f = 0; f < frames; ++f) {
    ViewPixels& v = views[static_cast<std::size_t>(f)];
    const T* K = intrinsics + 9 * f;
    v.fx = static_cast<double>(K[0]), v.fy = static_cast<double>(K[4]);
    v.cx = static_cast<double>(K[2]), v.cy = static_cast<double>(K[5]);
    require(std::isfinite(v.fx) && std::isfinite(v.fy) && v.fx > 0 && v.fy > 0 && std::isfinite(v.cx) &&
                std::isfinite(v.cy),
            "epipolar_matches: view ", f, " has intrinsics fx ", v.fx, ", fy ", v.fy, ", cx ", v.cx, ", cy ", v.cy);
    std::vector<float> unit(D);
    for (index_t p = 0; p < px; ++p) {
      if (!(static_cast<double>(foreground[f * px + p]) >= cfg.min_foreground)) continue;
      if (!unit_descriptor(descriptors + static_cast<std::size_t>(f * px + p) * D, dim, unit.data())) continue;
      v.pixel.push_back(p);
      v.desc.insert(v.desc.end(), unit.begin(), unit.end());
    }
  }
  // Each pixel's best cosine and partner in the other view, rows in parallel.
  auto nearest = [&](const ViewPixels& a, const ViewPixels& b, std::vector<index_t>& best, std::vector<float>& cos) {
    const index_t na = static_cast<index_t>(a.pixel.size()), nb = static_cast<index_t>(b.pixel.size());
    best.assign(static_cast<std::size_t>(na), -1), cos.assign(static_cast<std::size_t>(na), -2.f);
    parallel_for(na, [&](index_t i0, index_t i1, int) {
      for (index_t i = i0; i < i1; ++i) {
        const float* da = a.desc.data() + static_cast<std::size_t>(i) * D;
        for (index_t j = 0; j < nb; ++j) {
          const float* db = b.desc.data() + static_cast<std::size_t>(j) * D;
          float dot = 0;
          for (std::size_t k = 0; k < D; ++k) dot += da[k] * db[k];
          if (dot > cos[static_cast<std::size_t>(i)]) cos[static_cast<std::size_t>(i)] = dot, best[static_cast<std::size_t>(i)] = j;
        }
      }
    });
  };
  std::vector<EpipolarPair> pairs;
  std::vector<index_t> ab, ba;
  std::vector<float> cab, cba;
  for (index_t a = 0; a < frames; ++a)
    for (index_t b = a + 1; b < frames; ++b) {
      const ViewPixels &va = views[static_cast<std::size_t>(a)], &vb = views[static_cast<std::size_t>(b)];
      EpipolarPair pr;
      pr.a = a, pr.b = b, pr.focal = 0.25 * (va.fx + va.fy + vb.fx + vb.fy);
      if (!va.pixel.empty() && !vb.pixel.empty()) {
        nearest(va, vb, ab, cab);
        nearest(vb, va, ba, cba);
        for (std::size_t i = 0; i < ab.size(); ++i) {
          const index_t j = ab[i];
          if (j < 0 || ba[static_cast<std::size_t>(j)] != static_cast<index_t>(i) || cab[i] < cfg.min_cosine) continue;
          const index_t p = va.pixel[i], q = vb.pixel[static_cast<std::size_t>(j)];
          pr.xa.push_back({(static_cast<double>(p % width) - va.cx) / va.fx, (static_cast<double>(p / width) - va.cy) / va.fy});
          pr.xb.push_back({(static_cast<double>(q % width) - vb.cx) / vb.fx, (static_cast<double>(q / width) - vb.cy) / vb.fy});
        }
      }
      pairs.push_back(std::move(pr));
    }
  return pairs;
}

namespace epipolar_detail {

struct Pose {
  glm::dmat3 R{1.0};
  glm::dvec3 C{0.0};  // camera centre in the world
};

// f(squared Sampson error in pixels^2, signed error in pixels) for every match of `pr` under poses pa, pb.
template <class F>
void for_each_sampson(const EpipolarPair& pr, const Pose& pa, const Pose& pb, F&& f) {
  const glm::dmat3 Rab = pb.R * glm::transpose(pa.R);
  glm::dvec3 t = pb.R * (pa.C - pb.C);  // a's centre in b's frame: b's translation relative to a
  const double n = glm::length(t);
  if (!(n > 0)) {
    for (std::size_t i = 0; i < pr.xa.size(); ++i) f(std::numeric_limits<double>::infinity(), 0.0);
    return;
  }
  t /= n;
  glm::dmat3 tx(0.0);  // [t]x, column-major
  tx[1][0] = -t.z, tx[2][0] = t.y, tx[0][1] = t.z, tx[2][1] = -t.x, tx[0][2] = -t.y, tx[1][2] = t.x;
  const glm::dmat3 E = tx * Rab;  // x_b^T E x_a = 0
  const glm::dmat3 Et = glm::transpose(E);
  const double f2 = pr.focal * pr.focal;
  for (std::size_t i = 0; i < pr.xa.size(); ++i) {
    const glm::dvec3 xa(pr.xa[i], 1.0), xb(pr.xb[i], 1.0);
    const glm::dvec3 Ea = E * xa, Eb = Et * xb;
    const double r = glm::dot(xb, Ea);
    const double den = Ea.x * Ea.x + Ea.y * Ea.y + Eb.x * Eb.x + Eb.y * Eb.y;
    f(den > 0 ? f2 * r * r / den : std::numeric_limits<double>::infinity(), den > 0 ? pr.focal * r / std::sqrt(den) : 0.0);
  }
}

// Mean Geman-McClure cost e^2 / (e^2 + s^2) of a pair's matches, in [0, 1] (0 without matches).
inline double pair_cost(const EpipolarPair& pr, const Pose& pa, const Pose& pb, double scale) {
  if (pr.xa.empty()) return 0;
  const double s2 = scale * scale;
  double sum = 0;
  for_each_sampson(pr, pa, pb, [&](double e2, double) { sum += std::isfinite(e2) ? e2 / (e2 + s2) : 1.0; });
  return sum / static_cast<double>(pr.xa.size());
}

template <class T>
Pose pose_from_w2c(const T* E) {
  Pose p;
  glm::dvec3 t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) p.R[c][r] = static_cast<double>(E[4 * r + c]);
    t[r] = static_cast<double>(E[4 * r + 3]);
  }
  p.C = -(glm::transpose(p.R) * t);
  return p;
}

}  // namespace epipolar_detail

// The sum over pairs of the mean Geman-McClure cost e^2 / (e^2 + s^2) at s = `scale_px` (what each stage of refine_cameras_epipolar lowers)
// for world-to-camera extrinsics [S, 3, 4].
template <class T>
double epipolar_cost(const T* extrinsics, const std::vector<EpipolarPair>& pairs, index_t frames, double scale_px) {
  std::vector<epipolar_detail::Pose> pose(static_cast<std::size_t>(frames));
  for (index_t f = 0; f < frames; ++f) pose[static_cast<std::size_t>(f)] = epipolar_detail::pose_from_w2c(extrinsics + 12 * f);
  double sum = 0;
  for (const EpipolarPair& pr : pairs)
    sum += epipolar_detail::pair_cost(pr, pose[static_cast<std::size_t>(pr.a)], pose[static_cast<std::size_t>(pr.b)], scale_px);
  return sum;
}

// The Sampson error in pixels of each of a pair's matches under world-to-camera extrinsics [S, 3, 4].
template <class T>
std::vector<double> epipolar_errors_px(const T* extrinsics, const EpipolarPair& pr) {
  std::vector<double> out;
  out.reserve(pr.xa.size());
  epipolar_detail::for_each_sampson(pr, epipolar_detail::pose_from_w2c(extrinsics + 12 * pr.a),
                                    epipolar_detail::pose_from_w2c(extrinsics + 12 * pr.b),
                                    [&](double e2, double) { out.push_back(std::sqrt(e2)); });
  return out;
}

// Refines world-to-camera extrinsics [S, 3, 4] in place by the pairs' matches (epipolar_matches); view 0 stays where
// it is and, for the scale, view 1's centre keeps its distance from view 0's.
template <class T>
void refine_cameras_epipolar(T* extrinsics, const std::vector<EpipolarPair>& pairs, index_t frames,
                             const EpipolarRefineConfig& cfg = {}) {
  using namespace epipolar_detail;
  require(frames >= 1, "refine_cameras_epipolar: ", frames, " views");
  require(!cfg.scales_px.empty() && cfg.iterations >= 1, "refine_cameras_epipolar: invalid config (",
          cfg.scales_px.size(), " scales, ", cfg.iterations, " iterations)");
  for (double s : cfg.scales_px) require(s > 0 && std::isfinite(s), "refine_cameras_epipolar: scale ", s, " px must be > 0");
  for (const EpipolarPair& pr : pairs)
    require(pr.a >= 0 && pr.b >= 0 && pr.a < frames && pr.b < frames && pr.a != pr.b && pr.xa.size() == pr.xb.size(),
            "refine_cameras_epipolar: pair (", pr.a, ", ", pr.b, ") does not fit ", frames, " views");
  if (frames < 2) return;
  std::vector<Pose> pose(static_cast<std::size_t>(frames));
  for (index_t f = 0; f < frames; ++f) {
    for (int i = 0; i < 12; ++i)
      require(std::isfinite(static_cast<double>(extrinsics[12 * f + i])), "refine_cameras_epipolar: view ", f,
              " extrinsics[", i / 4, ",", i % 4, "] = ", static_cast<double>(extrinsics[12 * f + i]), " is not finite");
    pose[static_cast<std::size_t>(f)] = pose_from_w2c(extrinsics + 12 * f);
  }
  double spread = 0;
  for (index_t f = 1; f < frames; ++f) spread += glm::length(pose[static_cast<std::size_t>(f)].C - pose[0].C);
  spread /= static_cast<double>(frames - 1);
  if (!(spread > 0)) return;  // coincident centres: no baseline, nothing epipolar to refine
  const double radius1 = glm::length(pose[1].C - pose[0].C);
  const index_t P = 6 * (frames - 1);  // per view 2..S: a turn about its own axes (radians), its centre / spread
  // Pose after parameter offsets x (the base poses unchanged); view 1's centre scaled back to its distance from view 0
  // (the epipolar terms do not see a common scale of the centres, so this fixes it).
  auto apply = [&](const std::vector<Pose>& base, const Eigen::VectorXd& x) {
    std::vector<Pose> q = base;
    for (index_t v = 1; v < frames; ++v) {
      const Eigen::Index o = static_cast<Eigen::Index>(6 * (v - 1));
      const glm::dvec3 w(x[o], x[o + 1], x[o + 2]);
      const double angle = glm::length(w);
      if (angle > 0) {  // Rodrigues
        const glm::dvec3 k = w / angle;
        const glm::dmat3 Kx(0, k.z, -k.y, -k.z, 0, k.x, k.y, -k.x, 0);
        q[static_cast<std::size_t>(v)].R = (glm::dmat3(1.0) + std::sin(angle) * Kx + (1 - std::cos(angle)) * Kx * Kx) *
                                           base[static_cast<std::size_t>(v)].R;
      }
      q[static_cast<std::size_t>(v)].C += spread * glm::dvec3(x[o + 3], x[o + 4], x[o + 5]);
    }
    if (radius1 > 0 && glm::length(q[1].C - q[0].C) > 0) {
      const double k = radius1 / glm::length(q[1].C - q[0].C);
      for (index_t v = 1; v < frames; ++v) q[static_cast<std::size_t>(v)].C = q[0].C + k * (q[static_cast<std::size_t>(v)].C - q[0].C);
    }
    return q;
  };
  std::size_t M = 0;
  for (const EpipolarPair& pr : pairs) M += pr.xa.size();
  if (M == 0) return;
  // Signed Sampson errors of every match, pairs in order; each match weighs 1 / its pair's count.
  auto residuals = [&](const std::vector<Pose>& q, Eigen::VectorXd& r) {
    r.resize(static_cast<Eigen::Index>(M));
    Eigen::Index i = 0;
    for (const EpipolarPair& pr : pairs)
      for_each_sampson(pr, q[static_cast<std::size_t>(pr.a)], q[static_cast<std::size_t>(pr.b)],
                       [&](double e2, double e) { r[i++] = std::isfinite(e2) ? e : 1e6; });
  };
  Eigen::VectorXd pair_weight(static_cast<Eigen::Index>(M));
  {
    Eigen::Index i = 0;
    for (const EpipolarPair& pr : pairs)
      for (std::size_t m = 0; m < pr.xa.size(); ++m) pair_weight[i++] = 1.0 / static_cast<double>(pr.xa.size());
  }
  auto robust = [&](const Eigen::VectorXd& r, double s2) {
    return (pair_weight.array() * r.array().square() / (r.array().square() + s2)).sum();
  };
  Eigen::VectorXd r, r1, rp;
  Eigen::MatrixXd J(static_cast<Eigen::Index>(M), static_cast<Eigen::Index>(P));
  for (const double scale : cfg.scales_px) {
    const double s2 = scale * scale;
    double lambda = 1e-3;
    residuals(pose, r);
    double cost = robust(r, s2);
    for (int it = 0; it < cfg.iterations; ++it) {
      // Forward differences: the residuals are smooth in the pose.
      const double h = 1e-6;
      for (index_t k = 0; k < P; ++k) {
        Eigen::VectorXd x = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(P));
        x[static_cast<Eigen::Index>(k)] = h;
        residuals(apply(pose, x), rp);
        J.col(static_cast<Eigen::Index>(k)) = (rp - r) / h;
      }
      // Reweighted least squares: Geman-McClure's weight s^2 / (e^2 + s^2)^2 per match.
      const Eigen::ArrayXd wgt = pair_weight.array() * s2 / (r.array().square() + s2).square();
      const Eigen::MatrixXd A = J.transpose() * (wgt.matrix().asDiagonal() * J);
      const Eigen::VectorXd g = J.transpose() * (wgt * r.array()).matrix();
      bool improved = false;
      while (lambda < 1e10) {
        Eigen::MatrixXd Al = A;
        Al.diagonal() += lambda * (A.diagonal().array() + 1e-12).matrix();
        const Eigen::VectorXd x = -Al.ldlt().solve(g);
        const std::vector<Pose> q = apply(pose, x);
        residuals(q, r1);
        const double c1 = robust(r1, s2);
        if (std::isfinite(c1) && c1 < cost) {
          improved = cost - c1 > 1e-12 * cost;
          pose = q, r = r1, cost = c1, lambda = std::max(lambda / 10, 1e-9);
          break;
        }
        lambda *= 10;
      }
      if (!improved) break;
    }
  }
  for (index_t f = 1; f < frames; ++f) {
    Camera c;
    c.R = pose[static_cast<std::size_t>(f)].R;
    c.t = -(c.R * pose[static_cast<std::size_t>(f)].C);
    camera_arrays<T>(c, nullptr, extrinsics + 12 * f);
  }
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
