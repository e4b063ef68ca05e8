#pragma once
// Aligned allocation of large buffers on transparent huge pages: weights, activations and workspaces of megabytes are
// first touched inside timed work, where each 4 KiB page fault costs microseconds (bench/memory compares both).
// Linux only; elsewhere plain aligned allocation.
#include <algorithm>
#include <cstddef>
#include <new>

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include "flexsplat/core/parallel.hpp"

namespace flexsplat {
inline namespace v0 {

// Size and alignment of a transparent huge page on x86-64 and most aarch64 kernels.
inline constexpr std::size_t huge_page_bytes = std::size_t(1) << 21;
// Buffers at least this large start on a huge-page boundary and ask the kernel for huge pages.
inline constexpr std::size_t huge_page_min_bytes = huge_page_bytes;

// Asks the kernel to back [p, p + bytes) with huge pages (MADV_HUGEPAGE): honoured when THP is "always" or "madvise",
// a no-op when it is "never". p must be page-aligned. Returns whether the advice was accepted.
inline bool advise_huge_pages(void* p, std::size_t bytes) noexcept {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  return p && bytes && ::madvise(p, bytes, MADV_HUGEPAGE) == 0;
#else
  (void)p, (void)bytes;
  return false;
#endif
}

// The alignment allocate_aligned uses for `bytes` with at least `min_alignment`.
inline std::size_t allocation_alignment(std::size_t bytes, std::size_t min_alignment) noexcept {
  return bytes >= huge_page_min_bytes && min_alignment < huge_page_bytes ? huge_page_bytes : min_alignment;
}

// `bytes` uninitialised bytes aligned to min_alignment (a power of two), large ones on huge pages. Free with
// deallocate_aligned(p, bytes, min_alignment).
inline void* allocate_aligned(std::size_t bytes, std::size_t min_alignment) {
  const std::size_t align = allocation_alignment(bytes, min_alignment);
  void* p = ::operator new(bytes, std::align_val_t{align});
  if (align == huge_page_bytes) advise_huge_pages(p, bytes);
  return p;
}

// Maps fresh, uninitialised [p, p + bytes) in, a byte written per 4 KiB page, split over the pool's workers in huge
// pages: a first touch costs a kernel zero-fill (under a VM also the host's backing) that a vector's resize pays on one
// thread (bench/memory). Returns false, touching nothing, inside a parallel region, on one worker, or while another
// thread's region runs.
inline bool populate_pages(void* p, std::size_t bytes, ThreadPool& pool = global_pool()) {
  if (!p || bytes == 0) return false;
  auto* c = static_cast<volatile char*>(p);
  const std::size_t units = (bytes + huge_page_bytes - 1) / huge_page_bytes;
  return pool.try_run_on_all([&](int worker) {
    const auto n = static_cast<std::size_t>(pool.size()), w = static_cast<std::size_t>(worker);
    const std::size_t end = std::min(bytes, units * (w + 1) / n * huge_page_bytes);
    for (std::size_t i = units * w / n * huge_page_bytes; i < end; i += 4096) c[i] = 0;
  });
}

inline void deallocate_aligned(void* p, std::size_t bytes, std::size_t min_alignment) noexcept {
  ::operator delete(p, std::align_val_t{allocation_alignment(bytes, min_alignment)});
}

}  // namespace v0
}  // namespace flexsplat
