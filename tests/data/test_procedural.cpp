#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <numbers>

#include "flexsplat/data/mesh_render.hpp"
#include "flexsplat/data/procedural.hpp"

using namespace flexsplat;
using namespace flexsplat::data;

TEST_CASE("a blob's vertices lie on its wave-bent sphere and its normals are the surface's", "[data][procedural]") {
  Primitive blob;
  blob.kind = PrimitiveKind::blob;
  blob.shape = 0.3f;
  blob.waves = 12345;
  const glm::mat3 rot = glm::mat3(glm::mat3_cast(glm::angleAxis(0.4f, glm::normalize(glm::vec3(2, -1, 1)))));
  blob.linear = rot * glm::mat3(glm::vec3(0.6f, 0, 0), glm::vec3(0, 0.8f, 0), glm::vec3(0, 0, 0.5f));
  blob.translation = {0.1f, 0.2f, -0.1f};
  const int segments = 128, rings = segments / 2, stride = segments + 1;
  Mesh mesh;
  mesh.materials.push_back(blob.material);
  append_primitive(mesh, blob, 0, segments);
  REQUIRE(mesh.positions.size() == static_cast<std::size_t>((rings + 1) * stride));

  const data::detail::BlobWaves waves(blob.waves, blob.shape);
  const glm::mat3 inv = glm::inverse(blob.linear);
  float min_r = INFINITY, max_r = 0, worst_radius = 0, worst_normal = 1;
  for (int r = 1; r < rings; ++r)  // the poles' rows hold one point many times: no finite difference there
    for (int c = 1; c < segments; ++c) {
      const auto at = [&](int rr, int cc) { return mesh.positions[static_cast<std::size_t>(rr * stride + cc)]; };
      const glm::vec3 q = inv * (at(r, c) - blob.translation);  // canonical frame
      glm::vec3 n;
      const float expected = waves.radius(glm::normalize(q), n) / (1.0f + blob.shape);
      worst_radius = std::max(worst_radius, std::abs(glm::length(q) - expected));
      min_r = std::min(min_r, glm::length(q)), max_r = std::max(max_r, glm::length(q));
      // The surface's normal from the grid's central differences, against the mesh's (world frame).
      const glm::vec3 fd = glm::normalize(glm::cross(at(r + 1, c) - at(r - 1, c), at(r, c + 1) - at(r, c - 1)));
      const glm::vec3 normal = mesh.normals[static_cast<std::size_t>(r * stride + c)];
      worst_normal = std::min(worst_normal, std::abs(glm::dot(fd, normal)));
      if (r == rings / 2 && c == segments / 3) CHECK(glm::dot(normal, at(r, c) - blob.translation) > 0);  // outward
    }
  CHECK(worst_radius < 1e-5f);
  CHECK(worst_normal > 0.995f);
  CHECK(max_r <= 1.0f + 1e-5f);  // fits the canonical unit ball
  CHECK(max_r - min_r > 0.15f);  // and is bent, not a sphere
}

TEST_CASE("procedural objects: blob_fraction and attached draw organic objects, the defaults none of them",
          "[data][procedural]") {
  int blobs_default = 0, blobs_half = 0, solids_half = 0, parts = 0;
  for (std::uint64_t seed = 1; seed <= 60; ++seed) {
    const ProceduralObject plain = make_object(seed);
    for (const Primitive& p : plain.primitives) blobs_default += p.kind == PrimitiveKind::blob;

    ObjectConfig organic;
    organic.blob_fraction = 0.5f;
    organic.attached = true;
    const ProceduralObject o = make_object(seed, organic);
    const glm::mat3 body_inv = glm::inverse(o.primitives[0].linear);
    for (std::size_t i = 0; i < o.primitives.size(); ++i) {
      const Primitive& p = o.primitives[i];
      (p.kind == PrimitiveKind::blob ? blobs_half : solids_half) += 1;
      if (i == 0) continue;
      // Each part's centre in the body's canonical frame: between 0.6 and 1 of the way to its surface.
      const float reach = glm::length(body_inv * (p.translation - o.primitives[0].translation));
      CHECK(reach >= 0.6f - 1e-4f);
      CHECK(reach <= 1.0f + 1e-4f);
      ++parts;
    }
    float radius = 0;
    for (const glm::vec3& v : o.mesh.positions) radius = std::max(radius, glm::length(v));
    CHECK(radius == Approx(1.0f).margin(2e-3));  // normalised like every procedural object
  }
  CHECK(blobs_default == 0);
  CHECK(blobs_half > 40);
  CHECK(solids_half > 40);
  CHECK(parts > 100);

  ObjectConfig all;
  all.blob_fraction = 1.0f;
  for (const Primitive& p : make_object(5, all).primitives) CHECK(p.kind == PrimitiveKind::blob);
  all.blob_fraction = 1.5f;
  CHECK_THROWS_WITH(make_object(5, all), Catch::Contains("blob_fraction 1.5"));
}

TEST_CASE("procedural objects: soft_textures changes the materials alone", "[data][procedural]") {
  ObjectConfig soft;
  soft.soft_textures = true;
  int noise = 0;
  for (std::uint64_t seed = 1; seed <= 40; ++seed) {
    const ProceduralObject a = make_object(seed), b = make_object(seed, soft);
    REQUIRE(a.primitives.size() == b.primitives.size());
    CHECK(a.mesh.positions == b.mesh.positions);  // the same draws, so the same shapes and light
    CHECK(a.light_direction == b.light_direction);
    for (const Primitive& p : b.primitives) {
      CHECK(p.material.kind != TextureKind::checker);
      CHECK(p.material.kind != TextureKind::stripes);
      noise += p.material.kind == TextureKind::noise;
    }
  }
  CHECK(noise > 20);
}
