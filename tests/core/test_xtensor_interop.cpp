#include <catch2/catch.hpp>

#include <xtensor/xmath.hpp>
#include <xtensor/xview.hpp>

#include "flexsplat/core/xtensor_interop.hpp"

using namespace flexsplat;

TEST_CASE("as_xtensor adapts a tensor in place: writes through the adaptor land in the tensor", "[interop]") {
  Tensor<float, 3> t({2, 3, 4});
  for (index_t i = 0; i < t.size(); ++i) t.data()[i] = static_cast<float>(i);
  auto x = as_xtensor(t);
  CHECK(x.data() == t.data());
  CHECK(x.dimension() == 3);
  CHECK(x(1, 2, 3) == t(1, 2, 3));
  x(0, 1, 2) = -7.0f;
  CHECK(t(0, 1, 2) == -7.0f);
  x += 1.0f;
  CHECK(t(1, 2, 3) == 24.0f);
  xt::view(x, 1, xt::all(), xt::all()) = 0.0f;
  CHECK(t(1, 0, 0) == 0.0f);
  CHECK(t(0, 0, 0) == 1.0f);
  CHECK(xt::sum(x)() == 65.0f);  // 0..11 with 6 replaced by -7, plus 1 each; second half zero
}

TEST_CASE("as_xtensor refuses non-contiguous views", "[interop]") {
  Tensor<double, 2> t({4, 6});
  TensorView<double, 2> every_other(t.data(), Shape<2>{4, 3}, Shape<2>{6, 2});
  CHECK_THROWS_WITH(as_xtensor(every_other), Catch::Contains("contiguous"));
}

TEST_CASE("view_of_xtensor aliases an xtensor container", "[interop]") {
  xt::xtensor<double, 2> a = {{1.0, 2.0, 3.0}, {4.0, 5.0, 6.0}};
  auto v = view_of_xtensor(a);
  CHECK(v.shape() == Shape<2>{2, 3});
  CHECK(v.is_contiguous());
  v(1, 2) = 60.0;
  CHECK(a(1, 2) == 60.0);
  xt::xtensor<double, 2, xt::layout_type::column_major> c = a;
  auto cv = view_of_xtensor(c);
  CHECK(cv(1, 0) == 4.0);
  CHECK(cv.strides() == Shape<2>{1, 2});
  xt::xtensor<float, 3> unit = xt::zeros<float>({1, 3, 1});
  CHECK(view_of_xtensor(unit).is_contiguous());
}
