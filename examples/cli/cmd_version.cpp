// version: library version, the SIMD instruction set compiled in, what the CPU offers, and the worker count.
#include <cstdio>

#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/simd_dispatch.hpp"
#include "flexsplat/core/version.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int version(const Args& args) {
  require(args.empty(), "version takes no arguments");
  const auto& features = simd::cpu_features();
  std::printf("flexsplat %s\n", version_string);
  std::printf("simd: compiled for %s (%zu floats per batch)%s\n", simd::compiled_arch_name(), simd::width<float>,
              simd::enabled() ? "" : ", scalar path forced by FLEXSPLAT_SIMD=scalar");
  std::printf("cpu: %s\n", simd::describe(features).c_str());
  std::printf("threads: %d\n", global_pool().size());
  std::printf("run-time dispatch: %s\n", simd::dispatch_name(simd::dispatch_level()));
  simd::require_cpu_supports_build();
  return 0;
}

const RegisterCommand registered_cmd_version("version", {"print version, SIMD build, CPU features and thread count", "", version});

}  // namespace
}  // namespace flexsplat::cli
