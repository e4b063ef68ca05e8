#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

#include "flexsplat/data/mesh_render.hpp"
#include "flexsplat/data/procedural.hpp"

using namespace flexsplat;
using namespace flexsplat::data;

namespace {

Mesh single_primitive(const Primitive& prim, int segments) {
  Mesh mesh;
  mesh.materials.push_back(prim.material);
  append_primitive(mesh, prim, 0, segments);
  return mesh;
}

// World ray through the centre of pixel (x, y).
void pixel_ray(const Camera& cam, int x, int y, glm::dvec3& origin, glm::dvec3& dir) {
  origin = cam.centre();
  dir = glm::normalize(cam.to_world(cam.unproject({x + 0.5, y + 0.5}, 1.0)) - origin);
}

// Camera z of the world point origin + s * dir.
double camera_z(const Camera& cam, glm::dvec3 origin, glm::dvec3 dir, double s) {
  return cam.to_camera(origin + s * dir).z;
}

double sphere_hit(glm::dvec3 o, glm::dvec3 d, glm::dvec3 c, double r) {
  const glm::dvec3 oc = o - c;
  const double b = glm::dot(oc, d), disc = b * b - (glm::dot(oc, oc) - r * r);
  return disc < 0 ? -1 : -b - std::sqrt(disc);
}

}  // namespace

TEST_CASE("rendered box depth equals the ray-box intersection", "[data]") {
  Primitive box;
  box.kind = PrimitiveKind::box;
  const glm::mat3 rot = glm::mat3(glm::mat3_cast(glm::angleAxis(0.7f, glm::normalize(glm::vec3(1, 2, 3)))));
  box.linear = rot * glm::mat3(glm::vec3(0.5f, 0, 0), glm::vec3(0, 0.7f, 0), glm::vec3(0, 0, 0.4f));
  box.translation = {0.1f, -0.2f, 0.05f};
  const Mesh mesh = single_primitive(box, 8);
  const Camera cam = orbit_camera(25, 40, 3.0, 45, 96, 80, glm::dvec3(0.05, 0, 0));
  RenderOutput out;
  RenderWorkspace ws;
  RenderOptions opt;
  opt.normals = true;
  render_mesh(mesh, cam, opt, out, ws);
  const glm::dmat3 inv = glm::inverse(glm::dmat3(box.linear));
  int hits = 0, mismatched = 0;
  double worst = 0;
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      glm::dvec3 o, d;
      pixel_ray(cam, x, y, o, d);
      // Slab test in the box's canonical frame (where it is [-1, 1]^3).
      const glm::dvec3 lo = inv * (o - glm::dvec3(box.translation)), ld = inv * d;
      double t0 = -1e30, t1 = 1e30;
      for (int a = 0; a < 3; ++a) {
        const double ta = (-1 - lo[a]) / ld[a], tb = (1 - lo[a]) / ld[a];
        t0 = std::max(t0, std::min(ta, tb));
        t1 = std::min(t1, std::max(ta, tb));
      }
      const bool hit = t0 <= t1 && t0 > 0;
      if (hit != (out.depth(y, x) > 0)) {
        ++mismatched;
        continue;
      }
      if (!hit) continue;
      ++hits;
      worst = std::max(worst, std::abs(out.depth(y, x) - camera_z(cam, o, d, t0)));
      const glm::dvec3 n(out.normals(y, x, 0), out.normals(y, x, 1), out.normals(y, x, 2));
      CHECK(glm::dot(n, d) < 0);  // normals face the camera
    }
  CHECK(mismatched == 0);
  CHECK(hits > 1000);
  CHECK(worst < 2e-6);  // float32 output of depths near 3
}

TEST_CASE("rendered sphere depth lies between the circumscribed and inscribed spheres", "[data]") {
  const int segments = 96;  // meridian and ring spacing pi / 48: every facet point is within r (1 - cos delta)
  const double r = 0.8, delta = std::sqrt(2.0) * std::numbers::pi / 48;
  Primitive sphere;
  sphere.kind = PrimitiveKind::sphere;
  sphere.linear = glm::mat3(static_cast<float>(r));
  sphere.translation = {0.1f, -0.05f, 0.2f};
  const Mesh mesh = single_primitive(sphere, segments);
  const Camera cam = orbit_camera(-15, 200, 2.7, 50, 64, 64);
  RenderOutput out;
  RenderWorkspace ws;
  render_mesh(mesh, cam, RenderOptions{}, out, ws);
  int inside = 0;
  double max_excess = 0;
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      glm::dvec3 o, d;
      pixel_ray(cam, x, y, o, d);
      const double outer = sphere_hit(o, d, glm::dvec3(sphere.translation), r);
      const double inner = sphere_hit(o, d, glm::dvec3(sphere.translation), r * std::cos(delta));
      if (inner > 0) {  // the ray meets the inner sphere, so it must meet the polyhedron between the two
        ++inside;
        REQUIRE(out.depth(y, x) > 0);
        CHECK(out.depth(y, x) >= camera_z(cam, o, d, outer) - 2e-6);
        CHECK(out.depth(y, x) <= camera_z(cam, o, d, inner) + 2e-6);
      }
      if (outer < 0) CHECK(out.depth(y, x) == 0);
      if (out.depth(y, x) > 0) {  // the surface point is between the two spheres
        const double radius = glm::length(cam.to_world(cam.unproject({x + 0.5, y + 0.5}, out.depth(y, x))) -
                                          glm::dvec3(sphere.translation));
        CHECK(radius <= r + 2e-6);
        CHECK(radius >= r * std::cos(delta) - 2e-6);
        max_excess = std::max(max_excess, r - radius);
      }
    }
  CHECK(inside > 500);
  CHECK(max_excess > 0);  // the facets are inside the sphere, not on it
}

TEST_CASE("depth unprojected from one view reprojects onto another view's depth", "[data]") {
  const ProceduralObject object = make_object(1);
  const Camera a = orbit_camera(20, 30, 3.0, 45, 128, 128, glm::dvec3(0.02, -0.01, 0.03));
  const Camera b = orbit_camera(35, 75, 3.2, 48, 128, 128);
  RenderOutput ra, rb;
  RenderWorkspace ws;
  render_mesh(object.mesh, a, RenderOptions{}, ra, ws);
  render_mesh(object.mesh, b, RenderOptions{}, rb, ws);
  std::vector<double> errors;
  for (int y = 0; y < a.height; ++y)
    for (int x = 0; x < a.width; ++x) {
      if (ra.depth(y, x) <= 0) continue;
      const glm::dvec3 world = a.to_world(a.unproject({x + 0.5, y + 0.5}, ra.depth(y, x)));
      const glm::dvec3 pb = b.to_camera(world);
      const glm::dvec2 uv = b.project(pb);
      // Bilinear inverse depth of b around uv (exact on planar facets); skip where a neighbour is background.
      const double fx = uv.x - 0.5, fy = uv.y - 0.5;
      const int x0 = static_cast<int>(std::floor(fx)), y0 = static_cast<int>(std::floor(fy));
      if (x0 < 0 || y0 < 0 || x0 + 1 >= b.width || y0 + 1 >= b.height) continue;
      double inv = 0;
      bool valid = true;
      for (int j = 0; j < 2; ++j)
        for (int i = 0; i < 2; ++i) {
          const float z = rb.depth(y0 + j, x0 + i);
          valid = valid && z > 0;
          inv += (i ? fx - x0 : 1 - (fx - x0)) * (j ? fy - y0 : 1 - (fy - y0)) / z;
        }
      if (!valid || std::abs(1 / inv - pb.z) > 0.05) continue;  // background or occluded in b
      // Reprojection error in b's pixels: the 3D distance between b's surface point and a's, seen at depth z.
      const glm::dvec3 surface_b = b.unproject(uv, 1 / inv);
      errors.push_back(glm::length(surface_b - pb) * b.K[0][0] / pb.z);
    }
  REQUIRE(errors.size() > 1000);
  std::sort(errors.begin(), errors.end());
  CHECK(errors[errors.size() / 2] < 0.01);
  CHECK(errors[errors.size() * 9 / 10] < 0.1);
}

TEST_CASE("a rendered checkerboard plane follows the plane-to-image homography", "[data]") {
  // Plane z = 0, x, y in [-1, 1], checker of 8 cells per unit, unlit (ambient 1) black and white.
  Mesh mesh;
  Material checker;
  checker.kind = TextureKind::checker;
  checker.color0 = glm::vec3(0.0f);
  checker.color1 = glm::vec3(1.0f);
  checker.frequency = 4.0f;
  mesh.materials.push_back(checker);
  for (glm::vec3 p : {glm::vec3(-1, -1, 0), glm::vec3(1, -1, 0), glm::vec3(1, 1, 0), glm::vec3(-1, 1, 0)}) {
    mesh.positions.push_back(p);
    mesh.normals.push_back({0, 0, 1});
    mesh.texcoords.push_back({p.x, p.y, 0.1f});  // z well inside one cell: parity is decided by x and y
  }
  mesh.triangles = {{0, 1, 2}, {0, 2, 3}};
  mesh.triangle_material = {0, 0};
  const Camera cam = orbit_camera(35, 20, 2.2, 60, 128, 96);
  RenderOptions opt;
  opt.ambient = 1.0f;
  RenderOutput out;
  RenderWorkspace ws;
  render_mesh(mesh, cam, opt, out, ws);
  // H = K [r1 r2 t] maps plane (x, y, 1) to pixels; its inverse maps pixel corners back to the plane.
  glm::dmat3 rt(cam.R[0], cam.R[1], cam.t);
  const glm::dmat3 Hinv = glm::inverse(cam.K * rt);
  auto plane_at = [&](double u, double v) {
    const glm::dvec3 p = Hinv * glm::dvec3(u, v, 1);
    return glm::dvec2(p.x / p.z, p.y / p.z);
  };
  auto cell = [](glm::dvec2 p) { return glm::ivec2(std::floor(p.x * 4), std::floor(p.y * 4)); };
  int interior = 0, wrong = 0, boundary = 0;
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const glm::dvec2 c0 = plane_at(x, y), c1 = plane_at(x + 1, y), c2 = plane_at(x, y + 1), c3 = plane_at(x + 1, y + 1);
      bool on_plane = true;
      for (glm::dvec2 c : {c0, c1, c2, c3}) on_plane = on_plane && std::abs(c.x) < 1 && std::abs(c.y) < 1;
      if (!on_plane) continue;
      const glm::ivec2 k = cell(c0);
      if (cell(c1) != k || cell(c2) != k || cell(c3) != k) {
        ++boundary;
        CHECK(out.rgba(y, x, 3) == 1.0f);
        continue;
      }
      ++interior;
      const float expected = ((k.x + k.y) & 1) ? 1.0f : 0.0f;
      wrong += out.rgba(y, x, 0) != expected || out.rgba(y, x, 3) != 1.0f;
      // Depth: the ray through the pixel centre meets the plane at the homography's point.
      const glm::dvec2 p = plane_at(x + 0.5, y + 0.5);
      CHECK(out.depth(y, x) == Approx(cam.to_camera(glm::dvec3(p, 0)).z).epsilon(1e-6));
    }
  CHECK(interior > 2000);
  CHECK(boundary > 500);
  CHECK(wrong == 0);
}

TEST_CASE("near-plane clipping keeps the visible part of a triangle crossing the camera", "[data]") {
  Mesh mesh;
  mesh.materials.push_back(Material{});
  for (glm::vec3 p : {glm::vec3(-5, -5, 0), glm::vec3(5, -5, 0), glm::vec3(0, 5, 0)}) {
    mesh.positions.push_back(p);
    mesh.normals.push_back({0, 0, 1});
    mesh.texcoords.push_back(p);
  }
  mesh.triangles = {{0, 1, 2}};
  mesh.triangle_material = {0};
  // A camera just above the plane looking along +x at a shallow angle: the triangle extends behind it.
  Camera cam = look_at({0, 0, 0.3}, {1, 0, 0.1}, 64, 48, intrinsics_from_fov(64, 48, 60));
  RenderOutput out;
  RenderWorkspace ws;
  render_mesh(mesh, cam, RenderOptions{}, out, ws);
  int covered = 0;
  for (int y = 0; y < 48; ++y)
    for (int x = 0; x < 64; ++x) {
      if (out.depth(y, x) <= 0) continue;
      ++covered;
      const glm::dvec3 w = cam.to_world(cam.unproject({x + 0.5, y + 0.5}, out.depth(y, x)));
      CHECK(std::abs(w.z) < 1e-5);
    }
  CHECK(covered > 300);
}

TEST_CASE("render_mesh rejects a bad camera or mesh with a clear message", "[data]") {
  const ProceduralObject object = make_object(7);
  RenderOutput out;
  RenderWorkspace ws;
  Camera cam = orbit_camera(10, 10, 3, 45, 16, 16);
  cam.R[0][0] = 2;
  CHECK_THROWS_WITH(render_mesh(object.mesh, cam, RenderOptions{}, out, ws), Catch::Contains("not a rotation"));
  Mesh broken = object.mesh;
  broken.triangles[3].y = 1u << 30;
  CHECK_THROWS_WITH(render_mesh(broken, orbit_camera(10, 10, 3, 45, 16, 16), RenderOptions{}, out, ws),
                    Catch::Contains("triangle 3 indexes past"));
}
