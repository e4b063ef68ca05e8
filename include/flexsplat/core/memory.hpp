#pragma once
// Aligned allocation of large buffers on transparent huge pages: weights, activations and workspaces of megabytes are
// first touched inside timed work, where each 4 KiB page fault costs microseconds (bench/memory compares both).
// Linux only; elsewhere plain aligned allocation.
#include <cstddef>
#include <new>

#if defined(__linux__)
#include <sys/mman.h>
#endif

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

inline void deallocate_aligned(void* p, std::size_t bytes, std::size_t min_alignment) noexcept {
  ::operator delete(p, std::align_val_t{allocation_alignment(bytes, min_alignment)});
}

}  // namespace v0
}  // namespace flexsplat
