#pragma once
// Zero-copy bridges between TensorView and xtensor: xt::adapt over a view's memory, and views of xtensor containers.
#include <array>
#include <cstddef>

#include <xtensor/xadapt.hpp>
#include <xtensor/xtensor.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {

// Row-major xtensor adaptor that reads and writes the view's elements in place; the view must be contiguous.
template <class T, std::size_t Rank>
auto as_xtensor(TensorView<T, Rank> v) {
  require(v.is_contiguous(), "as_xtensor needs a contiguous view, got shape ", shape_string(v.shape()), " strides ",
          shape_string(v.strides()));
  std::array<std::size_t, Rank> shape{};
  for (std::size_t i = 0; i < Rank; ++i) shape[i] = static_cast<std::size_t>(v.shape(i));
  return xt::adapt(v.data(), static_cast<std::size_t>(v.size()), xt::no_ownership(), shape);
}

template <class T, std::size_t Rank>
auto as_xtensor(Tensor<T, Rank>& t) { return as_xtensor(t.view()); }
template <class T, std::size_t Rank>
auto as_xtensor(const Tensor<T, Rank>& t) { return as_xtensor(t.view()); }

// A view of an xtensor container (or adaptor) with its own strides; it aliases the container's memory.
template <class E>
auto view_of_xtensor(E& e) {
  using Elem = std::remove_reference_t<decltype(*e.data())>;
  constexpr std::size_t Rank = std::tuple_size_v<std::decay_t<decltype(e.shape())>>;
  Shape<Rank> shape{}, strides{};
  for (std::size_t i = 0; i < Rank; ++i) {
    shape[i] = static_cast<index_t>(e.shape()[i]);
    strides[i] = static_cast<index_t>(e.shape()[i] == 1 ? 0 : e.strides()[i]);
  }
  // xtensor reports stride 0 on unit axes; any value works there, so use the contiguous one.
  const Shape<Rank> contiguous = contiguous_strides(shape);
  for (std::size_t i = 0; i < Rank; ++i)
    if (shape[i] == 1) strides[i] = contiguous[i];
  return TensorView<Elem, Rank>(e.data() + e.data_offset(), shape, strides);
}

}  // namespace v0
}  // namespace flexsplat
