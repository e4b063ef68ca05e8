#pragma once
// Cameras from silhouettes and depth, for photos around one object: every view is placed on an orbit around a common
// centre (looking at it along its optical axis, image up towards the object's up, roll small) and the orbit
// parameters (elevation, azimuth, roll, distance) are searched so that every view's object pixels, unprojected with
// their depth, land inside every other view's silhouette and not in front of its surface (the visual-hull and
// free-space constraints, which hold between any two views, however little they overlap), where they meet that
// surface with the same colour. A beam search over a grid adding the views one by one, coordinate sweeps over the
// views, then a local pattern search. No gradient; the first view's camera is the world, as cameras_from_matches.
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/solvers/descriptor.hpp"
#include "flexsplat/geometry/unproject.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

struct OrbitSearchConfig {
  double min_foreground = 0.5;      // pixels at or above this object probability form the silhouette
  index_t samples = 256;            // object pixels per view scored against the other views
  double elevation_min_deg = -20;   // the coarse grid's elevations (degrees above the object's equator)
  double elevation_max_deg = 70;
  double elevation_step_deg = 10;
  double azimuth_step_deg = 10;     // the coarse grid's azimuths relative to the first view
  double silhouette_px = 2;         // a point this many pixels outside another view's silhouette costs 1
  double depth_tolerance = 0.03;    // relative depth within which two views see the same surface point
  double occluded_cost = 0.1;       // a point hidden behind another view's surface (explains nothing)
  double colour_weight = 0.5;       // cost of a colour difference of 1 (per channel mean) on a shared surface point
  // With OrbitDescriptors given, a shared surface point earns this times log(N p) / log N clamped to [-1, 1], p the
  // softmax over the other view's N object pixels of cos / descriptor_temperature at the pixel it lands on: a match
  // head's own likelihood against a uniform guess, evidence for a placement and against it.
  double descriptor_weight = 0;
  double descriptor_temperature = 0.1;  // loss/match.hpp's default
  // > 0: every sampled point may lie anywhere within this relative range of its depth along its ray (depth_candidates
  // evenly spaced depths, the cheapest counts) and the other view's surface is as uncertain (its tolerance grows by
  // the range): predicted depth is trusted to a range, the views' silhouettes, surfaces and colours choose within it
  // (a plane sweep per point). 0: the depth as given.
  double depth_range = 0;
  index_t depth_candidates = 5;
  // The rim's median depth lies in front of the orbit centre (by 5-15 % on the shared objects): the coarse search tries
  // these multiples of it for every view.
  std::vector<double> distance_scales{1.0, 1.05, 1.1, 1.15, 1.2};
  double coarse_tolerance = 3;      // the grid stages' silhouette and depth tolerances, in multiples of the above
  index_t beam_width = 16;           // partial solutions kept while views are added
  index_t finalists = 3;            // best beams refined to the end
  int sweeps = 2;                   // coordinate sweeps on the grid after the beam search
  int refine_rounds = 4;            // halvings of the local search's steps
  double refine_step_deg = 5;       // the local search's first angle step
  double refine_step_distance = 0.04;  // its first relative distance step
};

// Per-pixel descriptors [S, H, W, dim] (a match head's): shared surface points should have similar ones.
template <class T>
struct OrbitDescriptors {
  const T* data = nullptr;
  index_t dim = 0;
};

// The search's objective split by what each sampled point's cost came from (orbit_search_cost's `parts`): the parts
// sum to the cost. A point counts where it lands at its cheapest depth candidate.
struct OrbitCostParts {
  double off_image = 0;   // behind the other camera or outside its image: 1 each
  double silhouette = 0;  // outside the other view's silhouette
  double free_space = 0;  // in front of the other view's surface
  double occluded = 0;    // behind it (occluded_cost)
  double colour = 0;      // on it: the colour difference
  double descriptor = 0;  // on it: minus the descriptor reward
  double total() const { return off_image + silhouette + free_space + occluded + colour + descriptor; }
  OrbitCostParts& operator+=(const OrbitCostParts& o) {
    off_image += o.off_image, silhouette += o.silhouette, free_space += o.free_space;
    occluded += o.occluded, colour += o.colour, descriptor += o.descriptor;
    return *this;
  }
};

// One view's orbit parameters (radians; distance in depth units).
struct OrbitPose {
  double elevation = 0, azimuth = 0, roll = 0, distance = 1;
};

namespace orbit_detail {

struct View {
  index_t h = 0, w = 0;
  double fx = 1, fy = 1, cx = 0, cy = 0;
  std::vector<unsigned char> mask;  // [h * w] object pixel
  std::vector<float> outside;       // [h * w] pixels to the silhouette (0 inside)
  std::vector<float> depth;         // [h * w]
  std::vector<float> colour;        // [h * w * 3] (empty without images)
  std::vector<double> point;        // sampled object pixels in the camera frame [n, 3]
  std::vector<float> point_colour;  // [n, 3] (empty without images)
  index_t dim = 0;                  // descriptor width (0: none)
  std::vector<float> descriptor;    // [h * w, dim] unit length (zero where a descriptor is zero or not finite)
  std::vector<float> point_descriptor;  // [n, dim]
  index_t slot = 0;                 // position among the searched views
  // [other view's slot][n]: log of the sum over its object pixels of exp(cos / temperature), per sampled point (empty
  // without descriptors)
  std::vector<std::vector<double>> log_sum;
  double log_objects = 0;           // log of the number of object pixels (with descriptors)
  double distance = 1;              // from the camera to the orbit centre along the optical axis
};

// Two-pass 3-4 chamfer distance to the nearest mask pixel, in pixels.
inline void chamfer_outside(View& v) {
  const index_t h = v.h, w = v.w;
  const float inf = 1e9f;
  v.outside.assign(static_cast<std::size_t>(h * w), inf);
  auto at = [&](index_t y, index_t x) -> float& { return v.outside[static_cast<std::size_t>(y * w + x)]; };
  for (index_t i = 0; i < h * w; ++i)
    if (v.mask[static_cast<std::size_t>(i)]) v.outside[static_cast<std::size_t>(i)] = 0;
  for (index_t y = 0; y < h; ++y)
    for (index_t x = 0; x < w; ++x) {
      float d = at(y, x);
      if (x > 0) d = std::min(d, at(y, x - 1) + 3);
      if (y > 0) {
        d = std::min(d, at(y - 1, x) + 3);
        if (x > 0) d = std::min(d, at(y - 1, x - 1) + 4);
        if (x + 1 < w) d = std::min(d, at(y - 1, x + 1) + 4);
      }
      at(y, x) = d;
    }
  for (index_t y = h - 1; y >= 0; --y)
    for (index_t x = w - 1; x >= 0; --x) {
      float d = at(y, x);
      if (x + 1 < w) d = std::min(d, at(y, x + 1) + 3);
      if (y + 1 < h) {
        d = std::min(d, at(y + 1, x) + 3);
        if (x + 1 < w) d = std::min(d, at(y + 1, x + 1) + 4);
        if (x > 0) d = std::min(d, at(y + 1, x - 1) + 4);
      }
      at(y, x) = d;
    }
  for (float& d : v.outside) d /= 3;
}

// World-to-camera of an orbit pose around the origin, object up +z (core/camera.hpp's look_at), then the roll about
// the optical axis.
inline void orbit_extrinsics(const OrbitPose& p, glm::dmat3& R, glm::dvec3& t) {
  const glm::dvec3 eye = orbit_eye(p.elevation, p.azimuth, p.distance);
  const Camera cam = look_at(eye, glm::dvec3(0.0), 1, 1, glm::dmat3(1.0));
  const double c = std::cos(p.roll), s = std::sin(p.roll);
  glm::dmat3 roll(1.0);  // column-major: rotates the camera's x, y axes about z
  roll[0][0] = c, roll[1][0] = -s, roll[0][1] = s, roll[1][1] = c;
  R = roll * cam.R;
  t = -(R * eye);
}

struct Placed {
  glm::dmat3 R{1.0};
  glm::dvec3 t{0.0};
};

inline Placed place(const OrbitPose& p) {
  Placed q;
  orbit_extrinsics(p, q.R, q.t);
  return q;
}

// Cosine / temperature of view a's sampled point i and view b's pixel.
inline double descriptor_logit(const View& a, index_t i, const View& b, std::size_t pix, double temperature) {
  const float* da = a.point_descriptor.data() + static_cast<std::size_t>(i * a.dim);
  const float* db = b.descriptor.data() + pix * static_cast<std::size_t>(b.dim);
  double dot = 0;
  for (index_t d = 0; d < a.dim; ++d) dot += static_cast<double>(da[d]) * static_cast<double>(db[d]);
  return dot / temperature;
}

// a.log_sum[b.slot]: for each of view a's sampled points, the log-sum-exp of its logits over view b's object pixels.
inline void descriptor_log_sums(View& a, const View& b, double temperature) {
  const index_t n = static_cast<index_t>(a.point.size() / 3);
  std::vector<double>& out = a.log_sum[static_cast<std::size_t>(b.slot)];
  out.assign(static_cast<std::size_t>(n), 0.0);
  parallel_for(n, [&](index_t i0, index_t i1, int) {
    std::vector<double> s;
    for (index_t i = i0; i < i1; ++i) {
      s.clear();
      double top = -std::numeric_limits<double>::infinity();
      for (std::size_t p = 0; p < b.mask.size(); ++p)
        if (b.mask[p]) s.push_back(descriptor_logit(a, i, b, p, temperature)), top = std::max(top, s.back());
      double sum = 0;
      for (double x : s) sum += std::exp(x - top);
      out[static_cast<std::size_t>(i)] = top + std::log(sum);
    }
  });
}

// log(N p) / log N clamped to [-1, 1] and rounded to float (the descriptors' precision): p the softmax over view b's N object pixels of view
// a's point i's logits, at pixel pix.
inline double descriptor_reward(const View& a, index_t i, const View& b, std::size_t pix, double log_sum,
                                double temperature) {
  const double r = (descriptor_logit(a, i, b, pix, temperature) - log_sum + b.log_objects) / b.log_objects;
  return static_cast<double>(static_cast<float>(std::clamp(r, -1.0, 1.0)));
}

// Mean cost of view a's sampled points seen from view b; parts (may be null) receives it split by kind.
inline double pair_cost(const View& a, const Placed& pa, const View& b, const Placed& pb, const OrbitSearchConfig& cfg,
                        OrbitCostParts* parts = nullptr) {
  const index_t n = static_cast<index_t>(a.point.size() / 3);
  if (n == 0) return 0;
  const glm::dmat3 M = pb.R * glm::transpose(pa.R);
  const glm::dvec3 m = pb.t - M * pa.t;
  const bool colours = !a.point_colour.empty() && !b.colour.empty() && cfg.colour_weight > 0;
  const double* log_sum = static_cast<std::size_t>(b.slot) < a.log_sum.size() && !a.log_sum[static_cast<std::size_t>(b.slot)].empty()
                              ? a.log_sum[static_cast<std::size_t>(b.slot)].data()
                              : nullptr;
  const double floor = log_sum ? -cfg.descriptor_weight : 0;  // the cheapest a point can be
  // Cost of view a's point i placed at Y in view b's frame; into `part` (may be null) by kind, times w.
  auto point_cost = [&](index_t i, const glm::dvec3& Y, OrbitCostParts* part = nullptr, double w = 0) -> double {
    auto put = [&](double OrbitCostParts::*field, double c) {
      if (part) part->*field += w * c;
      return c;
    };
    if (!(Y.z > 1e-9)) return put(&OrbitCostParts::off_image, 1);
    const double u = b.fx * Y.x / Y.z + b.cx, v = b.fy * Y.y / Y.z + b.cy;
    const double ur = std::round(u), vr = std::round(v);
    if (!(ur >= 0 && vr >= 0 && ur < static_cast<double>(b.w) && vr < static_cast<double>(b.h)))
      return put(&OrbitCostParts::off_image, 1);
    const std::size_t pix = static_cast<std::size_t>(static_cast<index_t>(vr) * b.w + static_cast<index_t>(ur));
    const double out = static_cast<double>(b.outside[pix]);
    if (out > 0) return put(&OrbitCostParts::silhouette, std::min(out / cfg.silhouette_px, 1.0));
    // View b's depth is trusted to the same range as view a's.
    const double z = static_cast<double>(b.depth[pix]), tol = (cfg.depth_tolerance + cfg.depth_range) * z;
    if (Y.z < z - tol)  // free space of view b holds a surface point
      return put(&OrbitCostParts::free_space, std::min((z - tol - Y.z) / tol, 1.0));
    if (Y.z > z + tol) return put(&OrbitCostParts::occluded, cfg.occluded_cost);
    double c = 0;
    if (colours) {
      double diff = 0;
      for (int k = 0; k < 3; ++k)
        diff += std::abs(static_cast<double>(a.point_colour[static_cast<std::size_t>(3 * i + k)]) -
                         static_cast<double>(b.colour[3 * pix + static_cast<std::size_t>(k)]));
      c += put(&OrbitCostParts::colour, cfg.colour_weight * diff / 3);
    }
    if (log_sum)
      c += put(&OrbitCostParts::descriptor,
               -cfg.descriptor_weight * descriptor_reward(a, i, b, pix, log_sum[static_cast<std::size_t>(i)], cfg.descriptor_temperature));
    return c;
  };
  const index_t candidates = cfg.depth_range > 0 ? cfg.depth_candidates : 1;
  double sum = 0;
  for (index_t i = 0; i < n; ++i) {
    const glm::dvec3 X(a.point[static_cast<std::size_t>(3 * i)], a.point[static_cast<std::size_t>(3 * i + 1)],
                       a.point[static_cast<std::size_t>(3 * i + 2)]);
    double best = std::numeric_limits<double>::infinity(), best_along = 1;
    for (index_t k = 0; k < candidates && best > floor; ++k) {
      const double along = candidates == 1 ? 1.0
                                           : 1.0 + cfg.depth_range * (2.0 * static_cast<double>(k) /
                                                                          static_cast<double>(candidates - 1) - 1.0);
      const double c = point_cost(i, M * (along * X) + m);
      if (c < best) best = c, best_along = along;
    }
    if (parts) point_cost(i, M * (best_along * X) + m, parts, 1.0 / static_cast<double>(n));
    sum += best;
  }
  return sum / static_cast<double>(n);
}

// Cost of view v against the views in `others` (both directions).
inline double view_cost(const std::vector<View>& views, const std::vector<Placed>& placed, index_t v, const Placed& pv,
                        const OrbitSearchConfig& cfg) {
  double c = 0;
  for (index_t o = 0; o < static_cast<index_t>(views.size()); ++o) {
    if (o == v) continue;
    const std::size_t so = static_cast<std::size_t>(o), sv = static_cast<std::size_t>(v);
    c += pair_cost(views[sv], pv, views[so], placed[so], cfg) + pair_cost(views[so], placed[so], views[sv], pv, cfg);
  }
  return c;
}

// View f's silhouette, its distance to the rim-estimated orbit centre and its sampled points; false without object
// pixels.
template <class T>
bool prepare_view(View& v, const T* images, const T* foreground, const T* depth, const T* intrinsics, index_t f,
                  index_t height, index_t width, const OrbitSearchConfig& cfg, const OrbitDescriptors<T>& desc = {}) {
  const index_t px = height * width;
  v.h = height, v.w = width;
  const T* K = intrinsics + 9 * f;
  v.fx = static_cast<double>(K[0]), v.fy = static_cast<double>(K[4]);
  v.cx = static_cast<double>(K[2]), v.cy = static_cast<double>(K[5]);
  require(std::isfinite(v.fx) && std::isfinite(v.fy) && v.fx > 0 && v.fy > 0 && std::isfinite(v.cx) && std::isfinite(v.cy),
          "cameras_from_orbit_search: view ", f, " has intrinsics fx ", v.fx, ", fy ", v.fy, ", cx ", v.cx, ", cy ", v.cy);
  v.mask.assign(static_cast<std::size_t>(px), 0);
  v.depth.assign(static_cast<std::size_t>(px), 0.f);
  index_t count = 0;
  for (index_t p = 0; p < px; ++p) {
    const double fg = static_cast<double>(foreground[f * px + p]), z = static_cast<double>(depth[f * px + p]);
    v.depth[static_cast<std::size_t>(p)] = static_cast<float>(z);
    if (fg >= cfg.min_foreground && z > 0 && std::isfinite(z)) v.mask[static_cast<std::size_t>(p)] = 1, ++count;
  }
  if (images) {
    v.colour.resize(static_cast<std::size_t>(3 * px));
    for (index_t p = 0; p < px; ++p)
      for (index_t k = 0; k < 3; ++k)
        v.colour[static_cast<std::size_t>(3 * p + k)] = static_cast<float>(images[(f * 3 + k) * px + p]);
  }
  if (desc.data && desc.dim > 0) {
    const std::size_t D = static_cast<std::size_t>(desc.dim);
    v.dim = desc.dim;
    v.descriptor.assign(static_cast<std::size_t>(px) * D, 0.f);
    for (index_t p = 0; p < px; ++p)  // blank or broken descriptors stay zero: no cosine, no reward
      unit_descriptor(desc.data + static_cast<std::size_t>(f * px + p) * D, desc.dim,
                      v.descriptor.data() + static_cast<std::size_t>(p) * D);
  }
  if (count == 0) return false;
  if (v.dim > 0) v.log_objects = std::log(static_cast<double>(count));
  chamfer_outside(v);
  // The orbit centre's distance: the median depth of the silhouette's rim (a round object's rim lies at its centre's
  // depth).
  std::vector<double> rim;
  for (index_t y = 0; y < height; ++y)
    for (index_t x = 0; x < width; ++x) {
      const index_t p = y * width + x;
      if (!v.mask[static_cast<std::size_t>(p)]) continue;
      const bool edge = x == 0 || y == 0 || x + 1 == width || y + 1 == height || !v.mask[static_cast<std::size_t>(p - 1)] ||
                        !v.mask[static_cast<std::size_t>(p + 1)] || !v.mask[static_cast<std::size_t>(p - width)] ||
                        !v.mask[static_cast<std::size_t>(p + width)];
      if (edge) rim.push_back(static_cast<double>(v.depth[static_cast<std::size_t>(p)]));
    }
  std::nth_element(rim.begin(), rim.begin() + static_cast<std::ptrdiff_t>(rim.size() / 2), rim.end());
  v.distance = rim[rim.size() / 2];
  // Samples: every k-th object pixel.
  const std::vector<double> cam = camera_frame_points(depth, intrinsics, f, height, width);
  const index_t stride = std::max<index_t>(1, (count + cfg.samples - 1) / cfg.samples);
  index_t seen = 0;
  for (index_t p = 0; p < px; ++p) {
    if (!v.mask[static_cast<std::size_t>(p)]) continue;
    if (seen++ % stride) continue;
    v.point.insert(v.point.end(), cam.begin() + 3 * p, cam.begin() + 3 * (p + 1));
    if (images)
      for (index_t k = 0; k < 3; ++k) v.point_colour.push_back(v.colour[static_cast<std::size_t>(3 * p + k)]);
    if (v.dim > 0)
      v.point_descriptor.insert(v.point_descriptor.end(), v.descriptor.begin() + static_cast<std::ptrdiff_t>(p * v.dim),
                                v.descriptor.begin() + static_cast<std::ptrdiff_t>((p + 1) * v.dim));
  }
  return true;
}

// Sum of every ordered pair's cost.
inline double total_cost(const std::vector<View>& views, const std::vector<Placed>& placed, const OrbitSearchConfig& cfg,
                         OrbitCostParts* parts = nullptr) {
  double c = 0;
  for (std::size_t a = 0; a < views.size(); ++a)
    for (std::size_t b = 0; b < views.size(); ++b)
      if (a != b) c += pair_cost(views[a], placed[a], views[b], placed[b], cfg, parts);
  return c;
}

// Refuses maps and configs the search cannot use.
inline void check_search_input(const char* who, index_t frames, index_t height, index_t width,
                               const OrbitSearchConfig& cfg, index_t descriptor_dim) {
  require(frames >= 1 && height >= 1 && width >= 1, who, ": empty maps (", frames, " x ", height, " x ", width, ")");
  require(cfg.samples >= 1 && cfg.elevation_step_deg > 0 && cfg.azimuth_step_deg > 0 && cfg.silhouette_px > 0 &&
              cfg.depth_tolerance > 0 && cfg.depth_range >= 0 && cfg.depth_range < 0.5 && cfg.depth_candidates >= 2 &&
              cfg.colour_weight >= 0 && cfg.descriptor_weight >= 0 && cfg.descriptor_temperature > 0 &&
              descriptor_dim >= 0 &&
              cfg.elevation_max_deg >= cfg.elevation_min_deg &&
              cfg.elevation_max_deg < 89 && cfg.elevation_min_deg > -89,
          who, ": invalid config (samples ", cfg.samples, ", steps ", cfg.elevation_step_deg, " / ",
          cfg.azimuth_step_deg, " deg, elevations ", cfg.elevation_min_deg, " .. ", cfg.elevation_max_deg,
          ", depth range ", cfg.depth_range, " in [0, 0.5) with ", cfg.depth_candidates, " >= 2 candidates, colour and "
          "descriptor weights ", cfg.colour_weight, ", ", cfg.descriptor_weight, " >= 0, descriptor temperature ",
          cfg.descriptor_temperature, " > 0, descriptor width ", descriptor_dim, ")");
}

// Every view prepared; returns which have object pixels. With the first view usable, `act` holds the usable views
// (their indices in `active`) with their slots and descriptor log-sums; an unusable view takes no part.
template <class T>
std::vector<bool> prepare_views(std::vector<View>& act, std::vector<index_t>& active, const T* images,
                                const T* foreground, const T* depth, const T* intrinsics, index_t frames,
                                index_t height, index_t width, const OrbitSearchConfig& cfg,
                                const OrbitDescriptors<T>& descriptors) {
  std::vector<View> views(static_cast<std::size_t>(frames));
  std::vector<bool> usable(static_cast<std::size_t>(frames), false);
  for (index_t f = 0; f < frames; ++f)
    usable[static_cast<std::size_t>(f)] = prepare_view(views[static_cast<std::size_t>(f)], images, foreground, depth,
                                                       intrinsics, f, height, width, cfg, descriptors);
  act.clear(), active.clear();
  if (frames == 1 || !usable[0]) return usable;
  for (index_t f = 0; f < frames; ++f)
    if (usable[static_cast<std::size_t>(f)]) active.push_back(f), act.push_back(std::move(views[static_cast<std::size_t>(f)]));
  const index_t A = static_cast<index_t>(act.size());
  for (index_t a = 0; a < A; ++a) act[static_cast<std::size_t>(a)].slot = a;
  if (descriptors.data && descriptors.dim > 0 && cfg.descriptor_weight > 0)
    for (View& a : act) {
      a.log_sum.resize(static_cast<std::size_t>(A));
      for (const View& b : act)
        if (&a != &b && b.log_objects > 0) descriptor_log_sums(a, b, cfg.descriptor_temperature);
    }
  return usable;
}

// The given world-to-cameras [S, 3, 4] of the active views, refused if not finite.
template <class T>
std::vector<Placed> placed_cameras(const T* extrinsics, const T* intrinsics, const std::vector<index_t>& active,
                                   index_t height, index_t width) {
  std::vector<Placed> placed(active.size());
  for (std::size_t a = 0; a < active.size(); ++a) {
    const T* E = extrinsics + 12 * active[a];
    for (int i = 0; i < 12; ++i)
      require(std::isfinite(static_cast<double>(E[i])), "orbit_search_cost: view ", active[a], " extrinsics[", i / 4,
              ",", i % 4, "] = ", static_cast<double>(E[i]), " is not finite");
    const Camera cam = camera_from_arrays(intrinsics + 9 * active[a], E, static_cast<int>(width), static_cast<int>(height));
    placed[a].R = cam.R, placed[a].t = cam.t;
  }
  return placed;
}

}  // namespace orbit_detail

// Each view's world-to-camera [S, 3, 4] (the first view's camera is the world, [I | 0]) from its silhouette, depth and
// colour. images [S, 3, H, W] in [0, 1] (may be null: no colour term); foreground, depth [S, H, W]; intrinsics
// [S, 3, 3] with pixel (u, v) at integer coordinates (geometry/unproject.hpp). Views without object pixels keep
// [I | 0] and a false entry in `solved` (may be null, [S]). cost_out (may be null): the final total cost.
// descriptors (optional): a descriptor term beside the colour's.
// Over 150 lines: its stages (grid, beam, sweeps, pattern search) share the poses, placements and best-so-far state.
template <class T>
void cameras_from_orbit_search(T* extrinsics, const T* images, const T* foreground, const T* depth, const T* intrinsics,
                               index_t frames, index_t height, index_t width, const OrbitSearchConfig& cfg = {},
                               bool* solved = nullptr, double* cost_out = nullptr,
                               const OrbitDescriptors<T>& descriptors = {}) {
  using namespace orbit_detail;
  check_search_input("cameras_from_orbit_search", frames, height, width, cfg, descriptors.dim);
  const double deg = std::numbers::pi / 180;
  std::vector<View> act;
  std::vector<index_t> active;
  const std::vector<bool> usable = prepare_views(act, active, images, foreground, depth, intrinsics, frames, height,
                                                 width, cfg, descriptors);
  if (solved)
    for (index_t f = 0; f < frames; ++f) solved[f] = f == 0 || (usable[0] && usable[static_cast<std::size_t>(f)]);
  for (index_t f = 0; f < frames; ++f)
    for (int i = 0; i < 12; ++i) extrinsics[12 * f + i] = static_cast<T>(identity_w2c[i]);
  if (frames == 1 || !usable[0]) {
    if (cost_out) *cost_out = 0;
    return;
  }
  const index_t A = static_cast<index_t>(act.size());
  std::vector<double> elevations, azimuths;
  for (double e = cfg.elevation_min_deg; e <= cfg.elevation_max_deg + 1e-9; e += cfg.elevation_step_deg) elevations.push_back(e * deg);
  for (double a = 0; a < 360 - 1e-9; a += cfg.azimuth_step_deg) azimuths.push_back(a * deg);
  std::vector<OrbitPose> pose(static_cast<std::size_t>(A));
  std::vector<Placed> placed(static_cast<std::size_t>(A));
  auto total = [&] { return total_cost(act, placed, cfg); };
  // The grid's cells are far apart for a cost that is sharp at the solution: the grid stages see the silhouettes and
  // depths with wider tolerances.
  OrbitSearchConfig coarse = cfg;
  coarse.silhouette_px *= cfg.coarse_tolerance, coarse.depth_tolerance *= cfg.coarse_tolerance;
  // The grid's cells, elevation-major.
  const index_t cells = static_cast<index_t>(elevations.size() * azimuths.size());
  auto cell_pose = [&](OrbitPose p, index_t cell) {
    p.elevation = elevations[static_cast<std::size_t>(cell) / azimuths.size()];
    p.azimuth = azimuths[static_cast<std::size_t>(cell) % azimuths.size()], p.roll = 0;
    return p;
  };
  std::vector<double> cell_cost(static_cast<std::size_t>(cells));
  // Grid search of view v's elevation and azimuth against all the other placed views: the cells' costs in parallel,
  // the first cheapest in grid order chosen, so the same at any thread count.
  auto grid_view = [&](index_t v) {
    parallel_for(cells, [&](index_t c0, index_t c1, int) {
      for (index_t cell = c0; cell < c1; ++cell)
        cell_cost[static_cast<std::size_t>(cell)] =
            view_cost(act, placed, v, place(cell_pose(pose[static_cast<std::size_t>(v)], cell)), coarse);
    });
    index_t best = -1;
    double best_cost = std::numeric_limits<double>::infinity();
    for (index_t cell = 0; cell < cells; ++cell)
      if (cell_cost[static_cast<std::size_t>(cell)] < best_cost) best_cost = cell_cost[static_cast<std::size_t>(cell)], best = cell;
    if (best >= 0) pose[static_cast<std::size_t>(v)] = cell_pose(pose[static_cast<std::size_t>(v)], best);
    placed[static_cast<std::size_t>(v)] = place(pose[static_cast<std::size_t>(v)]);
  };
  // 1. Beam search: the views placed one by one on the grid, each placement scored against the views before it; the
  // first view's elevation and the distances' scale start the beams.
  struct Beam {
    std::vector<OrbitPose> pose;
    std::vector<Placed> placed;
    double cost = 0;
  };
  std::vector<Beam> beams;
  for (double scale : cfg.distance_scales)
    for (double e0 : elevations) {
      Beam b;
      b.pose.resize(static_cast<std::size_t>(A));
      for (index_t v = 0; v < A; ++v) b.pose[static_cast<std::size_t>(v)].distance = scale * act[static_cast<std::size_t>(v)].distance;
      b.pose[0].elevation = e0;
      b.placed.resize(static_cast<std::size_t>(A));
      b.placed[0] = place(b.pose[0]);
      beams.push_back(std::move(b));
    }
  struct Candidate {
    double cost;
    std::size_t beam;
    OrbitPose pose;
    Placed placed;
  };
  // Candidates in the order beam, distance scale, cell, scored in parallel: the same at any thread count.
  const index_t per_beam = static_cast<index_t>(cfg.distance_scales.size()) * cells;
  for (index_t v = 1; v < A; ++v) {
    std::vector<Candidate> cand(beams.size() * static_cast<std::size_t>(per_beam));
    parallel_for(static_cast<index_t>(cand.size()), [&](index_t k0, index_t k1, int) {
      for (index_t k = k0; k < k1; ++k) {
        const std::size_t bi = static_cast<std::size_t>(k / per_beam);
        const Beam& b = beams[bi];
        OrbitPose p = cell_pose(b.pose[static_cast<std::size_t>(v)], k % cells);
        p.distance = cfg.distance_scales[static_cast<std::size_t>(k % per_beam / cells)] *
                     act[static_cast<std::size_t>(v)].distance;
        const Placed q = place(p);
        double c = b.cost;
        for (index_t o = 0; o < v; ++o) {
          const std::size_t so = static_cast<std::size_t>(o);
          c += pair_cost(act[static_cast<std::size_t>(v)], q, act[so], b.placed[so], coarse) +
               pair_cost(act[so], b.placed[so], act[static_cast<std::size_t>(v)], q, coarse);
        }
        cand[static_cast<std::size_t>(k)] = {c, bi, p, q};
      }
    });
    const std::size_t keep = std::min(cand.size(), static_cast<std::size_t>(cfg.beam_width));
    std::partial_sort(cand.begin(), cand.begin() + static_cast<std::ptrdiff_t>(keep), cand.end(),
                      [](const Candidate& x, const Candidate& y) { return x.cost < y.cost; });
    std::vector<Beam> next;
    for (std::size_t k = 0; k < keep; ++k) {
      Beam b = beams[cand[k].beam];
      b.pose[static_cast<std::size_t>(v)] = cand[k].pose;
      b.placed[static_cast<std::size_t>(v)] = cand[k].placed;
      b.cost = cand[k].cost;
      next.push_back(std::move(b));
    }
    beams = std::move(next);
  }
  std::sort(beams.begin(), beams.end(), [](const Beam& x, const Beam& y) { return x.cost < y.cost; });
  std::vector<OrbitPose> best_pose;
  std::vector<Placed> best_placed;
  double best_total = std::numeric_limits<double>::infinity();
  for (std::size_t fin = 0; fin < std::min(beams.size(), static_cast<std::size_t>(cfg.finalists)); ++fin) {
  pose = beams[fin].pose, placed = beams[fin].placed;
  // 2. Coordinate sweeps on the grid: each view against all the others (the first keeps azimuth 0: the gauge).
  for (int s = 0; s < cfg.sweeps; ++s)
    for (index_t v = 0; v < A; ++v) {
      if (v == 0) {
        OrbitPose keep = pose[0];
        double best_c = view_cost(act, placed, 0, placed[0], coarse);
        for (double e : elevations) {
          OrbitPose p = pose[0];
          p.elevation = e;
          const double c = view_cost(act, placed, 0, place(p), coarse);
          if (c < best_c) best_c = c, keep = p;
        }
        pose[0] = keep, placed[0] = place(keep);
      } else {
        grid_view(v);
      }
    }
  // 3. Local pattern search on all four parameters, steps halving.
  double step = cfg.refine_step_deg * deg, dstep = cfg.refine_step_distance;
  for (int r = 0; r < cfg.refine_rounds; ++r, step /= 2, dstep /= 2) {
    for (int pass = 0; pass < 2; ++pass)
      for (index_t v = 0; v < A; ++v) {
        OrbitPose& p = pose[static_cast<std::size_t>(v)];
        double cur = view_cost(act, placed, v, placed[static_cast<std::size_t>(v)], cfg);
        for (int k = 0; k < 4; ++k) {
          if (v == 0 && k == 1) continue;  // the first view's azimuth is the gauge
          for (const double sign : {1.0, -1.0}) {
            OrbitPose q = p;
            double* field = k == 0 ? &q.elevation : k == 1 ? &q.azimuth : k == 2 ? &q.roll : &q.distance;
            *field = k == 3 ? q.distance * (1 + sign * dstep) : *field + sign * step;
            if (k == 0 && std::abs(q.elevation) > 88 * deg) continue;
            const Placed pq = place(q);
            const double c = view_cost(act, placed, v, pq, cfg);
            if (c < cur) {
              cur = c, p = q, placed[static_cast<std::size_t>(v)] = pq;
              break;
            }
          }
        }
      }
  }
  const double c = total();
  if (c < best_total) best_total = c, best_pose = pose, best_placed = placed;
  }
  pose = best_pose, placed = best_placed;
  if (cost_out) *cost_out = best_total;
  // Relative to the first view: E_v E_0^-1.
  const Placed& p0 = placed[0];
  const glm::dmat3 R0t = glm::transpose(p0.R);
  for (index_t i = 1; i < A; ++i) {  // the first view's entries stay exactly [I | 0]
    const Placed& p = placed[static_cast<std::size_t>(i)];
    Camera cam;
    cam.R = p.R * R0t;
    cam.t = p.t - cam.R * p0.t;
    camera_arrays<T>(cam, nullptr, extrinsics + 12 * active[static_cast<std::size_t>(i)]);
  }
}

// The cameras of photos taken in order around the object at equal azimuth steps (a turntable, or a walk around it):
// view f on the orbit at azimuth direction * f * 360 deg / frames, all at one elevation and one distance, image up
// towards the object's up. The elevation, the turning direction (+1 or -1) and the distance are searched on the views'
// silhouettes, depth and colour (the objective of cameras_from_orbit_search): a grid of cfg's elevations (at half its
// step) and distance_scales for either direction, then a pattern search, steps halving. Writes world-to-camera
// [S, 3, 4] relative to the first view (its entries exactly [I | 0]); the inputs are cameras_from_orbit_search's.
struct TurntableResult {
  double elevation_deg = 0, distance = 0, cost = 0;
  int direction = 1;
};

template <class T>
TurntableResult cameras_from_turntable(T* extrinsics, const T* images, const T* foreground, const T* depth,
                                       const T* intrinsics, index_t frames, index_t height, index_t width,
                                       const OrbitSearchConfig& cfg = {}) {
  using namespace orbit_detail;
  check_search_input("cameras_from_turntable", frames, height, width, cfg, 0);
  const double deg = std::numbers::pi / 180;
  std::vector<View> act;
  std::vector<index_t> active;
  prepare_views(act, active, images, foreground, depth, intrinsics, frames, height, width, cfg, OrbitDescriptors<T>{});
  for (index_t f = 0; f < frames; ++f)
    for (int i = 0; i < 12; ++i) extrinsics[12 * f + i] = static_cast<T>(identity_w2c[i]);
  TurntableResult best;
  if (act.size() < 2) return best;
  std::vector<double> rim;
  for (const View& v : act) rim.push_back(v.distance);
  std::nth_element(rim.begin(), rim.begin() + static_cast<std::ptrdiff_t>(rim.size() / 2), rim.end());
  const double rim_distance = rim[rim.size() / 2];
  std::vector<Placed> placed(act.size());
  auto cost = [&](double elevation, int direction, double distance, const OrbitSearchConfig& c) {
    for (std::size_t a = 0; a < act.size(); ++a)
      placed[a] = place({elevation, direction * 2 * std::numbers::pi * static_cast<double>(active[a]) /
                                        static_cast<double>(frames), 0, distance});
    return total_cost(act, placed, c);
  };
  OrbitSearchConfig coarse = cfg;
  coarse.silhouette_px *= cfg.coarse_tolerance, coarse.depth_tolerance *= cfg.coarse_tolerance;
  best.cost = std::numeric_limits<double>::infinity();
  double e_best = 0, d_best = rim_distance;
  for (const int dir : {1, -1})
    for (double e = cfg.elevation_min_deg; e <= cfg.elevation_max_deg + 1e-9; e += 0.5 * cfg.elevation_step_deg)
      for (const double k : cfg.distance_scales) {
        const double c = cost(e * deg, dir, k * rim_distance, coarse);
        if (c < best.cost) best.cost = c, best.direction = dir, e_best = e * deg, d_best = k * rim_distance;
      }
  best.cost = cost(e_best, best.direction, d_best, cfg);
  double step = 0.25 * cfg.elevation_step_deg * deg, dstep = cfg.refine_step_distance;
  for (int r = 0; r < 2 * cfg.refine_rounds; ++r, step /= 2, dstep /= 2) {
    bool moved = true;
    while (moved) {
      moved = false;
      for (const double se : {1.0, -1.0, 0.0, 0.0})
        for (const double sd : {0.0, 0.0, 1.0, -1.0}) {
          if ((se == 0) == (sd == 0)) continue;
          const double e = e_best + se * step, d = d_best * (1 + sd * dstep);
          if (std::abs(e) > 88 * deg) continue;
          const double c = cost(e, best.direction, d, cfg);
          if (c < best.cost) best.cost = c, e_best = e, d_best = d, moved = true;
        }
    }
  }
  best.elevation_deg = e_best / deg;
  best.distance = d_best;
  // Every view placed by its index (views without object pixels too), relative to the first.
  const Placed p0 = place({e_best, 0, 0, d_best});
  const glm::dmat3 R0t = glm::transpose(p0.R);
  for (index_t f = 1; f < frames; ++f) {
    const Placed p = place({e_best, best.direction * 2 * std::numbers::pi * static_cast<double>(f) /
                                        static_cast<double>(frames), 0, d_best});
    Camera cam;
    cam.R = p.R * R0t;
    cam.t = p.t - cam.R * p0.t;
    camera_arrays<T>(cam, nullptr, extrinsics + 12 * f);
  }
  return best;
}

// The search's objective for given cameras: the sum of the pair costs over ordered pairs of the usable views, what
// cameras_from_orbit_search minimises and reports through cost_out (0 for one view or an unusable first view).
// extrinsics [S, 3, 4] world-to-camera, any world frame, translations in the depth's units; the other inputs as the
// search's. To compare a found placement with another, e.g. the truth's. parts (may be null) receives the cost split by
// kind (added to what it holds).
template <class T>
double orbit_search_cost(const T* extrinsics, const T* images, const T* foreground, const T* depth, const T* intrinsics,
                         index_t frames, index_t height, index_t width, const OrbitSearchConfig& cfg = {},
                         const OrbitDescriptors<T>& descriptors = {}, OrbitCostParts* parts = nullptr) {
  using namespace orbit_detail;
  check_search_input("orbit_search_cost", frames, height, width, cfg, descriptors.dim);
  std::vector<View> act;
  std::vector<index_t> active;
  prepare_views(act, active, images, foreground, depth, intrinsics, frames, height, width, cfg, descriptors);
  if (act.size() < 2) return 0;
  return total_cost(act, placed_cameras(extrinsics, intrinsics, active, height, width), cfg, parts);
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
