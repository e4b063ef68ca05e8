#pragma once
// Zero-copy bridges between TensorView (rank 1 and 2) and Eigen::Map with run-time strides.
#include <Eigen/Core>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {

template <class T>
using EigenVector = Eigen::Matrix<std::remove_const_t<T>, Eigen::Dynamic, 1>;
template <class T>
using EigenRowMatrix = Eigen::Matrix<std::remove_const_t<T>, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Const-ness of T carries over to the Map.
template <class T>
using EigenVectorMap =
    Eigen::Map<std::conditional_t<std::is_const_v<T>, const EigenVector<T>, EigenVector<T>>, 0, Eigen::InnerStride<>>;
template <class T>
using EigenMatrixMap = Eigen::Map<std::conditional_t<std::is_const_v<T>, const EigenRowMatrix<T>, EigenRowMatrix<T>>,
                                  0, Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>>;

namespace detail {
inline void require_eigen_strides(index_t outer, index_t inner) {
  require(outer >= 0 && inner >= 0, "Eigen maps need non-negative strides, got [", outer, ", ", inner, "]");
}
}  // namespace detail

template <class T>
EigenVectorMap<T> as_eigen(TensorView<T, 1> v) {
  detail::require_eigen_strides(0, v.strides()[0]);
  return EigenVectorMap<T>(v.data(), v.shape(0), Eigen::InnerStride<>(v.strides()[0]));
}

// Row-major map: element (i, j) of the Map is v(i, j), whatever the view's strides.
template <class T>
EigenMatrixMap<T> as_eigen(TensorView<T, 2> v) {
  detail::require_eigen_strides(v.strides()[0], v.strides()[1]);
  return EigenMatrixMap<T>(v.data(), v.shape(0), v.shape(1),
                           Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>(v.strides()[0], v.strides()[1]));
}

template <class T, std::size_t Rank>
auto as_eigen(Tensor<T, Rank>& t) { return as_eigen(t.view()); }
template <class T, std::size_t Rank>
auto as_eigen(const Tensor<T, Rank>& t) { return as_eigen(t.view()); }

// A rank-2 view of any Eigen matrix or Map with direct access (column- or row-major, any strides).
template <class Derived>
auto view_of(Eigen::DenseBase<Derived>& m) {
  using Scalar = typename Derived::Scalar;
  using Elem = std::conditional_t<bool(Eigen::internal::traits<Derived>::Flags & Eigen::LvalueBit), Scalar,
                                  const Scalar>;
  static_assert(bool(Eigen::internal::traits<Derived>::Flags & Eigen::DirectAccessBit),
                "view_of needs an Eigen object with direct memory access");
  Derived& d = m.derived();
  const index_t inner = d.innerStride(), outer = d.outerStride();
  const Shape<2> strides = Derived::IsRowMajor ? Shape<2>{outer, inner} : Shape<2>{inner, outer};
  return TensorView<Elem, 2>(const_cast<Elem*>(d.data()), Shape<2>{d.rows(), d.cols()}, strides);
}
template <class Derived>
auto view_of(const Eigen::DenseBase<Derived>& m) {
  using Scalar = typename Derived::Scalar;
  static_assert(bool(Eigen::internal::traits<Derived>::Flags & Eigen::DirectAccessBit),
                "view_of needs an Eigen object with direct memory access");
  const Derived& d = m.derived();
  const index_t inner = d.innerStride(), outer = d.outerStride();
  const Shape<2> strides = Derived::IsRowMajor ? Shape<2>{outer, inner} : Shape<2>{inner, outer};
  return TensorView<const Scalar, 2>(d.data(), Shape<2>{d.rows(), d.cols()}, strides);
}

}  // namespace v0
}  // namespace flexsplat
