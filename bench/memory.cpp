// First-touch cost of fresh memory with 4 KiB pages and with the huge-page advice core/memory.hpp gives large buffers.
// Usage: memory [MiB=1024] [rounds=3]. Each round maps fresh memory, writes one byte per 4 KiB page, and frees it.
#include <sys/mman.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <new>

#include "flexsplat/core/memory.hpp"

namespace {
double touch_seconds(std::size_t bytes, bool huge) {
  const auto t0 = std::chrono::steady_clock::now();
  void* p = huge ? flexsplat::allocate_aligned(bytes, 64) : ::operator new(bytes, std::align_val_t{64});
  if (!huge) ::madvise(p, bytes & ~std::size_t(4095), MADV_NOHUGEPAGE);  // 4 KiB pages even where THP is "always"
  auto* c = static_cast<volatile char*>(p);
  for (std::size_t i = 0; i < bytes; i += 4096) c[i] = 1;
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (huge) flexsplat::deallocate_aligned(p, bytes, 64);
  else ::operator delete(p, std::align_val_t{64});
  return s;
}
}  // namespace

int main(int argc, char** argv) {
  const std::size_t mib = argc > 1 ? std::strtoull(argv[1], nullptr, 10) : 1024;
  const int rounds = argc > 2 ? std::atoi(argv[2]) : 3;
  const std::size_t bytes = mib << 20;
  std::printf("first touch of %zu MiB: seconds per round, then the fastest\n", mib);
  for (bool huge : {false, true}) {
    double best = 1e30;
    std::printf("  %-26s", huge ? "huge-page advice:" : "4 KiB pages:");
    for (int r = 0; r < rounds; ++r) {
      const double s = touch_seconds(bytes, huge);
      best = s < best ? s : best;
      std::printf(" %.3f", s);
    }
    std::printf("  -> %.3f s, %.2f GB/s\n", best, static_cast<double>(bytes) / best * 1e-9);
  }
  return 0;
}
