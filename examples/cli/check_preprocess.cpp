// Registers the "preprocess" reference checker (VGGT load_and_preprocess_images); the logic lives in the library.
#include "flexsplat/geometry/preprocess_reference.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

const RegisterChecker registered_check_preprocess("preprocess", [](const safetensors::File& bundle, ReferenceReport& report) {
  check_preprocess_reference(bundle, report);
});

}  // namespace
}  // namespace flexsplat::cli
