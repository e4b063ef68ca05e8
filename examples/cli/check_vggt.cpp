// Registers the `vggt` reference checker (logic in flexsplat/geometry/reference.hpp).
#include "flexsplat/geometry/reference.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {
const RegisterChecker registered_check_vggt("vggt", [](const safetensors::File& file, ReferenceReport& report) {
  geometry::check_vggt_reference(file, report);
});
}  // namespace
}  // namespace flexsplat::cli
