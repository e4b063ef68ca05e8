// Registers the "deform_core" reference checker (float64, 1e-10 of each tensor's max abs value).
#include "flexsplat/decoder/reference.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {
const RegisterChecker registered_check_deform_core("deform_core", [](const safetensors::File& file, ReferenceReport& report) {
  decoder::check_deform_core_bundle<double>(file, report, 1e-10);
});
}  // namespace
}  // namespace flexsplat::cli
