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
