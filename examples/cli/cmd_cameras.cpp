// cameras: a capture's cameras (COLMAP model folder, transforms.json or cameras.json) listed, or written in another
// of those formats.
#include <cstdio>
#include <string>

#include "flexsplat/io/capture_cameras.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int cameras_command(Args args) {
  std::string out, format;
  const bool has_out = take_option(args, "-o", out) || take_option(args, "--output", out);
  const bool has_format = take_option(args, "--format", format);
  for (const auto& a : args) require(a.empty() || a[0] != '-', "cameras: unknown option '", a, "'");
  require(args.size() == 1, "cameras needs exactly one PATH (a COLMAP model folder, a transforms.json or a cameras.json)");
  require(has_out == has_format, "cameras: -o OUT and --format F go together");
  require(!has_format || format == "colmap-text" || format == "colmap-binary" || format == "transforms",
          "cameras: --format '", format, "' is not one of: colmap-text, colmap-binary, transforms");
  io::CameraFormat from{};
  const std::vector<Camera> cams = io::load_capture_cameras(args[0], {}, &from);
  std::printf("%s: %s, %zu camera(s)\n", args[0].c_str(), io::camera_format_name(from), cams.size());
  for (const Camera& c : cams) {
    const glm::dvec3 o = c.centre();
    std::printf("  %s %dx%d fx=%.6g fy=%.6g cx=%.6g cy=%.6g centre=(%.6g, %.6g, %.6g)\n", c.name.c_str(), c.width,
                c.height, c.K[0][0], c.K[1][1], c.K[2][0], c.K[2][1], o.x, o.y, o.z);
  }
  if (!has_out) return 0;
  if (format == "colmap-text") io::write_colmap_text(out, cams);
  if (format == "colmap-binary") io::write_colmap_binary(out, cams);
  if (format == "transforms") io::write_transforms_json(out, cams);
  std::printf("wrote %s (%s)\n", out.c_str(), format.c_str());
  return 0;
}

const RegisterCommand registered_cmd_cameras(
    "cameras", {"list a capture's cameras, or write them as a COLMAP model or a transforms.json",
                "PATH [-o OUT --format colmap-text|colmap-binary|transforms]\n"
                "  PATH: a COLMAP sparse model folder (cameras.txt + images.txt or the .bin pair), a nerfstudio /\n"
                "  instant-ngp transforms.json, or a cameras.json; the cameras `reconstruct --cameras PATH` reads\n"
                "  -o OUT: a folder for the COLMAP formats (one PINHOLE camera per image), a file for transforms\n"
                "  (docs/app.md)",
                cameras_command});

}  // namespace
}  // namespace flexsplat::cli
