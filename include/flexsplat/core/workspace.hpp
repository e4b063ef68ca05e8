#pragma once
// Bump allocator for activations and scratch: 64-byte aligned, mark/reset, grows only when fully reset, reports peak.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <new>
#include <span>
#include <type_traits>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/memory.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {

// Not thread-safe: give each worker its own Workspace. Memory is uninitialised.
// Overflow during a use goes to extra blocks (earlier pointers stay valid); the next full reset() replaces all blocks
// with one block of the peak size, so a repeated workload stops allocating after its first run.
class Workspace {
public:
  static constexpr std::size_t alignment = 64;

  struct Mark {
    std::size_t blocks = 0, offset = 0, used = 0;
  };

  Workspace() = default;
  explicit Workspace(std::size_t bytes) { reserve(bytes); }
  Workspace(Workspace&& other) noexcept { swap(other); }
  Workspace& operator=(Workspace&& other) noexcept {
    Workspace tmp(std::move(other));
    swap(tmp);
    return *this;
  }
  Workspace(const Workspace&) = delete;
  Workspace& operator=(const Workspace&) = delete;
  ~Workspace() {
    for (auto& b : blocks_) release(b);
  }

  // Raw aligned bytes; valid until a reset to a mark taken before this call.
  void* allocate_bytes(std::size_t bytes) {
    require(bytes <= std::numeric_limits<std::size_t>::max() - alignment, "workspace: request of ", bytes,
            " bytes is too large");
    const std::size_t rounded = round_up(bytes);
    if (blocks_.empty() || offset_ + rounded > blocks_.back().size) {
      require(growth_allowed_, "workspace: request of ", bytes, " bytes exceeds the reserved capacity of ", capacity_bytes(), " bytes (", used_,
              " in use) and growth is disabled");
      add_block(std::max(rounded, std::max(capacity_bytes(), alignment)));
    }
    std::byte* p = blocks_.back().data + offset_;
    offset_ += rounded;
    used_ += rounded;
    peak_ = std::max(peak_, used_);
    return p;
  }

  // count uninitialised elements of a trivially copyable T.
  template <class T>
  std::span<T> allocate(index_t count) {
    static_assert(std::is_trivially_copyable_v<T> && alignof(T) <= alignment, "workspace holds plain aligned data");
    require(count >= 0 && static_cast<std::uint64_t>(count) <= std::numeric_limits<std::size_t>::max() / sizeof(T),
            "workspace: invalid element count ", count);
    if (count == 0) return {};
    return {static_cast<T*>(allocate_bytes(static_cast<std::size_t>(count) * sizeof(T))),
            static_cast<std::size_t>(count)};
  }

  template <class T, std::size_t Rank>
  TensorView<T, Rank> tensor(const Shape<Rank>& shape) {
    const index_t n = checked_numel(shape);
    return TensorView<T, Rank>(allocate<T>(n).data(), shape);
  }

  Mark mark() const noexcept { return {blocks_.size(), offset_, used_}; }

  // Frees everything allocated after m; resetting to an empty mark consolidates the blocks.
  void reset(const Mark& m) {
    require(m.used <= used_ && m.blocks <= blocks_.size(), "workspace: reset to a mark that is no longer valid");
    if (m.used == 0) {
      reset();
      return;
    }
    while (blocks_.size() > m.blocks) {
      release(blocks_.back());
      blocks_.pop_back();
    }
    offset_ = m.offset;
    used_ = m.used;
  }

  void reset() {
    if (blocks_.size() > 1) {
      for (auto& b : blocks_) release(b);
      blocks_.clear();
      add_block(peak_);
    }
    offset_ = 0;
    used_ = 0;
  }

  // Ensures one block of at least bytes; only when nothing is in use.
  void reserve(std::size_t bytes) {
    require(used_ == 0, "workspace: reserve() while ", used_, " bytes are in use");
    reset();
    if (bytes == 0 || capacity_bytes() >= bytes) return;
    for (auto& b : blocks_) release(b);
    blocks_.clear();
    add_block(round_up(bytes));
  }

  // With growth off, exceeding the capacity throws: proves a kernel stays inside its reservation.
  void set_growth_allowed(bool allowed) noexcept { growth_allowed_ = allowed; }

  std::size_t used_bytes() const noexcept { return used_; }
  std::size_t peak_bytes() const noexcept { return peak_; }
  std::size_t capacity_bytes() const noexcept {
    std::size_t c = 0;
    for (auto& b : blocks_) c += b.size;
    return c;
  }
  // Heap allocations made so far: constant across repeated uses once warmed up.
  std::size_t heap_allocations() const noexcept { return heap_allocations_; }

  // Resets to the mark taken at construction when the scope ends.
  class Scope {
  public:
    explicit Scope(Workspace& ws) : ws_(ws), mark_(ws.mark()) {}
    ~Scope() { ws_.reset(mark_); }
    Scope(const Scope&) = delete;
    Scope& operator=(const Scope&) = delete;

  private:
    Workspace& ws_;
    Mark mark_;
  };

private:
  struct Block {
    std::byte* data = nullptr;
    std::size_t size = 0;
  };
  static std::size_t round_up(std::size_t bytes) { return (bytes + alignment - 1) / alignment * alignment; }
  void add_block(std::size_t bytes) {
    blocks_.reserve(blocks_.size() + 1);
    Block b;
    b.data = static_cast<std::byte*>(allocate_aligned(bytes, alignment));
    b.size = bytes;
    blocks_.push_back(b);
    offset_ = 0;
    ++heap_allocations_;
  }
  static void release(Block& b) noexcept {
    deallocate_aligned(b.data, b.size, alignment);
    b.data = nullptr;
  }
  void swap(Workspace& o) noexcept {
    std::swap(blocks_, o.blocks_);
    std::swap(offset_, o.offset_);
    std::swap(used_, o.used_);
    std::swap(peak_, o.peak_);
    std::swap(heap_allocations_, o.heap_allocations_);
    std::swap(growth_allowed_, o.growth_allowed_);
  }

  std::vector<Block> blocks_;
  std::size_t offset_ = 0;  // within blocks_.back()
  std::size_t used_ = 0;    // bytes handed out, summed over blocks
  std::size_t peak_ = 0;
  std::size_t heap_allocations_ = 0;
  bool growth_allowed_ = true;
};

}  // namespace v0
}  // namespace flexsplat
