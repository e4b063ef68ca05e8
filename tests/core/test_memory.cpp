#include <catch2/catch.hpp>

#include <cstdint>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#include <unistd.h>
#endif

#include "flexsplat/core/memory.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/tensor.hpp"
#include "skip.hpp"

using namespace flexsplat;

namespace {
// The VmFlags line of the mapping in /proc/self/smaps that holds address p ("" if none).
std::string vm_flags_of(const void* p) {
  std::ifstream smaps("/proc/self/smaps");
  const auto a = reinterpret_cast<std::uintptr_t>(p);
  std::string line;
  bool inside = false;
  while (std::getline(smaps, line)) {
    std::uintptr_t lo = 0, hi = 0;
    char dash = 0;
    std::istringstream head(line);
    if (head >> std::hex >> lo >> dash >> hi && dash == '-') inside = lo <= a && a < hi;
    else if (inside && line.rfind("VmFlags:", 0) == 0) return line;
  }
  return "";
}
}  // namespace

TEST_CASE("memory: large buffers start on a huge page and carry the huge-page advice", "[core][memory]") {
  const std::size_t bytes = 3 * huge_page_bytes + 4096;
  void* p = allocate_aligned(bytes, 64);
  CHECK(reinterpret_cast<std::uintptr_t>(p) % huge_page_bytes == 0);
  static_cast<char*>(p)[bytes - 1] = 1;  // the whole range is usable
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  const std::string flags = vm_flags_of(p);
  INFO(flags);
  // VM_HUGEPAGE ("hg") unless the kernel refuses the advice (no THP support): then advising again must fail too.
  if (flags.find(" hg") == std::string::npos) CHECK_FALSE(advise_huge_pages(p, bytes));
#endif
  deallocate_aligned(p, bytes, 64);
}

TEST_CASE("memory: small buffers keep their own alignment", "[core][memory]") {
  CHECK(allocation_alignment(huge_page_min_bytes - 1, 64) == 64);
  CHECK(allocation_alignment(huge_page_min_bytes, 64) == huge_page_bytes);
  CHECK(allocation_alignment(huge_page_min_bytes, std::size_t(1) << 22) == std::size_t(1) << 22);
  void* p = allocate_aligned(1000, 64);
  CHECK(reinterpret_cast<std::uintptr_t>(p) % 64 == 0);
  deallocate_aligned(p, 1000, 64);
}

TEST_CASE("memory: AlignedAllocator vectors grow across the huge-page threshold", "[core][memory]") {
  std::vector<float, AlignedAllocator<float>> v;
  for (std::size_t n : {std::size_t(100), huge_page_bytes / sizeof(float) + 1, std::size_t(10)}) {
    v.resize(n, 2.0f);
    v.shrink_to_fit();
    CHECK(reinterpret_cast<std::uintptr_t>(v.data()) % 64 == 0);
    CHECK(v.back() == 2.0f);
  }
  AlignedAllocator<double> a;
  CHECK_THROWS_AS(a.allocate(std::numeric_limits<std::size_t>::max() / 4), std::bad_array_new_length);
}

#if defined(__linux__)
namespace {
// Pages of [p, p + bytes) the kernel has mapped in (mincore).
std::size_t resident_pages(void* p, std::size_t bytes) {
  const auto page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
  std::vector<unsigned char> in((bytes + page - 1) / page);
  if (::mincore(p, bytes, in.data()) != 0) return 0;
  std::size_t n = 0;
  for (unsigned char c : in) n += c & 1u;
  return n;
}
}  // namespace

TEST_CASE("memory: populate_pages maps a fresh range in on the pool's workers, and declines on one", "[core][memory]") {
  const auto page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
  const std::size_t bytes = 5 * huge_page_bytes + 3 * page, pages = bytes / page;
  for (int threads : {1, 2, 3}) {
    INFO(threads << " workers");
    ThreadPool pool(threads);
    void* p = ::mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    REQUIRE(p != MAP_FAILED);
    REQUIRE(resident_pages(p, bytes) == 0);
    const bool done = populate_pages(p, bytes, pool);
    CHECK(done == (threads > 1));
    CHECK(resident_pages(p, bytes) == (done ? pages : 0));
    ::munmap(p, bytes);
  }
}

TEST_CASE("memory: a large AlignedAllocator vector is mapped in before its elements are written", "[core][memory]") {
  // populated only where the global pool can run (more than one worker, no region running)
  if (global_pool().size() <= 1) FLEXSPLAT_SKIP("one-worker global pool: AlignedAllocator does not populate");
  AlignedAllocator<float> a;
  const std::size_t n = 3 * huge_page_bytes / sizeof(float);
  float* p = a.allocate(n);
  const auto page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
  CHECK(resident_pages(p, n * sizeof(float)) == n * sizeof(float) / page);
  a.deallocate(p, n);
}
#endif
