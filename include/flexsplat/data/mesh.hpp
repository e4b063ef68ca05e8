#pragma once
// Triangle meshes with procedural solid textures: what the generator builds and the CPU renderer draws.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/data/random.hpp"

namespace flexsplat {
inline namespace v0 {
namespace data {

enum class TextureKind : std::uint8_t { solid, checker, stripes, noise, gradient };

inline const char* texture_name(TextureKind kind) {
  switch (kind) {
    case TextureKind::solid: return "solid";
    case TextureKind::checker: return "checker";
    case TextureKind::stripes: return "stripes";
    case TextureKind::noise: return "noise";
    case TextureKind::gradient: return "gradient";
  }
  return "?";
}

// A solid texture evaluated at a point of the primitive's own (canonical) frame, so patterns move with the
// primitive and need no UV unwrapping.
struct Material {
  TextureKind kind = TextureKind::solid;
  glm::vec3 color0{0.8f}, color1{0.2f};
  float frequency = 4.0f;         // cells, stripes or noise features per canonical unit
  glm::vec3 direction{0, 0, 1};   // stripes / gradient axis (unit)
  glm::vec3 offset{0.0f};         // shifts the pattern so cell borders do not sit on the primitive's symmetry planes
  std::uint32_t noise_seed = 0;
};

struct Mesh {
  std::vector<glm::vec3> positions;  // world frame
  std::vector<glm::vec3> normals;    // world frame, unit, per vertex (smooth or per-face duplicates)
  std::vector<glm::vec3> texcoords;  // canonical primitive frame: the point a solid texture is evaluated at
  std::vector<glm::uvec3> triangles;
  std::vector<std::uint32_t> triangle_material;  // index into materials, one per triangle
  std::vector<Material> materials;

  std::size_t vertex_count() const noexcept { return positions.size(); }
  std::size_t triangle_count() const noexcept { return triangles.size(); }
};

// Every index in range, attribute arrays of equal length, finite positions: the renderer's precondition.
inline void validate_mesh(const Mesh& mesh, const std::string& context) {
  const std::size_t n = mesh.positions.size();
  require(mesh.normals.size() == n && mesh.texcoords.size() == n, context, ": mesh has ", n, " positions, ",
          mesh.normals.size(), " normals and ", mesh.texcoords.size(), " texcoords (must be equal)");
  require(mesh.triangle_material.size() == mesh.triangles.size(), context, ": mesh has ", mesh.triangles.size(),
          " triangles but ", mesh.triangle_material.size(), " triangle materials");
  for (std::size_t i = 0; i < n; ++i)
    if (!(std::isfinite(mesh.positions[i].x) && std::isfinite(mesh.positions[i].y) &&
          std::isfinite(mesh.positions[i].z)))
      fail(context, ": vertex ", i, " has a non-finite position");
  for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
    const glm::uvec3 tri = mesh.triangles[t];
    if (tri.x >= n || tri.y >= n || tri.z >= n) fail(context, ": triangle ", t, " indexes past ", n, " vertices");
    if (mesh.triangle_material[t] >= mesh.materials.size())
      fail(context, ": triangle ", t, " uses material ", mesh.triangle_material[t], " of ", mesh.materials.size());
  }
}

namespace detail {

inline float lattice_value(int x, int y, int z, std::uint32_t seed) {
  std::uint64_t h = mix64((static_cast<std::uint64_t>(static_cast<std::uint32_t>(x)) << 32) ^
                          static_cast<std::uint32_t>(y));
  h = mix64(h ^ (static_cast<std::uint64_t>(static_cast<std::uint32_t>(z)) << 21) ^ seed);
  return static_cast<float>(h >> 40) * 0x1.0p-24f;
}

// Trilinear value noise with smoothstep weights, in [0, 1].
inline float value_noise(glm::vec3 p, std::uint32_t seed) {
  const glm::vec3 f = glm::floor(p);
  const glm::vec3 t = p - f;
  const glm::vec3 w = t * t * (3.0f - 2.0f * t);
  const int x = static_cast<int>(f.x), y = static_cast<int>(f.y), z = static_cast<int>(f.z);
  float c[2][2][2];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) c[i][j][k] = lattice_value(x + i, y + j, z + k, seed);
  const float x00 = c[0][0][0] + w.x * (c[1][0][0] - c[0][0][0]), x10 = c[0][1][0] + w.x * (c[1][1][0] - c[0][1][0]);
  const float x01 = c[0][0][1] + w.x * (c[1][0][1] - c[0][0][1]), x11 = c[0][1][1] + w.x * (c[1][1][1] - c[0][1][1]);
  const float y0 = x00 + w.y * (x10 - x00), y1 = x01 + w.y * (x11 - x01);
  return y0 + w.z * (y1 - y0);
}

}  // namespace detail

// Albedo in [0, 1]^3 at canonical point p.
inline glm::vec3 albedo(const Material& m, glm::vec3 p) {
  const glm::vec3 q = p + m.offset;
  switch (m.kind) {
    case TextureKind::solid: return m.color0;
    case TextureKind::checker: {
      const glm::vec3 c = glm::floor(q * m.frequency);
      const int parity = (static_cast<int>(c.x) + static_cast<int>(c.y) + static_cast<int>(c.z)) & 1;
      return parity ? m.color1 : m.color0;
    }
    case TextureKind::stripes: {
      const float s = glm::dot(q, m.direction) * m.frequency;
      return s - std::floor(s) < 0.5f ? m.color0 : m.color1;
    }
    case TextureKind::noise: {
      const glm::vec3 r = q * m.frequency;
      const float n = (2.0f * detail::value_noise(r, m.noise_seed) +
                       detail::value_noise(2.0f * r, m.noise_seed ^ 0x9e37u)) / 3.0f;
      return glm::mix(m.color0, m.color1, glm::clamp(1.6f * (n - 0.5f) + 0.5f, 0.0f, 1.0f));
    }
    case TextureKind::gradient: {
      const float t = glm::clamp(0.5f + 0.5f * glm::dot(q, m.direction), 0.0f, 1.0f);
      return glm::mix(m.color0, m.color1, t);
    }
  }
  return m.color0;
}

}  // namespace data
}  // namespace v0
}  // namespace flexsplat
