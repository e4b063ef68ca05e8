// convert: Gaussian sets between .ply (INRIA 3DGS) and .glb (KHR_gaussian_splatting), optionally quantised.
#include <cstdio>

#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/export/file.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

gltf::RotationEncoding parse_rotation(const std::string& s) {
  if (s == "float") return gltf::RotationEncoding::Float;
  if (s == "int8") return gltf::RotationEncoding::Int8Normalized;
  if (s == "int16") return gltf::RotationEncoding::Int16Normalized;
  fail("--rotation '", s, "': expected float, int8 or int16");
}

gltf::UnitEncoding parse_unit(const std::string& flag, const std::string& s) {
  if (s == "float") return gltf::UnitEncoding::Float;
  if (s == "uint8") return gltf::UnitEncoding::UInt8Normalized;
  if (s == "uint16") return gltf::UnitEncoding::UInt16Normalized;
  fail(flag, " '", s, "': expected float, uint8 or uint16");
}

int convert(Args args) {
  gltf::WriteOptions options;
  std::string value;
  if (take_flag(args, "--quantize")) {
    options.rotation = gltf::RotationEncoding::Int16Normalized;
    options.scale = gltf::UnitEncoding::UInt16Normalized;
    options.opacity = gltf::UnitEncoding::UInt8Normalized;
  }
  if (take_option(args, "--rotation", value)) options.rotation = parse_rotation(value);
  if (take_option(args, "--scale", value)) options.scale = parse_unit("--scale", value);
  if (take_option(args, "--opacity", value)) options.opacity = parse_unit("--opacity", value);
  if (take_option(args, "--color-space", value)) options.color_space = value;
  if (take_flag(args, "--no-color")) options.color_fallback = false;
  const bool no_cameras = take_flag(args, "--no-cameras");
  std::string camera_spec;
  take_option(args, "--cameras", camera_spec);
  require(args.size() == 2, "convert needs IN and OUT (got ", args.size(), " positional arguments)");
  const auto set = gaussians::read_gaussians(args[0], &options.cameras);
  if (!camera_spec.empty()) options.cameras = io::load_camera_spec(camera_spec);
  // A .ply holds no cameras: a .glb's own cameras are dropped there, explicitly requested ones are an error.
  const bool to_ply = gaussians::format_of(args[1]) == gaussians::FileFormat::Ply;
  if (no_cameras || (to_ply && camera_spec.empty())) options.cameras.clear();
  const auto report = gaussians::write_gaussians(set, args[1], options);
  std::printf("%s -> %s: %lld Gaussians, SH degree %d, %lld cameras, %zu bytes\n", args[0].c_str(), args[1].c_str(),
              static_cast<long long>(set.size()), set.sh_degree(), static_cast<long long>(options.cameras.size()),
              report.bytes);
  if (report.repairs.opacities_clamped || report.repairs.rotations_renormalised)
    std::printf("repaired: %lld opacities clamped to [0, 1], %lld quaternions renormalised\n",
                static_cast<long long>(report.repairs.opacities_clamped),
                static_cast<long long>(report.repairs.rotations_renormalised));
  return 0;
}

const RegisterCommand registered_cmd_convert(
    "convert", {"convert Gaussians between .ply (INRIA) and .glb (KHR_gaussian_splatting)",
                "IN.{ply,glb} OUT.{ply,glb} [--quantize] [--rotation float|int8|int16] [--scale float|uint8|uint16] "
                "[--opacity float|uint8|uint16] [--color-space srgb_rec709_display|lin_rec709_display] [--no-color] "
                "[--no-cameras] [--cameras cameras.json[:index]]",
                convert});

}  // namespace
}  // namespace flexsplat::cli
