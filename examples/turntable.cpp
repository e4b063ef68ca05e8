// A turntable of any Gaussian splat file (.glb or .ply): views orbiting the Gaussians, rendered with the library's CPU
// rasterizer and written side by side as one PNG.
//   turntable IN.glb|IN.ply [-o turntable.png] [--views 8] [--size 128]
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <string>
#include <vector>

#include <glm/glm.hpp>
#include <glm/gtc/matrix_transform.hpp>

#include "flexsplat/core/camera.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/export/render_set.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/plot.hpp"

using namespace flexsplat;

int main(int argc, char** argv) try {
  std::string input, output = "turntable.png";
  int views = 8, size = 128;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "-o" && i + 1 < argc) output = argv[++i];
    else if (a == "--views" && i + 1 < argc) views = std::atoi(argv[++i]);
    else if (a == "--size" && i + 1 < argc) size = std::atoi(argv[++i]);
    else if (input.empty() && a[0] != '-') input = a;
    else views = 0;  // unknown argument: print the usage
  }
  if (input.empty() || views < 1 || views > 64 || size < 8 || size > 4096) {
    std::fprintf(stderr, "usage: turntable IN.glb|IN.ply [-o turntable.png] [--views 1..64] [--size 8..4096]\n");
    return 2;
  }

  // 1. The Gaussians, and the cameras a .glb holds (a reconstruction's input photos).
  std::vector<Camera> cameras;
  const GaussianSet<float> set = gaussians::read_gaussians(input, &cameras);

  // 2. The orbit: about the opacity-weighted centre of the Gaussians. A file with cameras sets the up axis and the
  //    start from its first camera (OpenCV: y points down); otherwise world z is up (the shared objects' frame) and
  //    the start is at 20 degrees elevation, far enough for a 45 degree view to hold 90% of the Gaussian centres.
  glm::dvec3 centre(0.0);
  double weight = 0;
  for (index_t i = 0; i < set.size(); ++i) {
    centre += double(set.opacities(i)) * glm::dvec3(set.means(i, 0), set.means(i, 1), set.means(i, 2));
    weight += set.opacities(i);
  }
  require(weight > 0, "'", input, "': every Gaussian is transparent, nothing to turn around");
  centre /= weight;
  std::vector<double> distance;
  for (index_t i = 0; i < set.size(); ++i)
    distance.push_back(glm::length(glm::dvec3(set.means(i, 0), set.means(i, 1), set.means(i, 2)) - centre));
  std::nth_element(distance.begin(), distance.begin() + static_cast<std::ptrdiff_t>(distance.size() * 9 / 10), distance.end());
  const double radius = distance[distance.size() * 9 / 10];
  require(radius > 0 || !cameras.empty(), "'", input, "': the Gaussians sit at one point; no orbit to choose");
  const double half_fov = 22.5 * std::numbers::pi / 180, elevation = 20 * std::numbers::pi / 180;
  glm::dvec3 up(0, 0, 1), eye = centre + radius / std::sin(half_fov) * glm::dvec3(std::cos(elevation), 0, std::sin(elevation));
  if (!cameras.empty()) {
    up = -glm::transpose(cameras[0].R)[1];  // rows of R are the camera's axes in the world; y points down
    eye = cameras[0].centre();
  }
  const glm::dmat3 K = intrinsics_from_fov(size, size, 45.0);

  // 3. Render each view on white with the CPU rasterizer.
  raster::RenderOptions options;
  options.background = {1, 1, 1};
  raster::RenderWorkspace<float> workspace;
  raster::RenderOutputs<float> out;
  std::vector<Tensor<float, 3>> frames;
  std::vector<image::GridCell> cells;
  for (int f = 0; f < views; ++f) {
    const double angle = 2 * std::numbers::pi * f / views;
    const glm::dvec3 e = centre + glm::dvec3(glm::rotate(glm::dmat4(1.0), angle, up) * glm::dvec4(eye - centre, 0.0));
    gaussians::render_set(set, look_at(e, centre, size, size, K, up), options, workspace, out);
    frames.push_back(out.image);
  }
  for (const Tensor<float, 3>& fr : frames)
    cells.push_back({fr.view(), std::to_string(360 * static_cast<int>(cells.size()) / views) + " deg"});

  // 4. One picture: the views side by side, each labelled with its angle.
  const Tensor<std::uint8_t, 3> strip = image::image_grid(cells, views, size);
  image::write_png(output, strip);
  std::size_t covered = 0;  // pixels the Gaussians darken (the background is white)
  for (const auto& fr : frames)
    for (index_t i = 0; i < fr.size(); i += 3) covered += fr.data()[i] + fr.data()[i + 1] + fr.data()[i + 2] < 2.9f;
  std::printf("%s: %lld Gaussians, %d views of %dx%d in %lldx%lld pixels, object covers %.1f%% of the views\n",
              output.c_str(), static_cast<long long>(set.size()), views, size, size,
              static_cast<long long>(strip.shape(1)), static_cast<long long>(strip.shape(0)),
              100.0 * static_cast<double>(covered) / (static_cast<double>(views) * size * size));
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "turntable: error: %s\n", e.what());
  return 1;
}
