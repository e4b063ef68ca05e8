// info: counts, SH degree, bounds and value ranges of a .ply or .glb Gaussian file.
#include <algorithm>
#include <cstdio>

#include "flexsplat/export/file.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int info(Args args) {
  require(args.size() == 1, "info needs exactly one FILE");
  std::vector<Camera> cameras;
  const auto set = gaussians::read_gaussians(args[0], &cameras);
  const auto b = gaussians::position_bounds(set);
  std::printf("file: %s\n", args[0].c_str());
  std::printf("gaussians: %lld\n", static_cast<long long>(set.size()));
  std::printf("sh_degree: %d (%lld coefficients per channel)\n", set.sh_degree(),
              static_cast<long long>(set.sh.shape(1)));
  std::printf("bounds_min: %.6g %.6g %.6g\n", b.min[0], b.min[1], b.min[2]);
  std::printf("bounds_max: %.6g %.6g %.6g\n", b.max[0], b.max[1], b.max[2]);
  if (set.size() > 0) {
    const auto s = set.scales.span();
    const auto o = set.opacities.span();
    std::printf("scale_range: %.6g %.6g\n", *std::min_element(s.begin(), s.end()), *std::max_element(s.begin(), s.end()));
    std::printf("opacity_range: %.6g %.6g\n", *std::min_element(o.begin(), o.end()), *std::max_element(o.begin(), o.end()));
  }
  std::printf("cameras: %zu\n", cameras.size());
  for (const auto& cam : cameras)
    std::printf("  %s %dx%d fx=%.6g fy=%.6g cx=%.6g cy=%.6g\n", cam.name.c_str(), cam.width, cam.height, cam.K[0][0],
                cam.K[1][1], cam.K[2][0], cam.K[2][1]);
  return 0;
}

const RegisterCommand registered_cmd_info("info", {"counts, SH degree and bounds of a .ply or .glb Gaussian file", "FILE", info});

}  // namespace
}  // namespace flexsplat::cli
