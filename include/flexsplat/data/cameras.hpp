#pragma once
// The data module's orbit samplers (the camera type is core/camera.hpp's): random views covering the shared
// Blender renders, and the structured 4-view evaluation set.
#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/data/random.hpp"

namespace flexsplat {
inline namespace v0 {
namespace data {

// Orbit camera: eye = radius * (cos el cos az, cos el sin az, sin el) (core/camera.hpp's orbit_eye) looking at
// `target`, as in the shared renders.
inline Camera orbit_camera(double elevation_deg, double azimuth_deg, double radius, double hfov_deg, int width,
                           int height, glm::dvec3 target = glm::dvec3(0.0)) {
  const double el = elevation_deg * std::numbers::pi / 180, az = azimuth_deg * std::numbers::pi / 180;
  const glm::dvec3 eye = orbit_eye(el, az, radius);
  Camera cam = look_at(eye, target, width, height, intrinsics_from_fov(width, height, hfov_deg));
  cam.elevation_deg = elevation_deg;
  cam.azimuth_deg = azimuth_deg;
  return cam;
}

// Ranges of the random orbit views. The shared renders (measured from their cameras.json, see docs/data.md) use
// elevation 0..60 deg, azimuth 0..315 deg, radius 3.0 and horizontal FOV 45 deg; the defaults contain them with
// margin, and radius / FOV are paired so that the unit bounding sphere always fits in the image.
struct OrbitRanges {
  double elevation_min = -10, elevation_max = 70;  // degrees
  double azimuth_min = 0, azimuth_max = 360;       // degrees
  double radius_min = 2.8, radius_max = 3.4;
  double hfov_min = 42, hfov_max = 50;             // degrees
  double target_jitter = 0.05;                     // look-at point uniform in a ball of this radius
  // > 0: a scene's views after its first lie within this many degrees of azimuth (and half as many of elevation) of
  // it, inside the ranges above: small baselines first, the curriculum of pose training. 0: independent views.
  double max_baseline_deg = 0;
};

inline void check_ranges(const OrbitRanges& r) {
  require(r.elevation_min <= r.elevation_max && r.elevation_min > -89 && r.elevation_max < 89,
          "OrbitRanges: elevation [", r.elevation_min, ", ", r.elevation_max, "] must be ordered inside (-89, 89)");
  require(r.azimuth_min <= r.azimuth_max, "OrbitRanges: azimuth range is reversed");
  require(r.radius_min > 0 && r.radius_min <= r.radius_max, "OrbitRanges: radius [", r.radius_min, ", ",
          r.radius_max, "] must be positive and ordered");
  require(r.hfov_min > 1 && r.hfov_max < 170 && r.hfov_min <= r.hfov_max, "OrbitRanges: fov [", r.hfov_min, ", ",
          r.hfov_max, "] must be ordered inside (1, 170)");
  require(r.target_jitter >= 0 && r.target_jitter < r.radius_min, "OrbitRanges: target jitter ", r.target_jitter,
          " must be in [0, radius_min)");
  require(r.max_baseline_deg >= 0 && r.max_baseline_deg <= 360, "OrbitRanges: max_baseline_deg ", r.max_baseline_deg,
          " must be in [0, 360]");
}

// One random orbit view; with `first` and ranges.max_baseline_deg > 0, one near that view.
inline Camera sample_orbit_camera(Rng& rng, const OrbitRanges& ranges, int width, int height,
                                  const Camera* first = nullptr) {
  check_ranges(ranges);
  double el = rng.uniform(ranges.elevation_min, ranges.elevation_max);
  double az = rng.uniform(ranges.azimuth_min, ranges.azimuth_max);
  if (first && ranges.max_baseline_deg > 0) {
    const double b = ranges.max_baseline_deg;
    el = std::clamp(first->elevation_deg + (el - ranges.elevation_min) / std::max(ranges.elevation_max - ranges.elevation_min, 1e-9) * b - b / 2,
                    ranges.elevation_min, ranges.elevation_max);
    az = first->azimuth_deg + (az - ranges.azimuth_min) / std::max(ranges.azimuth_max - ranges.azimuth_min, 1e-9) * 2 * b - b;
  }
  const double radius = rng.uniform(ranges.radius_min, ranges.radius_max);
  const double fov = rng.uniform(ranges.hfov_min, ranges.hfov_max);
  glm::dvec3 target(0.0);
  if (ranges.target_jitter > 0)
    for (;;) {
      const glm::dvec3 p(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
      if (glm::dot(p, p) <= 1) {
        target = ranges.target_jitter * p;
        break;
      }
    }
  return orbit_camera(el, az, radius, fov, width, height, target);
}

// The evaluation's structured input views: elevation 20 deg, azimuths 0/90/180/270, radius 3, FOV 45.
inline std::vector<Camera> structured_cameras(int width, int height) {
  std::vector<Camera> cams;
  for (double az : {0.0, 90.0, 180.0, 270.0}) cams.push_back(orbit_camera(20, az, 3.0, 45.0, width, height));
  return cams;
}

// Orbit parameters recovered from a camera looking at (about) the origin: elevation, azimuth (in [0, 360)), radius
// and horizontal FOV, all in degrees except the radius.
struct OrbitParameters {
  double elevation_deg, azimuth_deg, radius, hfov_deg;
};

inline OrbitParameters orbit_parameters(const Camera& cam) {
  const glm::dvec3 c = cam.centre();
  const double radius = glm::length(c);
  double az = std::atan2(c.y, c.x) * 180 / std::numbers::pi;
  if (az < 0) az += 360;
  return {std::asin(c.z / radius) * 180 / std::numbers::pi, az, radius,
          2 * std::atan(0.5 * cam.width / cam.K[0][0]) * 180 / std::numbers::pi};
}

}  // namespace data
}  // namespace v0
}  // namespace flexsplat
