// Views per second generated in memory (procedural object + CPU mesh render + batch assembly, no files), through
// data::generate_batch, at 128^2 and 256^2: wall clock over all threads, and per CPU-second of the process (less
// sensitive to other load on a shared machine). Usage: build/bench/data [batches=5] [scenes per batch=4] [views=8]
#include <algorithm>
#include <chrono>
#include <ctime>
#include <cstdio>
#include <cstdlib>
#include <vector>

#include "flexsplat/data/dataset.hpp"

using namespace flexsplat;

int main(int argc, char** argv) {
  const int batches = argc > 1 ? std::atoi(argv[1]) : 5;
  const int scenes = argc > 2 ? std::atoi(argv[2]) : 4;
  const int views = argc > 3 ? std::atoi(argv[3]) : 8;
  if (batches < 1 || scenes < 1 || views < 2) {
    std::fprintf(stderr, "usage: data [batches >= 1] [scenes >= 1] [views >= 2]\n");
    return 2;
  }
  std::printf("threads %d, %d batches of %d scenes x %d views (4 structured inputs + %d targets), median batch\n",
              global_pool().size(), batches, scenes, views, views - 4);
  std::printf("%-8s %-12s %12s %12s %16s %14s\n", "size", "supersample", "ms/batch", "views/s", "views/CPU-s",
              "CPU ms/object");
  for (int size : {128, 256})
    for (int ss : {1, 2}) {
      data::GeneratorConfig cfg;
      cfg.size = size;
      cfg.supersample = ss;
      data::BatchOptions o;
      o.inputs = 4;
      o.targets = views - 4;
      std::vector<double> ms;
      const std::clock_t cpu0 = std::clock();
      for (int b = 0; b < batches; ++b) {
        const auto t0 = std::chrono::steady_clock::now();
        const auto batch = data::generate_batch(cfg, scenes, 1, static_cast<std::uint64_t>(b), o);
        ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
        if (batch.size() != static_cast<std::size_t>(scenes)) return 1;
      }
      const double cpu_s = static_cast<double>(std::clock() - cpu0) / CLOCKS_PER_SEC;
      std::sort(ms.begin(), ms.end());
      const double median = ms[ms.size() / 2];
      // Object construction alone (primitives, tessellation, normalisation), CPU time over 50 objects.
      const std::clock_t obj0 = std::clock();
      std::size_t triangles = 0;
      for (int i = 0; i < 50; ++i)
        triangles += data::make_object(data::object_seed(1, static_cast<std::uint64_t>(i))).mesh.triangle_count();
      const double object_ms = 1000.0 * static_cast<double>(std::clock() - obj0) / CLOCKS_PER_SEC / 50;
      if (triangles == 0) return 1;
      char name[16];
      std::snprintf(name, sizeof name, "%dx%d", size, size);
      std::printf("%-8s %-12d %12.1f %12.1f %16.1f %14.3f\n", name, ss, median, scenes * views / (median / 1000.0),
                  batches * scenes * views / cpu_s, object_ms);
    }
  return 0;
}
