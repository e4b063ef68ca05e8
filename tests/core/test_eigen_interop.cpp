#include <catch2/catch.hpp>

#include "flexsplat/core/eigen_interop.hpp"

using namespace flexsplat;

TEST_CASE("as_eigen maps a contiguous rank-2 view without copying", "[interop]") {
  Tensor<float, 2> t({3, 4});
  for (index_t i = 0; i < t.size(); ++i) t.data()[i] = static_cast<float>(i);
  auto m = as_eigen(t);
  CHECK(m.data() == t.data());
  CHECK(m.rows() == 3);
  CHECK(m.cols() == 4);
  CHECK(m(2, 1) == t(2, 1));
  m(1, 3) = -5.0f;  // writes land in the tensor
  CHECK(t(1, 3) == -5.0f);
  m.row(0).setConstant(2.0f);
  CHECK(t(0, 0) == 2.0f);
  CHECK(t(0, 3) == 2.0f);
  const Tensor<float, 2>& ct = t;
  auto cm = as_eigen(ct);
  CHECK(cm.sum() == Approx(m.sum()));
}

TEST_CASE("as_eigen honours strides of transposed-like and sliced views", "[interop]") {
  Tensor<double, 2> t({4, 6});
  for (index_t i = 0; i < t.size(); ++i) t.data()[i] = static_cast<double>(i);
  // Column 2 of t as a rank-1 view with stride 6.
  TensorView<double, 1> column(t.data() + 2, Shape<1>{4}, Shape<1>{6});
  auto v = as_eigen(column);
  CHECK(v.size() == 4);
  CHECK(v(3) == t(3, 2));
  v(1) = 100.0;
  CHECK(t(1, 2) == 100.0);
  // The transpose of t as a 6x4 view with swapped strides.
  TensorView<double, 2> transposed(t.data(), Shape<2>{6, 4}, Shape<2>{1, 6});
  auto mt = as_eigen(transposed);
  CHECK(mt(5, 3) == t(3, 5));
  CHECK((mt.transpose() - as_eigen(t)).cwiseAbs().maxCoeff() == 0.0);
  // Every other column.
  TensorView<double, 2> every_other(t.data(), Shape<2>{4, 3}, Shape<2>{6, 2});
  as_eigen(every_other).setZero();
  CHECK(t(3, 4) == 0.0);
  CHECK(t(3, 5) == 23.0);
  TensorView<double, 1> backwards(t.data() + 5, Shape<1>{6}, Shape<1>{-1});
  CHECK_THROWS_WITH(as_eigen(backwards), Catch::Contains("non-negative strides"));
}

TEST_CASE("view_of sees Eigen matrices of both storage orders in place", "[interop]") {
  Eigen::MatrixXf col_major(3, 2);
  col_major << 1, 2, 3, 4, 5, 6;
  auto v = view_of(col_major);
  CHECK(v.shape() == Shape<2>{3, 2});
  CHECK(v(2, 1) == 6.0f);
  v(0, 1) = 9.0f;
  CHECK(col_major(0, 1) == 9.0f);
  Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> row_major = col_major;
  auto rv = view_of(row_major);
  CHECK(rv.is_contiguous());
  CHECK(rv(2, 0) == 5.0f);
  const Eigen::MatrixXf& ccol = col_major;
  auto cv = view_of(ccol);
  static_assert(std::is_same_v<decltype(cv), TensorView<const float, 2>>);
  CHECK(cv(1, 0) == 3.0f);
  // Round trip: Tensor -> Map -> view gives the same strides.
  Tensor<float, 2> t({2, 5});
  auto map = as_eigen(t);
  auto back = view_of(map);
  CHECK(back.data() == t.data());
  CHECK(back.strides() == t.view().strides());
}
