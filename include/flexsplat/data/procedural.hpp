#pragma once
// Procedural objects in the spirit of LRM-Zero's Zeroverse: a union of 1-9 randomly scaled, rotated and placed
// primitives, each with its own random solid texture, normalised to the unit bounding sphere. Deterministic from a
// 64-bit seed (nothing depends on threads or call order).
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <vector>

#include <glm/glm.hpp>
#include <glm/gtc/quaternion.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/data/mesh.hpp"
#include "flexsplat/data/random.hpp"

namespace flexsplat {
inline namespace v0 {
namespace data {

enum class PrimitiveKind : std::uint8_t { box, sphere, cylinder, cone, torus, capsule, plate, swept_tube, blob };
// make_object draws its kinds uniformly from the first 8 (box .. swept_tube); blobs come from
// ObjectConfig::blob_fraction.
inline constexpr int kSolidKinds = 8;

inline const char* primitive_name(PrimitiveKind kind) {
  constexpr const char* names[] = {"box",     "sphere", "cylinder", "cone", "torus",
                                   "capsule", "plate",  "swept_tube", "blob"};
  return names[static_cast<int>(kind)];
}

// One placed primitive: world = linear * canonical + translation. Canonical shapes fit in [-1, 1]^3:
// box and plate are [-1, 1]^2 x [-1, 1] / [-t, t]; sphere radius 1; cylinder and cone radius 1 over z in [-1, 1]
// (cone apex at z = 1); torus and swept tube have tube radius `shape` and reach radius 1; capsule has half-length
// `shape` between its hemispheres, scaled to fit; blob is the unit sphere with its radius bent by smooth waves of
// total amplitude `shape` (drawn from `waves`), scaled to fit.
struct Primitive {
  PrimitiveKind kind = PrimitiveKind::sphere;
  glm::mat3 linear{1.0f};
  glm::vec3 translation{0.0f};
  float shape = 0.0f;  // torus/tube radius, capsule half-length, plate half-thickness
  float arc = 0.0f;    // swept tube: swept angle in radians
  std::uint64_t waves = 0;  // blob: seed of its radius waves
  Material material;
};

struct ObjectConfig {
  int min_primitives = 1, max_primitives = 9;
  int segments = 32;                      // around a circle; meridians get segments / 2
  float min_extent = 0.2f, max_extent = 0.7f;  // per-axis half-size before normalisation
  float placement = 0.55f;                // primitive centres uniform in [-placement, placement]^3
  // Organic objects, nearer the real meshes than loose unions: the share of primitives that are blobs, and parts
  // after the first centred near the first one's surface (a body with limbs) instead of anywhere in the cube.
  float blob_fraction = 0.0f;
  bool attached = false;
  bool soft_textures = false;  // no checkers or stripes and no forced contrast, like the real meshes' mottled materials
};

struct ProceduralObject {
  std::uint64_t seed = 0;
  std::vector<Primitive> primitives;  // after normalisation (they describe the mesh exactly)
  Mesh mesh;
  glm::vec3 light_direction{0, 0, 1};  // world frame, unit, towards the light; one per object so views agree
  float ambient = 0.4f;
};

namespace detail {

// Appends a (rows + 1) x (cols + 1) vertex grid; f(u, v, position, normal) fills canonical values for u, v in [0, 1].
template <class F>
void add_grid(Mesh& mesh, const Primitive& prim, std::uint32_t material, int rows, int cols, F&& f) {
  const glm::mat3 normal_matrix = glm::transpose(glm::inverse(prim.linear));
  const auto base = static_cast<std::uint32_t>(mesh.positions.size());
  for (int r = 0; r <= rows; ++r)
    for (int c = 0; c <= cols; ++c) {
      glm::vec3 p, n;
      f(static_cast<float>(c) / static_cast<float>(cols), static_cast<float>(r) / static_cast<float>(rows), p, n);
      mesh.positions.push_back(prim.linear * p + prim.translation);
      mesh.normals.push_back(glm::normalize(normal_matrix * n));
      mesh.texcoords.push_back(p);
    }
  const auto stride = static_cast<std::uint32_t>(cols + 1);
  for (int r = 0; r < rows; ++r)
    for (int c = 0; c < cols; ++c) {
      const std::uint32_t a = base + static_cast<std::uint32_t>(r) * stride + static_cast<std::uint32_t>(c);
      const std::uint32_t b = a + 1, d = a + stride, e = d + 1;
      mesh.triangles.push_back({a, b, d});
      mesh.triangles.push_back({b, e, d});
      mesh.triangle_material.push_back(material);
      mesh.triangle_material.push_back(material);
    }
}

// Flat disc of radius `radius` at height z, facing `facing` (+1 or -1 along z), in the canonical frame.
inline void add_disc(Mesh& mesh, const Primitive& prim, std::uint32_t material, int segments, float z, float facing,
                     float radius = 1.0f) {
  add_grid(mesh, prim, material, 1, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
    const float phi = 2.0f * std::numbers::pi_v<float> * u;
    p = {radius * v * std::cos(phi), radius * v * std::sin(phi), z};
    n = {0.0f, 0.0f, facing};
  });
}

inline void add_box(Mesh& mesh, const Primitive& prim, std::uint32_t material, glm::vec3 half) {
  for (int axis = 0; axis < 3; ++axis)
    for (float sign : {-1.0f, 1.0f})
      add_grid(mesh, prim, material, 1, 1, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        p = glm::vec3(0.0f);
        n = glm::vec3(0.0f);
        p[axis] = sign * half[axis];
        p[(axis + 1) % 3] = (2.0f * u - 1.0f) * half[(axis + 1) % 3];
        p[(axis + 2) % 3] = (2.0f * v - 1.0f) * half[(axis + 2) % 3];
        n[axis] = sign;
      });
}

inline glm::vec3 hsv_to_rgb(float h, float s, float v) {
  h = (h - std::floor(h)) * 6.0f;
  const int sector = std::min(static_cast<int>(h), 5);
  const float f = h - static_cast<float>(sector);
  const float p = v * (1 - s), q = v * (1 - s * f), t = v * (1 - s * (1 - f));
  switch (sector) {
    case 0: return {v, t, p};
    case 1: return {q, v, p};
    case 2: return {p, v, t};
    case 3: return {p, q, v};
    case 4: return {t, p, v};
    default: return {v, p, q};
  }
}

inline glm::vec3 random_unit(Rng& rng) {
  for (;;) {
    const glm::dvec3 g(rng.normal(), rng.normal(), rng.normal());
    const double len = glm::length(g);
    if (len > 1e-6) return glm::vec3(g / len);
  }
}

// Uniform random rotation (Shoemake's subgroup method).
inline glm::mat3 random_rotation(Rng& rng) {
  const double u1 = rng.uniform(), u2 = 2 * std::numbers::pi * rng.uniform(), u3 = 2 * std::numbers::pi * rng.uniform();
  const double a = std::sqrt(1 - u1), b = std::sqrt(u1);
  const glm::dquat q(a * std::cos(u2), b * std::sin(u3), b * std::cos(u3), a * std::sin(u2));  // w, x, y, z
  return glm::mat3(glm::mat3_cast(glm::normalize(q)));
}

// A colour near the object's palette hue: analogous most of the time, complementary sometimes.
inline glm::vec3 palette_color(Rng& rng, float base_hue) {
  const float hue = base_hue + static_cast<float>(rng.uniform() < 0.3 ? 0.5 : 0.0) +
                    static_cast<float>(rng.uniform(-0.12, 0.12));
  return hsv_to_rgb(hue, static_cast<float>(rng.uniform(0.2, 0.9)), static_cast<float>(rng.uniform(0.3, 0.95)));
}

// soft: solid, noise or gradient, with the palette's own contrast (shading, not pattern edges, shows the shape); the
// same draws as the default, so only the mapping changes.
inline Material random_material(Rng& rng, float base_hue, bool soft = false) {
  Material m;
  const int kind = rng.integer(0, 4);
  constexpr TextureKind soft_kinds[] = {TextureKind::solid, TextureKind::noise, TextureKind::gradient,
                                        TextureKind::noise, TextureKind::solid};
  m.kind = static_cast<TextureKind>(kind);
  m.color0 = palette_color(rng, base_hue);
  m.color1 = palette_color(rng, base_hue);
  if (!soft && glm::length(m.color0 - m.color1) < 0.25f) m.color1 = glm::vec3(1.0f) - 0.8f * m.color0;  // keep patterns visible
  m.direction = random_unit(rng);
  m.offset = glm::vec3(rng.uniform(), rng.uniform(), rng.uniform());
  m.noise_seed = static_cast<std::uint32_t>(rng.next());
  switch (m.kind) {
    case TextureKind::checker: m.frequency = static_cast<float>(rng.uniform(1.5, 5.0)); break;
    case TextureKind::stripes: m.frequency = static_cast<float>(rng.uniform(1.5, 6.0)); break;
    case TextureKind::noise: m.frequency = static_cast<float>(rng.uniform(1.5, 5.0)); break;
    default: m.frequency = 1.0f;
  }
  if (soft) {
    m.kind = soft_kinds[kind];
    if (m.kind != TextureKind::noise) m.frequency = 1.0f;
  }
  return m;
}

// The unit sphere's point at grid coordinates (u, v) in [0, 1]^2: longitude 2 pi u, colatitude pi v.
inline glm::vec3 unit_sphere_point(float u, float v) {
  const float phi = 2 * std::numbers::pi_v<float> * u, theta = std::numbers::pi_v<float> * v;
  return {std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi), std::cos(theta)};
}

// A blob's radius over the unit sphere: 1 + sum_k a_k sin(f_k w_k . n + phase_k), the a_k summing to `total`.
struct BlobWaves {
  static constexpr int count = 6;
  std::array<glm::vec3, count> direction{};  // f_k w_k
  std::array<float, count> amplitude{}, phase{};

  BlobWaves(std::uint64_t seed, float total) {
    Rng rng(seed);
    float sum = 0.0f;
    for (int k = 0; k < count; ++k) {
      direction[k] = random_unit(rng) * static_cast<float>(rng.uniform(1.0, 3.0));
      phase[k] = static_cast<float>(rng.uniform(0.0, 2.0 * std::numbers::pi));
      amplitude[k] = static_cast<float>(rng.uniform(0.2, 1.0));
      sum += amplitude[k];
    }
    for (float& a : amplitude) a *= total / sum;
  }
  // The radius at unit direction n and its surface normal (n minus the radius' tangential gradient over the radius).
  float radius(glm::vec3 n, glm::vec3& normal) const {
    float r = 1.0f;
    glm::vec3 grad(0.0f);
    for (int k = 0; k < count; ++k) {
      const float x = glm::dot(direction[k], n) + phase[k];
      r += amplitude[k] * std::sin(x);
      grad += amplitude[k] * std::cos(x) * direction[k];
    }
    normal = glm::normalize(n - (grad - glm::dot(grad, n) * n) / r);
    return r;
  }
};

}  // namespace detail

// Appends one primitive's triangles (canonical shape mapped by prim.linear / prim.translation) with material index
// `material` (which must exist in mesh.materials by the time the mesh is rendered).
inline void append_primitive(Mesh& mesh, const Primitive& prim, std::uint32_t material, int segments) {
  require(segments >= 3 && segments <= 4096, "append_primitive: segments ", segments, " outside [3, 4096]");
  const float pi = std::numbers::pi_v<float>;
  const int rings = std::max(2, segments / 2);
  switch (prim.kind) {
    case PrimitiveKind::box: detail::add_box(mesh, prim, material, glm::vec3(1.0f)); break;
    case PrimitiveKind::plate: detail::add_box(mesh, prim, material, glm::vec3(1.0f, 1.0f, prim.shape)); break;
    case PrimitiveKind::sphere:
      detail::add_grid(mesh, prim, material, rings, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        p = n = detail::unit_sphere_point(u, v);
      });
      break;
    case PrimitiveKind::blob: {
      const detail::BlobWaves waves(prim.waves, prim.shape);
      const float fit = 1.0f / (1.0f + prim.shape);
      detail::add_grid(mesh, prim, material, rings, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        const glm::vec3 dir = detail::unit_sphere_point(u, v);
        p = fit * waves.radius(dir, n) * dir;
      });
      break;
    }
    case PrimitiveKind::cylinder:
      detail::add_grid(mesh, prim, material, 1, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        const float phi = 2 * pi * u;
        p = {std::cos(phi), std::sin(phi), 2 * v - 1};
        n = {std::cos(phi), std::sin(phi), 0};
      });
      detail::add_disc(mesh, prim, material, segments, 1.0f, 1.0f);
      detail::add_disc(mesh, prim, material, segments, -1.0f, -1.0f);
      break;
    case PrimitiveKind::cone:
      detail::add_grid(mesh, prim, material, 1, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        const float phi = 2 * pi * u;
        p = {(1 - v) * std::cos(phi), (1 - v) * std::sin(phi), 2 * v - 1};
        n = glm::normalize(glm::vec3(2 * std::cos(phi), 2 * std::sin(phi), 1));
      });
      detail::add_disc(mesh, prim, material, segments, -1.0f, -1.0f);
      break;
    case PrimitiveKind::torus:
    case PrimitiveKind::swept_tube: {
      const float r = prim.shape, R = 1.0f - prim.shape;
      const float arc = prim.kind == PrimitiveKind::torus ? 2 * pi : prim.arc;
      const int along = std::max(3, static_cast<int>(std::ceil(segments * arc / (2 * pi))));
      detail::add_grid(mesh, prim, material, rings, along, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        const float phi = arc * u, theta = 2 * pi * v;
        n = {std::cos(theta) * std::cos(phi), std::cos(theta) * std::sin(phi), std::sin(theta)};
        p = {(R + r * std::cos(theta)) * std::cos(phi), (R + r * std::cos(theta)) * std::sin(phi), r * std::sin(theta)};
      });
      if (prim.kind == PrimitiveKind::swept_tube)
        for (int end = 0; end < 2; ++end) {
          const float phi = end ? arc : 0.0f;
          const glm::vec3 radial(std::cos(phi), std::sin(phi), 0), tangent(-std::sin(phi), std::cos(phi), 0);
          detail::add_grid(mesh, prim, material, 1, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
            const float theta = 2 * pi * u;
            p = (R + v * r * std::cos(theta)) * radial + glm::vec3(0, 0, v * r * std::sin(theta));
            n = end ? tangent : -tangent;
          });
        }
      break;
    }
    case PrimitiveKind::capsule: {
      const float h = prim.shape, s = 1.0f / (1.0f + h);
      for (int half = 0; half < 2; ++half) {
        const float sign = half ? -1.0f : 1.0f;
        detail::add_grid(mesh, prim, material, rings / 2 + 1, segments,
                         [&](float u, float v, glm::vec3& p, glm::vec3& n) {
                           const float phi = 2 * pi * u, theta = 0.5f * pi * v;
                           n = {std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi),
                                sign * std::cos(theta)};
                           p = s * (n + glm::vec3(0, 0, sign * h));
                         });
      }
      detail::add_grid(mesh, prim, material, 1, segments, [&](float u, float v, glm::vec3& p, glm::vec3& n) {
        const float phi = 2 * pi * u;
        n = {std::cos(phi), std::sin(phi), 0};
        p = s * (n + glm::vec3(0, 0, (2 * v - 1) * h));
      });
      break;
    }
  }
}

// Refuses an ObjectConfig make_object cannot follow, naming the field and value.
inline void check_object_config(const ObjectConfig& config) {
  require(config.min_primitives >= 1 && config.max_primitives >= config.min_primitives && config.max_primitives <= 64,
          "ObjectConfig: primitive count range [", config.min_primitives, ", ", config.max_primitives,
          "] must satisfy 1 <= min <= max <= 64");
  require(config.min_extent > 0 && config.max_extent >= config.min_extent && config.placement >= 0,
          "ObjectConfig: extents [", config.min_extent, ", ", config.max_extent, "] and placement ", config.placement,
          " must be positive and ordered");
  require(config.blob_fraction >= 0 && config.blob_fraction <= 1, "ObjectConfig: blob_fraction ", config.blob_fraction,
          " outside [0, 1]");
}

// The object for `seed`: primitives, their mesh (normalised so the bounding sphere about the bounding-box centre has
// radius 1) and the object's light.
inline ProceduralObject make_object(std::uint64_t seed, const ObjectConfig& config = {}) {
  check_object_config(config);
  ProceduralObject object;
  object.seed = seed;
  Rng rng(stream_seed(seed, Stream::shape));
  const int count = rng.integer(config.min_primitives, config.max_primitives);
  const auto base_hue = static_cast<float>(rng.uniform());
  for (int i = 0; i < count; ++i) {
    Primitive prim;
    // Draws only what the config asks for, so that the default objects stay those of earlier releases.
    const bool blob = config.blob_fraction > 0 && rng.uniform() < config.blob_fraction;
    prim.kind = blob ? PrimitiveKind::blob : static_cast<PrimitiveKind>(rng.integer(0, kSolidKinds - 1));
    glm::vec3 extent(static_cast<float>(rng.uniform(config.min_extent, config.max_extent)));
    for (int a = 0; a < 3; ++a) extent[a] *= static_cast<float>(rng.uniform(0.6, 1.4));
    if (prim.kind == PrimitiveKind::plate) extent.z = extent.x;  // thickness comes from `shape`
    if (i > 0 && config.attached) extent *= 0.6f;                  // limbs smaller than the body
    prim.linear = detail::random_rotation(rng) * glm::mat3(glm::vec3(extent.x, 0, 0), glm::vec3(0, extent.y, 0),
                                                          glm::vec3(0, 0, extent.z));
    const float p = config.placement;
    if (i > 0 && config.attached)
      prim.translation = object.primitives[0].linear * (detail::random_unit(rng) * static_cast<float>(rng.uniform(0.6, 1.0)));
    else if (i > 0)
      prim.translation = {rng.uniform(-p, p), rng.uniform(-p, p), rng.uniform(-p, p)};
    switch (prim.kind) {
      case PrimitiveKind::blob:
        prim.shape = static_cast<float>(rng.uniform(0.1, 0.35));
        prim.waves = rng.next();
        break;
      case PrimitiveKind::torus: prim.shape = static_cast<float>(rng.uniform(0.12, 0.35)); break;
      case PrimitiveKind::swept_tube:
        prim.shape = static_cast<float>(rng.uniform(0.1, 0.3));
        prim.arc = static_cast<float>(rng.uniform(0.5, 1.6) * std::numbers::pi);
        break;
      case PrimitiveKind::capsule: prim.shape = static_cast<float>(rng.uniform(0.3, 1.5)); break;
      case PrimitiveKind::plate: prim.shape = static_cast<float>(rng.uniform(0.03, 0.08)); break;
      default: break;
    }
    prim.material = detail::random_material(rng, base_hue, config.soft_textures);
    object.primitives.push_back(prim);
  }
  for (std::size_t i = 0; i < object.primitives.size(); ++i) {
    object.mesh.materials.push_back(object.primitives[i].material);
    append_primitive(object.mesh, object.primitives[i], static_cast<std::uint32_t>(i), config.segments);
  }
  // Normalise: bounding-box centre to the origin, farthest vertex to radius 1.
  glm::vec3 lo(INFINITY), hi(-INFINITY);
  for (const glm::vec3& v : object.mesh.positions) {
    lo = glm::min(lo, v);
    hi = glm::max(hi, v);
  }
  const glm::vec3 centre = 0.5f * (lo + hi);
  float radius = 0.0f;
  for (const glm::vec3& v : object.mesh.positions) radius = std::max(radius, glm::length(v - centre));
  require(radius > 0 && std::isfinite(radius), "make_object(seed ", seed, "): degenerate object of radius ", radius);
  const float s = 1.0f / radius;
  for (glm::vec3& v : object.mesh.positions) v = (v - centre) * s;
  for (Primitive& prim : object.primitives) {
    prim.linear *= s;
    prim.translation = (prim.translation - centre) * s;
  }
  Rng light(stream_seed(seed, Stream::light));
  const double elevation = light.uniform(15, 75) * std::numbers::pi / 180, azimuth = light.uniform(0, 2 * std::numbers::pi);
  object.light_direction = glm::vec3(std::cos(elevation) * std::cos(azimuth), std::cos(elevation) * std::sin(azimuth),
                                     std::sin(elevation));
  object.ambient = static_cast<float>(light.uniform(0.35, 0.6));
  return object;
}

}  // namespace data
}  // namespace v0
}  // namespace flexsplat
