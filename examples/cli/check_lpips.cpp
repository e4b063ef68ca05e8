// Registers the `lpips` reference checker (logic in flexsplat/loss/lpips_reference.hpp).
#include "flexsplat/loss/lpips_reference.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {
const RegisterChecker registered_check_lpips("lpips", [](const safetensors::File& file, ReferenceReport& report) {
  loss::check_lpips_bundle(file, report);
});
}  // namespace
}  // namespace flexsplat::cli
