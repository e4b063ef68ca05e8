// Numerical stress of every stage (tests/stress/stress_cases.hpp): random extreme inputs, each case finite or a
// clear flexsplat::Error for invalid input. Prints one row per stage and the failing cases.
//   build/bench/stress [--cases N (per stage, default 1000)] [--seed S] [--stage raster|decoder|geometry|model]
//                      [--first K (start at case K: replays a failure)]
#include <cstdio>
#include <cstdlib>
#include <string>

#include "../tests/stress/stress_cases.hpp"

int main(int argc, char** argv) {
  long cases = 1000;
  std::uint64_t seed = 1;
  std::string stage;
  long first = 0;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--cases" && i + 1 < argc) cases = std::atol(argv[++i]);
    else if (a == "--seed" && i + 1 < argc) seed = std::strtoull(argv[++i], nullptr, 10);
    else if (a == "--stage" && i + 1 < argc) stage = argv[++i];
    else if (a == "--first" && i + 1 < argc) first = std::atol(argv[++i]);
    else {
      std::fprintf(stderr, "usage: %s [--cases N] [--seed S] [--stage raster|decoder|geometry|model] [--first K]\n", argv[0]);
      return 2;
    }
  }
  const auto results = flexsplat_stress::run_all(cases, seed, stage, first);
  long failures = 0;
  std::printf("| stage | cases | finite | refused (invalid input) | failures | seconds |\n|---|---|---|---|---|---|\n");
  for (const auto& r : results) {
    std::printf("| %s | %ld | %ld | %ld | %ld | %.1f |\n", r.stage.c_str(), r.cases, r.finite, r.refused, r.failures, r.seconds);
    failures += r.failures;
  }
  for (const auto& r : results) {
    for (const auto& [message, count] : r.errors) std::printf("%s refused %ldx: %s\n", r.stage.c_str(), count, message.c_str());
    long shown = 0;
    for (const auto& f : r.failed)
      if (shown++ < 20) std::printf("%s FAILED %s\n", r.stage.c_str(), f.c_str());
  }
  return failures == 0 ? 0 : 1;
}
