#pragma once
// N-d tensors with compile-time element type and rank: TensorView (non-owning, strided) and Tensor (owning, contiguous).
#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <new>
#include <span>
#include <string>
#include <type_traits>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/index.hpp"
#include "flexsplat/core/memory.hpp"

namespace flexsplat {
inline namespace v0 {

template <std::size_t Rank>
using Shape = std::array<index_t, Rank>;

template <std::size_t Rank>
std::string shape_string(const Shape<Rank>& shape) {
  std::string s = "[";
  for (std::size_t i = 0; i < Rank; ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + "]";
}

// Number of elements; throws instead of overflowing or accepting negative extents.
template <std::size_t Rank>
index_t checked_numel(const Shape<Rank>& shape) {
  index_t n = 1;
  for (index_t extent : shape) {
    if (!(extent >= 0)) fail("tensor shape ", shape_string(shape), " has a negative extent");
    if (!(extent == 0 || n <= std::numeric_limits<index_t>::max() / extent)) fail("tensor shape ",
            shape_string(shape), " overflows the element count");
    n *= extent;
  }
  return n;
}

template <std::size_t Rank>
Shape<Rank> contiguous_strides(const Shape<Rank>& shape) {
  Shape<Rank> strides{};
  index_t s = 1;
  for (std::size_t i = Rank; i-- > 0;) {
    strides[i] = s;
    s *= shape[i];
  }
  return strides;
}

template <class T, std::size_t Rank>
class TensorView {
public:
  static_assert(Rank >= 1, "rank-0 tensors are plain values");
  using value_type = std::remove_const_t<T>;
  static constexpr std::size_t rank = Rank;

  TensorView() = default;
  TensorView(T* data, const Shape<Rank>& shape) : data_(data), shape_(shape), strides_(contiguous_strides(shape)) {
    checked_numel(shape);
  }
  TensorView(T* data, const Shape<Rank>& shape, const Shape<Rank>& strides)
      : data_(data), shape_(shape), strides_(strides) {}
  // A view of T converts to a view of const T.
  template <class U, class = std::enable_if_t<std::is_same_v<const U, T> && !std::is_same_v<U, T>>>
  TensorView(const TensorView<U, Rank>& other) : data_(other.data()), shape_(other.shape()), strides_(other.strides()) {}

  T* data() const noexcept { return data_; }
  const Shape<Rank>& shape() const noexcept { return shape_; }
  const Shape<Rank>& strides() const noexcept { return strides_; }
  index_t shape(std::size_t axis) const noexcept { return shape_[axis]; }
  index_t size() const noexcept {
    index_t n = 1;
    for (index_t e : shape_) n *= e;
    return n;
  }
  bool empty() const noexcept { return size() == 0; }
  bool is_contiguous() const noexcept {
    index_t s = 1;
    for (std::size_t i = Rank; i-- > 0;) {
      if (shape_[i] != 1 && strides_[i] != s) return false;
      s *= shape_[i];
    }
    return true;
  }

  template <class... I>
  T& operator()(I... idx) const noexcept {
    static_assert(sizeof...(I) == Rank, "index count must equal the rank");
    const index_t ids[] = {static_cast<index_t>(idx)...};
    index_t off = 0;
    for (std::size_t i = 0; i < Rank; ++i) off += ids[i] * strides_[i];
    return data_[off];
  }

  // Raw span over the elements; only for contiguous views (hot loops run on these).
  std::span<T> span() const {
    if (!(is_contiguous())) fail("tensor view ", shape_string(shape_), " is not contiguous");
    return {data_, static_cast<std::size_t>(size())};
  }

  // Slice along the first axis: a view of rank - 1, or a reference to the element for rank 1.
  decltype(auto) operator[](index_t i) const {
    if constexpr (Rank == 1) {
      return (data_[i * strides_[0]]);
    } else {
      Shape<Rank - 1> s{}, st{};
      for (std::size_t k = 1; k < Rank; ++k) {
        s[k - 1] = shape_[k];
        st[k - 1] = strides_[k];
      }
      return TensorView<T, Rank - 1>(data_ + i * strides_[0], s, st);
    }
  }

  // Contiguous range [begin, end) of the first axis.
  TensorView slice(index_t begin, index_t end) const {
    if (!(0 <= begin && begin <= end && end <= shape_[0])) fail("slice [", begin, ", ", end, ") out of range for shape ",
            shape_string(shape_));
    Shape<Rank> s = shape_;
    s[0] = end - begin;
    return TensorView(data_ + begin * strides_[0], s, strides_);
  }

  template <std::size_t NewRank>
  TensorView<T, NewRank> reshape(const Shape<NewRank>& new_shape) const {
    if (!(is_contiguous())) fail("reshape of a non-contiguous view ", shape_string(shape_));
    if (!(checked_numel(new_shape) == size())) fail("cannot reshape ", shape_string(shape_), " to ",
            shape_string(new_shape));
    return TensorView<T, NewRank>(data_, new_shape);
  }

private:
  T* data_ = nullptr;
  Shape<Rank> shape_{};
  Shape<Rank> strides_{};
};

// Cache-line aligned so SIMD loads on tensor rows never straddle lines by construction; buffers of megabytes go on
// huge pages (core/memory.hpp).
template <class T>
struct AlignedAllocator {
  using value_type = T;
  static constexpr std::size_t alignment = 64;
  AlignedAllocator() = default;
  template <class U>
  AlignedAllocator(const AlignedAllocator<U>&) noexcept {}
  T* allocate(std::size_t n) {
    if (n > std::numeric_limits<std::size_t>::max() / sizeof(T)) throw std::bad_array_new_length();
    void* p = allocate_aligned(n * sizeof(T), alignment);
    if (n * sizeof(T) >= huge_page_min_bytes) populate_pages(p, n * sizeof(T));  // resize() then writes mapped pages
    return static_cast<T*>(p);
  }
  void deallocate(T* p, std::size_t n) noexcept { deallocate_aligned(p, n * sizeof(T), alignment); }
  template <class U>
  bool operator==(const AlignedAllocator<U>&) const noexcept { return true; }
};

// Caches and workspaces: a megabyte-sized std::vector<T> would be first touched 4 KiB page by page.
template <class T>
using AlignedVector = std::vector<T, AlignedAllocator<T>>;

template <class T, std::size_t Rank>
class Tensor {
public:
  using value_type = T;
  static constexpr std::size_t rank = Rank;

  Tensor() = default;
  explicit Tensor(const Shape<Rank>& shape, T fill = T{})
      : shape_(shape), storage_(static_cast<std::size_t>(checked_numel(shape)), fill) {}

  T* data() noexcept { return storage_.data(); }
  const T* data() const noexcept { return storage_.data(); }
  const Shape<Rank>& shape() const noexcept { return shape_; }
  index_t shape(std::size_t axis) const noexcept { return shape_[axis]; }
  index_t size() const noexcept { return static_cast<index_t>(storage_.size()); }
  bool empty() const noexcept { return storage_.empty(); }

  TensorView<T, Rank> view() noexcept { return {data(), shape_}; }
  TensorView<const T, Rank> view() const noexcept { return {data(), shape_}; }
  operator TensorView<T, Rank>() noexcept { return view(); }
  operator TensorView<const T, Rank>() const noexcept { return view(); }
  std::span<T> span() noexcept { return {storage_.data(), storage_.size()}; }
  std::span<const T> span() const noexcept { return {storage_.data(), storage_.size()}; }

  template <class... I>
  T& operator()(I... idx) noexcept { return view()(idx...); }
  template <class... I>
  const T& operator()(I... idx) const noexcept { return view()(idx...); }
  decltype(auto) operator[](index_t i) noexcept { return view()[i]; }
  decltype(auto) operator[](index_t i) const noexcept { return view()[i]; }

  void fill(T value) noexcept { std::fill(storage_.begin(), storage_.end(), value); }
  void resize(const Shape<Rank>& shape) {
    shape_ = shape;
    storage_.assign(static_cast<std::size_t>(checked_numel(shape)), T{});
  }

private:
  Shape<Rank> shape_{};
  std::vector<T, AlignedAllocator<T>> storage_;
};

template <class T, std::size_t Rank>
Tensor<std::remove_const_t<T>, Rank> copy_of(TensorView<T, Rank> src) {
  Tensor<std::remove_const_t<T>, Rank> out(src.shape());
  if (src.is_contiguous()) {
    std::copy(src.data(), src.data() + src.size(), out.data());
    return out;
  }
  Shape<Rank> idx{};
  for (index_t n = 0; n < out.size(); ++n) {
    index_t off = 0;
    for (std::size_t i = 0; i < Rank; ++i) off += idx[i] * src.strides()[i];
    out.data()[n] = src.data()[off];
    for (std::size_t i = Rank; i-- > 0;) {
      if (++idx[i] < src.shape()[i]) break;
      idx[i] = 0;
    }
  }
  return out;
}

}  // namespace v0
}  // namespace flexsplat
