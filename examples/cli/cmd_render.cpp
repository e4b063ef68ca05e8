// render: a .ply or .glb Gaussian file through the CPU rasterizer from cameras.json (or the file's own cameras).
#include <cstdio>
#include <sstream>

#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/export/render_set.hpp"
#include "flexsplat/image/image_io.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

std::array<double, 3> parse_background(const std::string& s) {
  if (s == "white") return {1, 1, 1};
  if (s == "black") return {0, 0, 0};
  std::array<double, 3> rgb{};
  char sep1 = 0, sep2 = 0;
  std::istringstream in(s);
  in >> rgb[0] >> sep1 >> rgb[1] >> sep2 >> rgb[2];
  require(!in.fail() && sep1 == ',' && sep2 == ',' && in.peek() == EOF, "--background '", s,
          "': expected white, black or r,g,b in [0, 1]");
  return rgb;
}

int render(Args args) {
  std::string camera_spec, output, background = "white", index_text;
  take_option(args, "--camera", camera_spec);
  take_option(args, "--index", index_text);
  require(take_option(args, "-o", output) || take_option(args, "--output", output), "render needs -o out.png");
  take_option(args, "--background", background);
  raster::RenderOptions options;
  options.antialiased = take_flag(args, "--antialiased");
  const bool rgba = take_flag(args, "--rgba");
  require(args.size() == 1, "render needs exactly one Gaussian FILE (got ", args.size(), " positional arguments)");
  options.background = parse_background(background);
  std::vector<Camera> cameras;
  const auto set = gaussians::read_gaussians(args[0], &cameras);
  if (!camera_spec.empty()) cameras = io::load_camera_spec(camera_spec);
  require(!cameras.empty(), "render: no camera (pass --camera cameras.json[:index]; '", args[0], "' has none)");
  if (!index_text.empty()) {
    const auto index = static_cast<std::size_t>(
        parse_integer(index_text, "--index", 0, static_cast<long long>(cameras.size()) - 1));
    cameras = {cameras[index]};
  }
  raster::RenderWorkspace<float> workspace;
  raster::RenderOutputs<float> out;
  const std::filesystem::path base(output);
  for (std::size_t i = 0; i < cameras.size(); ++i) {
    std::filesystem::path path = base;
    if (cameras.size() > 1) {
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_%03zu", i);
      path = base.parent_path() / (base.stem().string() + suffix + base.extension().string());
    }
    gaussians::render_set(set, cameras[i], options, workspace, out);
    if (rgba) {
      Tensor<float, 3> with_alpha({out.image.shape(0), out.image.shape(1), 4});
      for (index_t p = 0; p < out.alpha.size(); ++p) {
        for (int c = 0; c < 3; ++c) with_alpha.data()[4 * p + c] = out.image.data()[3 * p + c];
        with_alpha.data()[4 * p + 3] = out.alpha.data()[p];
      }
      image::write_png(path, with_alpha);
    } else {
      image::write_png(path, out.image);
    }
    std::printf("%s: %dx%d from camera '%s'\n", path.string().c_str(), cameras[i].width, cameras[i].height,
                cameras[i].name.c_str());
  }
  return 0;
}

const RegisterCommand registered_cmd_render(
    "render", {"render a .ply or .glb Gaussian file with the CPU rasterizer to PNG",
               "FILE [--camera cameras.json[:index]] [--index I] -o out.png [--background white|black|r,g,b] "
               "[--antialiased] [--rgba]  (several cameras: out_000.png, out_001.png, ...)",
               render});

}  // namespace
}  // namespace flexsplat::cli
