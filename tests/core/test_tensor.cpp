#include <catch2/catch.hpp>

#include "flexsplat/core/tensor.hpp"

using namespace flexsplat;

TEST_CASE("tensor indexing, slicing and reshape agree with row-major layout", "[tensor]") {
  Tensor<float, 3> t({2, 3, 4});
  for (index_t i = 0; i < t.size(); ++i) t.data()[i] = static_cast<float>(i);
  CHECK(t(1, 2, 3) == 23.0f);
  auto row = t[1];
  CHECK(row.shape(0) == 3);
  CHECK(row(2, 3) == 23.0f);
  auto flat = t.view().reshape(Shape<2>{6, 4});
  CHECK(flat(5, 3) == 23.0f);
  CHECK(t.view().slice(1, 2).size() == 12);
  CHECK_THROWS_WITH(t.view().reshape(Shape<2>{5, 4}), Catch::Contains("cannot reshape [2, 3, 4]"));
}

TEST_CASE("tensor shapes that overflow the element count are rejected", "[tensor]") {
  CHECK_THROWS_WITH((Tensor<float, 3>({1 << 30, 1 << 30, 1 << 30})), Catch::Contains("overflows"));
  CHECK_THROWS_WITH((Tensor<float, 1>({-1})), Catch::Contains("negative"));
}

TEST_CASE("rank-1 operator[] returns a reference that writes into the tensor", "[tensor]") {
  Tensor<int, 1> t({3});
  t[1] = 5;
  CHECK(t(1) == 5);
  auto v = t.view();
  v[2] = 7;
  CHECK(t(2) == 7);
  Tensor<int, 2> m({2, 2});
  m[1][0] = 4;
  CHECK(m(1, 0) == 4);
  const Tensor<int, 1>& ct = t;
  static_assert(std::is_same_v<decltype(ct[0]), const int&>);
}

TEST_CASE("copy_of gathers a strided view and slices are bounds-checked", "[tensor]") {
  Tensor<float, 2> t({3, 4});
  for (index_t i = 0; i < t.size(); ++i) t.data()[i] = static_cast<float>(i);
  TensorView<float, 2> transposed(t.data(), Shape<2>{4, 3}, Shape<2>{1, 4});
  CHECK_FALSE(transposed.is_contiguous());
  CHECK_THROWS_WITH(transposed.span(), Catch::Contains("not contiguous"));
  const auto c = copy_of(transposed);
  for (index_t i = 0; i < 4; ++i)
    for (index_t j = 0; j < 3; ++j) CHECK(c(i, j) == t(j, i));
  CHECK_THROWS_WITH(t.view().slice(2, 4), Catch::Contains("slice [2, 4) out of range for shape [3, 4]"));
  TensorView<const float, 2> as_const = t.view();
  CHECK(as_const(2, 3) == 11.0f);
  Tensor<float, 2> empty({0, 5});
  CHECK(empty.empty());
  CHECK(copy_of(empty.view()).shape() == Shape<2>{0, 5});
}
