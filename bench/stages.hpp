#pragma once
// The benchmarks' table of profile::stages(): per stage its wall and CPU seconds per call round, the FLOPs the op
// scopes counted in it (GEMMs, attention), their rate and its fraction of a reference GEMM rate (the roofline).
#include <cstdio>
#include <string>
#include <vector>

#include "flexsplat/core/profile.hpp"

namespace flexsplat::bench {

// rounds: the stages' totals are divided by it; rate_gflops 0 leaves out the fraction column.
inline void print_stages(const std::vector<profile::StageTotals>& stages, int rounds, double rate_gflops) {
  std::printf("  %-40s %9s %9s %10s %9s %s\n", "stage", "wall s", "CPU s", "GFLOP", "GFLOP/s",
              rate_gflops > 0 ? "of GEMM rate" : "");
  for (const profile::StageTotals& s : stages) {
    const std::size_t slash = s.path.rfind('/');
    const std::string name = std::string(static_cast<std::size_t>(2 * s.depth), ' ') +
                             (slash == std::string::npos ? s.path : s.path.substr(slash + 1));
    const double wall = s.seconds / rounds, gflop = s.flops / rounds / 1e9;
    const double rate = wall > 0 ? gflop / wall : 0;
    std::printf("  %-40s %9.3f %9.3f %10.2f %9.1f", name.c_str(), wall, s.cpu_seconds / rounds, gflop, rate);
    if (rate_gflops > 0 && gflop > 0) std::printf("  %5.2f", rate / rate_gflops);
    std::printf("\n");
  }
}

}  // namespace flexsplat::bench
