// First-touch cost of fresh memory with 4 KiB pages, with the huge-page advice core/memory.hpp gives large buffers, and
// with those pages mapped in on the pool's workers first (populate_pages, as AlignedAllocator does).
// Usage: memory [MiB=512] [rounds=3]. Each round allocates and writes one byte per 4 KiB page; every block is held to
// the end, so no round gets memory an earlier one touched (peak: 3 x rounds x MiB).
#include <sys/mman.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <new>
#include <vector>

#include "flexsplat/core/memory.hpp"

namespace {
enum class Mode { small_pages, huge, huge_populated };

struct Block {
  void* p = nullptr;
  bool huge = false;
};

void release(Block b, std::size_t bytes) {
  if (b.huge) flexsplat::deallocate_aligned(b.p, bytes, 64);
  else ::operator delete(b.p, std::align_val_t{64});
}

double touch_seconds(std::size_t bytes, Mode mode, Block& block) {
  const bool huge = mode != Mode::small_pages;
  const auto t0 = std::chrono::steady_clock::now();
  void* p = huge ? flexsplat::allocate_aligned(bytes, 64) : ::operator new(bytes, std::align_val_t{64});
  if (!huge) ::madvise(p, bytes & ~std::size_t(4095), MADV_NOHUGEPAGE);  // 4 KiB pages even where THP is "always"
  if (mode == Mode::huge_populated) flexsplat::populate_pages(p, bytes);
  auto* c = static_cast<volatile char*>(p);
  for (std::size_t i = 0; i < bytes; i += 4096) c[i] = 1;
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  block = {p, huge};
  return s;
}
}  // namespace

int main(int argc, char** argv) {
  const std::size_t mib = argc > 1 ? std::strtoull(argv[1], nullptr, 10) : 512;
  const int rounds = argc > 2 ? std::atoi(argv[2]) : 3;
  if (mib == 0 || rounds < 1) {
    std::fprintf(stderr, "memory: MiB and rounds must be positive, got %s and %s\n", argc > 1 ? argv[1] : "512",
                 argc > 2 ? argv[2] : "3");
    return 2;
  }
  const std::size_t bytes = mib << 20;
  std::printf("first touch of %zu MiB: seconds per round, then the median\n", mib);
  const int workers = flexsplat::global_pool().size();
  std::vector<Block> held;
  for (Mode mode : {Mode::small_pages, Mode::huge, Mode::huge_populated}) {
    std::vector<double> seconds;
    char label[64];
    std::snprintf(label, sizeof label, "%s", mode == Mode::small_pages ? "4 KiB pages:" : "huge-page advice:");
    if (mode == Mode::huge_populated) std::snprintf(label, sizeof label, "huge, populated on %d:", workers);
    std::printf("  %-26s", label);
    for (int r = 0; r < rounds; ++r) {
      Block b;
      const double s = touch_seconds(bytes, mode, b);
      held.push_back(b);
      seconds.push_back(s);
      std::printf(" %.3f", s);
    }
    std::sort(seconds.begin(), seconds.end());
    const double median = seconds[seconds.size() / 2];
    std::printf("  -> %.3f s, %.2f GB/s\n", median, static_cast<double>(bytes) / median * 1e-9);
  }
  for (Block b : held) release(b, bytes);
  return 0;
}
