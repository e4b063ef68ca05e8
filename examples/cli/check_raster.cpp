// Registers the `raster` reference checker (logic in flexsplat/raster/reference.hpp).
#include "flexsplat/raster/reference.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {
const RegisterChecker registered_check_raster("raster", raster::check_raster_bundle);
}  // namespace
}  // namespace flexsplat::cli
