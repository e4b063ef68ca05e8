#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <random>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

#include "flexsplat/solvers/procrustes.hpp"
#include "flexsplat/geometry/unproject.hpp"

using namespace flexsplat;

namespace {
Eigen::Matrix3d random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n;
  Eigen::Quaterniond q(n(rng), n(rng), n(rng), n(rng));
  return q.normalized().toRotationMatrix();
}
}  // namespace

TEST_CASE("rigid_fit recovers a rotation and translation exactly, ignores unweighted pairs and never reflects",
          "[geometry][procrustes]") {
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::Matrix3d R = random_rotation(rng);
    const Eigen::Vector3d t(u(rng), u(rng), u(rng));
    const index_t n = 50;
    std::vector<double> src(3 * n), dst(3 * n), w(n);
    for (index_t i = 0; i < n; ++i) {
      const Eigen::Vector3d p(u(rng), u(rng), u(rng));
      Eigen::Vector3d q = R * p + t;
      w[i] = 0.5 + 0.5 * (u(rng) + 1);
      if (i % 7 == 0) q += Eigen::Vector3d(5, -3, 2), w[i] = (i % 14 == 0) ? 0.0 : -1.0;  // outliers without weight
      for (int k = 0; k < 3; ++k) src[3 * i + k] = p(k), dst[3 * i + k] = q(k);
    }
    double Rf[9], tf[3];
    REQUIRE(geometry::rigid_fit(src.data(), dst.data(), w.data(), n, Rf, tf));
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) CHECK(Rf[3 * r + c] == Approx(R(r, c)).margin(1e-12));
      CHECK(tf[r] == Approx(t(r)).margin(1e-12));
    }
  }
  // Mirror-image points: the best proper rotation, determinant +1, not the reflection that would fit exactly.
  std::vector<double> src{1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1}, dst(src), w(4, 1.0);
  for (int i = 0; i < 4; ++i) dst[3 * i + 2] = -dst[3 * i + 2];
  double Rf[9], tf[3];
  REQUIRE(geometry::rigid_fit(src.data(), dst.data(), w.data(), 4, Rf, tf));
  const Eigen::Map<const Eigen::Matrix<double, 3, 3, Eigen::RowMajor>> Rm(Rf);
  CHECK(Rm.determinant() == Approx(1.0).margin(1e-12));
  CHECK((Rm * Rm.transpose() - Eigen::Matrix3d::Identity()).norm() < 1e-12);
  // Collinear points (or fewer than three with weight) leave the rotation free: reported, identity returned.
  std::vector<double> line{0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3};
  CHECK_FALSE(geometry::rigid_fit(line.data(), line.data(), w.data(), 4, Rf, tf));
  CHECK(Rf[0] == 1.0);
  const std::vector<double> two{1, 1, 0, 0};
  CHECK_FALSE(geometry::rigid_fit(src.data(), src.data(), two.data(), 4, Rf, tf));
}

TEST_CASE("cameras_from_points solves each view's camera from a point map and depth made with it, background "
          "at the confidence floor ignored", "[geometry][procrustes]") {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1, 1);
  const index_t S = 3, H = 9, W = 11, px = H * W;
  std::vector<double> E(12 * S), K(9 * S), depth(S * px), points(3 * S * px), conf(S * px);
  for (index_t f = 0; f < S; ++f) {
    const Eigen::Matrix3d R = f == 0 ? Eigen::Matrix3d::Identity() : random_rotation(rng);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) E[12 * f + 4 * r + c] = R(r, c);
      E[12 * f + 4 * r + 3] = f == 0 ? 0.0 : u(rng);
    }
    const double k[9] = {12.0 + f, 0, 5.2, 0, 11.0, 3.9, 0, 0, 1};
    std::copy(k, k + 9, K.begin() + 9 * f);
    for (index_t p = 0; p < px; ++p) {
      depth[f * px + p] = 2.0 + 0.5 * u(rng);
      conf[f * px + p] = p % 5 == 0 ? 1.0 : 1.5 + u(rng) * 0.4;
    }
  }
  geometry::unproject_depth_forward<double>(points.data(), depth.data(), E.data(), K.data(), S, H, W);
  for (index_t f = 0; f < S; ++f)
    for (index_t p = 0; p < px; p += 5)
      for (int k = 0; k < 3; ++k) points[3 * (f * px + p) + k] = 100.0 * u(rng);  // background: garbage at conf 1
  std::vector<double> solved(12 * S);
  bool ok[S];
  geometry::cameras_from_points<double>(solved.data(), points.data(), conf.data(), depth.data(), K.data(), S, H, W, ok);
  for (index_t f = 0; f < S; ++f) {
    CHECK(ok[f]);
    for (int i = 0; i < 12; ++i) CHECK(solved[12 * f + i] == Approx(E[12 * f + i]).margin(1e-9));
  }
  // Every pixel at the floor: nothing to fit.
  std::fill(conf.begin(), conf.end(), 1.0);
  geometry::cameras_from_points<double>(solved.data(), points.data(), conf.data(), depth.data(), K.data(), S, H, W, ok);
  CHECK_FALSE(ok[1]);
  K[0] = 0;
  CHECK_THROWS_WITH(geometry::cameras_from_points<double>(solved.data(), points.data(), conf.data(), depth.data(),
                                                          K.data(), S, H, W, ok),
                    Catch::Contains("frame 0 has focal lengths (0"));
}

namespace {
// Views of a textured bump z = 3 + 0.3 sin(2x) cos(2y) (world = view 0's frame): the descriptor of a pixel is the code
// of the surface point it sees (a fixed random projection through a sine), so nearest neighbours find the true
// correspondences. Pixels count as object where `object(view, X)` holds for the surface point X they see.
struct BumpViews {
  static constexpr index_t H = 24, W = 24, px = H * W, D = 8;
  index_t S;
  std::vector<double> E, K, depth, desc, fg;
  std::vector<Eigen::Vector3d> seen;  // the surface point of every pixel
  std::vector<double> proj;

  template <class Object>
  BumpViews(const std::vector<Eigen::Matrix3d>& R, const std::vector<Eigen::Vector3d>& t, Object object, std::mt19937& rng)
      : S(static_cast<index_t>(R.size())), E(12 * S), K(9 * S), depth(S * px), desc(S * px * D), fg(S * px, 0.0),
        seen(S * px), proj(3 * D) {
    std::uniform_real_distribution<double> u(-1, 1);
    for (double& p : proj) p = u(rng);
    for (index_t v = 0; v < S; ++v) {
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) E[12 * v + 4 * r + c] = R[v](r, c);
        E[12 * v + 4 * r + 3] = t[v](r);
      }
      const double k[9] = {30, 0, 11.5, 0, 30, 11.5, 0, 0, 1};
      std::copy(k, k + 9, K.begin() + 9 * v);
      for (index_t y = 0; y < H; ++y)
        for (index_t x = 0; x < W; ++x) {
          // March along the pixel's ray (camera frame of view v) to the surface.
          const Eigen::Vector3d dir((x - 11.5) / 30, (y - 11.5) / 30, 1);
          double z = 1;
          for (int it = 0; it < 200; ++it) {
            const Eigen::Vector3d X = R[v].transpose() * (z * dir - t[v]);
            z += 0.5 * (surface_z(X(0), X(1)) - X(2));
          }
          const Eigen::Vector3d X = R[v].transpose() * (z * dir - t[v]);
          const index_t p = v * px + y * W + x;
          depth[p] = z;
          seen[p] = X;
          fg[p] = std::abs(surface_z(X(0), X(1)) - X(2)) < 1e-6 && object(v, X) ? 0.9 : 0.1;
          code(X, &desc[p * D]);
        }
    }
  }
  static double surface_z(double x, double y) { return 3 + 0.3 * std::sin(2 * x) * std::cos(2 * y); }
  void code(const Eigen::Vector3d& X, double* out) const {
    for (index_t k = 0; k < D; ++k)
      out[k] = std::sin(3 * (proj[3 * k] * X(0) + proj[3 * k + 1] * X(1) + proj[3 * k + 2] * X(2)));
  }
  // Rotation error (degrees) and translation error of the solved camera of view v against the truth.
  std::pair<double, double> error(const std::vector<double>& solved, index_t v) const {
    const Eigen::Map<const Eigen::Matrix<double, 3, 4, Eigen::RowMajor>> got(solved.data() + 12 * v), want(E.data() + 12 * v);
    const double angle =
        Eigen::AngleAxisd(got.block<3, 3>(0, 0) * want.block<3, 3>(0, 0).transpose()).angle() * 180 / 3.14159265358979;
    return {angle, (got.col(3) - want.col(3)).norm()};
  }
};

// Three cameras side by side along x, each turned a little further right (0, 0.1, 0.2 rad about y).
std::pair<std::vector<Eigen::Matrix3d>, std::vector<Eigen::Vector3d>> side_by_side() {
  const std::vector<Eigen::Matrix3d> R{Eigen::Matrix3d::Identity(),
                                       Eigen::AngleAxisd(-0.1, Eigen::Vector3d::UnitY()).toRotationMatrix(),
                                       Eigen::AngleAxisd(-0.2, Eigen::Vector3d::UnitY()).toRotationMatrix()};
  return {R, {Eigen::Vector3d::Zero(), R[1] * Eigen::Vector3d(-0.9, 0, 0), R[2] * Eigen::Vector3d(-1.8, 0, 0)}};
}
}  // namespace

TEST_CASE("cameras_from_matches solves cameras from descriptor matches and depth, wrong matches voted out",
          "[geometry][procrustes]") {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  const Eigen::Matrix3d R1 = Eigen::AngleAxisd(0.35, Eigen::Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  BumpViews b({Eigen::Matrix3d::Identity(), R1}, {Eigen::Vector3d::Zero(), Eigen::Vector3d(0.4, -0.1, 0.3)},
              [](index_t, const Eigen::Vector3d&) { return true; }, rng);
  const index_t px = BumpViews::px, D = BumpViews::D;
  for (index_t p = px; p < 2 * px; ++p)  // 10% of view 1's descriptors scrambled
    if (p % 10 == 3)
      for (index_t k = 0; k < D; ++k) b.desc[p * D + k] = u(rng);
  std::vector<double> solved(24);
  bool ok[2];
  index_t found[2];
  geometry::cameras_from_matches<double>(solved.data(), b.desc.data(), b.fg.data(), b.depth.data(), b.K.data(), 2,
                                         BumpViews::H, BumpViews::W, D, ok, found);
  CHECK(ok[0]);
  CHECK(ok[1]);
  CHECK(found[0] == 0);
  CHECK(found[1] > px / 4);
  for (int i = 0; i < 12; ++i) CHECK(solved[i] == Approx(b.E[i]).margin(1e-12));
  // Matches snap to pixels (one pixel is 1.9 degrees of view here): within a pixel's angle and 3% of the depth.
  const auto [angle, shift] = b.error(solved, 1);
  INFO("rotation error " << angle << " deg");
  CHECK(angle < 1.9);
  CHECK(shift < 0.09);
  // The same twice: hypotheses come from a fixed sequence.
  std::vector<double> again(24);
  geometry::cameras_from_matches<double>(again.data(), b.desc.data(), b.fg.data(), b.depth.data(), b.K.data(), 2,
                                         BumpViews::H, BumpViews::W, D);
  CHECK(again == solved);
  // No pixel counts as object: nothing to match.
  std::fill(b.fg.begin(), b.fg.end(), 0.0);
  geometry::cameras_from_matches<double>(solved.data(), b.desc.data(), b.fg.data(), b.depth.data(), b.K.data(), 2,
                                         BumpViews::H, BumpViews::W, D, ok);
  CHECK_FALSE(ok[1]);
  for (int i = 0; i < 12; ++i) CHECK(solved[12 + i] == (i == 0 || i == 5 || i == 10 ? 1.0 : 0.0));
}

TEST_CASE("cameras_from_matches keeps the pose when most matches are confidently wrong", "[geometry][procrustes]") {
  // 60% of view 1's pixels carry the code of another surface point view 0 sees, so their matches are exact in
  // descriptor space and wrong in 3-D: a least-squares start (all matches weighted alike) lands far off.
  std::mt19937 rng(11);
  const Eigen::Matrix3d R1 = Eigen::AngleAxisd(0.3, Eigen::Vector3d(-0.1, 1, 0.2).normalized()).toRotationMatrix();
  BumpViews b({Eigen::Matrix3d::Identity(), R1}, {Eigen::Vector3d::Zero(), Eigen::Vector3d(0.5, 0.1, 0.2)},
              [](index_t, const Eigen::Vector3d&) { return true; }, rng);
  const index_t px = BumpViews::px, D = BumpViews::D;
  std::uniform_int_distribution<index_t> pick(0, px - 1);
  std::uniform_real_distribution<double> coin(0, 1);
  for (index_t p = px; p < 2 * px; ++p)
    if (coin(rng) < 0.6) b.code(b.seen[static_cast<std::size_t>(pick(rng))], &b.desc[p * D]);
  std::vector<double> solved(24);
  bool ok[2];
  geometry::cameras_from_matches<double>(solved.data(), b.desc.data(), b.fg.data(), b.depth.data(), b.K.data(), 2,
                                         BumpViews::H, BumpViews::W, D, ok);
  REQUIRE(ok[1]);
  const auto [angle, shift] = b.error(solved, 1);
  INFO("rotation error " << angle << " deg, translation error " << shift);
  CHECK(angle < 1.9);
  CHECK(shift < 0.09);
}

TEST_CASE("cameras_from_matches places a view that shares nothing with the first through one that does",
          "[geometry][procrustes]") {
  // Three cameras side by side along x: view 2's object pixels are surface points view 0 cannot see (x > 1.25, past
  // the edge of its field of view at this depth), all of which view 1 sees.
  std::mt19937 rng(5);
  const auto [R, t] = side_by_side();
  BumpViews b(R, t, [](index_t v, const Eigen::Vector3d& X) { return v != 2 || X(0) > 1.25; }, rng);
  std::vector<double> solved(36);
  bool ok[3];
  index_t found[3];
  geometry::cameras_from_matches<double>(solved.data(), b.desc.data(), b.fg.data(), b.depth.data(), b.K.data(), 3,
                                         BumpViews::H, BumpViews::W, BumpViews::D, ok, found);
  REQUIRE(ok[1]);
  REQUIRE(ok[2]);
  CHECK(found[2] > 20);
  for (index_t v = 1; v < 3; ++v) {
    const auto [angle, shift] = b.error(solved, v);
    INFO("view " << v << ": rotation error " << angle << " deg, translation error " << shift);
    CHECK(angle < 1.9);
    CHECK(shift < 0.09);
  }
  // The pixels of view 2 do not see anything view 0 sees as object, so view 0 alone cannot place it.
  std::vector<double> two(24), d2, f2, z2, k2;
  for (index_t v : {0, 2}) {
    d2.insert(d2.end(), b.desc.begin() + v * BumpViews::px * BumpViews::D, b.desc.begin() + (v + 1) * BumpViews::px * BumpViews::D);
    f2.insert(f2.end(), b.fg.begin() + v * BumpViews::px, b.fg.begin() + (v + 1) * BumpViews::px);
    z2.insert(z2.end(), b.depth.begin() + v * BumpViews::px, b.depth.begin() + (v + 1) * BumpViews::px);
    k2.insert(k2.end(), b.K.begin() + 9 * v, b.K.begin() + 9 * v + 9);
  }
  geometry::cameras_from_matches<double>(two.data(), d2.data(), f2.data(), z2.data(), k2.data(), 2, BumpViews::H,
                                         BumpViews::W, BumpViews::D, ok);
  const Eigen::Map<const Eigen::Matrix<double, 3, 4, Eigen::RowMajor>> got(two.data() + 12);
  const double angle = Eigen::AngleAxisd(got.block<3, 3>(0, 0) * R[2].transpose()).angle() * 180 / 3.14159265358979;
  CHECK((!ok[1] || angle > 1.9 || (got.col(3) - t[2]).norm() > 0.09));
}

TEST_CASE("cameras_from_matches: reordering views 2..V reorders the cameras", "[geometry][procrustes][permutation]") {
  // Four views of the bump, 20% of each non-reference view's descriptors scrambled; solved as 0,1,2,3 and as 0,3,1,2.
  std::mt19937 rng(3);
  std::vector<Eigen::Matrix3d> R{Eigen::Matrix3d::Identity()};
  std::vector<Eigen::Vector3d> t{Eigen::Vector3d::Zero()};
  for (int v = 1; v < 4; ++v) {
    R.push_back(Eigen::AngleAxisd(0.12 * v, Eigen::Vector3d(0.1 * v, 1, -0.2).normalized()).toRotationMatrix());
    t.push_back(Eigen::Vector3d(0.2 * v, -0.05 * v, 0.1));
  }
  BumpViews b(R, t, [](index_t, const Eigen::Vector3d&) { return true; }, rng);
  const index_t px = BumpViews::px, D = BumpViews::D;
  std::uniform_real_distribution<double> u(-1, 1), coin(0, 1);
  for (index_t p = px; p < 4 * px; ++p)
    if (coin(rng) < 0.2)
      for (index_t k = 0; k < D; ++k) b.desc[p * D + k] = u(rng);
  const index_t order[4] = {0, 3, 1, 2};
  std::vector<double> desc, fg, depth, K;
  for (index_t v : order) {
    desc.insert(desc.end(), b.desc.begin() + v * px * D, b.desc.begin() + (v + 1) * px * D);
    fg.insert(fg.end(), b.fg.begin() + v * px, b.fg.begin() + (v + 1) * px);
    depth.insert(depth.end(), b.depth.begin() + v * px, b.depth.begin() + (v + 1) * px);
    K.insert(K.end(), b.K.begin() + 9 * v, b.K.begin() + 9 * v + 9);
  }
  std::vector<double> first(48), second(48);
  bool ok1[4], ok2[4];
  index_t n1[4], n2[4];
  geometry::cameras_from_matches<double>(first.data(), b.desc.data(), b.fg.data(), b.depth.data(), b.K.data(), 4,
                                         BumpViews::H, BumpViews::W, D, ok1, n1);
  geometry::cameras_from_matches<double>(second.data(), desc.data(), fg.data(), depth.data(), K.data(), 4, BumpViews::H,
                                         BumpViews::W, D, ok2, n2);
  for (index_t v = 0; v < 4; ++v) {
    CAPTURE(v);
    REQUIRE(ok1[order[v]]);
    CHECK(ok2[v]);
    CHECK(n2[v] == n1[order[v]]);
    for (int i = 0; i < 12; ++i) CHECK(second[static_cast<std::size_t>(12 * v + i)] == Approx(first[static_cast<std::size_t>(12 * order[v] + i)]).margin(1e-9));
  }
  // Placed: views 1..3 are turned 6.9, 13.8 and 20.6 degrees and moved 0.23, 0.42 and 0.63 from view 0, so an unsolved
  // (identity) camera is off by that much. The solved ones are off by 0.8, 3.5 and 4.0 degrees and 0.008, 0.06 and
  // 0.13 here (views linked through another view add up the errors of both fits, and 20% of their descriptors are
  // scrambled): each must be within 5 degrees and half the unsolved error, in rotation and in translation, which an
  // identity camera fails on every view.
  std::vector<double> identity(48, 0.0);
  for (index_t v = 0; v < 4; ++v)
    for (int r = 0; r < 3; ++r) identity[static_cast<std::size_t>(12 * v + 5 * r)] = 1;
  for (index_t v = 1; v < 4; ++v) {
    const auto [angle, shift] = b.error(first, v);
    const auto [unsolved_angle, unsolved_shift] = b.error(identity, v);
    INFO("view " << v << ": rotation error " << angle << " deg, translation error " << shift << "; an identity camera: "
                 << unsolved_angle << " deg, " << unsolved_shift);
    REQUIRE(unsolved_angle > 6.8);
    REQUIRE(unsolved_shift > 0.2);
    CHECK(angle < std::min(5.0, unsolved_angle / 2));
    CHECK(shift < unsolved_shift / 2);
  }
}

TEST_CASE("cameras_from_correspondences solves cameras from given pixel correspondences, either order of a pair",
          "[geometry][procrustes]") {
  // The three side-by-side views of the previous case; correspondences from the geometry: a pixel of view a whose
  // surface point projects into view b onto a pixel that sees the same point (within a tenth of the bump's period);
  // view 2 shares nothing with view 0 and is placed through view 1.
  std::mt19937 rng(5);
  const auto [R, t] = side_by_side();
  BumpViews b(R, t, [](index_t, const Eigen::Vector3d&) { return true; }, rng);
  struct Match {
    index_t view_a, pixel_a, view_b, pixel_b;
  };
  std::vector<Match> matches;
  const index_t H = BumpViews::H, W = BumpViews::W, px = BumpViews::px;
  index_t count_01 = 0, count_21 = 0;
  for (index_t a = 0; a < 3; ++a)
    for (index_t bv = 0; bv < 3; ++bv) {
      // Pair (0, 1) as 0 -> 1, pair (1, 2) only as 2 -> 1 (the larger view first); views 0 and 2 share nothing.
      if (!((a == 0 && bv == 1) || (a == 2 && bv == 1))) continue;
      for (index_t p = 0; p < px; p += 3) {
        const Eigen::Vector3d X = b.seen[static_cast<std::size_t>(a * px + p)];
        const Eigen::Vector3d c = R[bv] * X + t[bv];
        const long x = std::lround(30 * c(0) / c(2) + 11.5), y = std::lround(30 * c(1) / c(2) + 11.5);
        if (x < 0 || y < 0 || x >= W || y >= H) continue;
        const index_t q = y * W + x;
        if ((b.seen[static_cast<std::size_t>(bv * px + q)] - X).norm() > 0.3) continue;
        matches.push_back({a, p, bv, q});
        ++(a == 0 ? count_01 : count_21);
      }
    }
  REQUIRE(count_01 >= 6);
  REQUIRE(count_21 >= 6);
  std::vector<double> solved(36);
  bool ok[3];
  index_t found[3];
  geometry::cameras_from_correspondences<double, Match>(solved.data(), std::span<const Match>(matches), b.depth.data(),
                                                        b.K.data(), 3, H, W, ok, found);
  for (int i = 0; i < 12; ++i) CHECK(solved[i] == Approx(b.E[i]).margin(1e-12));
  for (index_t v = 1; v < 3; ++v) {
    REQUIRE(ok[v]);
    CHECK(found[v] >= 6);
    const auto [angle, shift] = b.error(solved, v);
    INFO("view " << v << ": rotation error " << angle << " deg, translation error " << shift);
    CHECK(angle < 1.9);
    CHECK(shift < 0.09);
  }
  // Without correspondences nothing links; a correspondence outside the views is refused by name.
  geometry::cameras_from_correspondences<double, Match>(solved.data(), std::span<const Match>(), b.depth.data(),
                                                        b.K.data(), 3, H, W, ok);
  CHECK(ok[0]);
  CHECK_FALSE(ok[1]);
  CHECK_FALSE(ok[2]);
  const std::vector<Match> bad{{0, 5, 3, 7}};
  CHECK_THROWS_WITH((geometry::cameras_from_correspondences<double, Match>(solved.data(), std::span<const Match>(bad),
                                                                           b.depth.data(), b.K.data(), 3, H, W)),
                    Catch::Contains("correspondence (view 0 pixel 5, view 3 pixel 7) is outside 3 views of 24 x 24"));
}
