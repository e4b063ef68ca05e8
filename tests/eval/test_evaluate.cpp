// The evaluation protocol's options: eval's --views text (a view count, or the input frames in order).
#include <catch2/catch.hpp>

#include <vector>

#include "flexsplat/eval/evaluate.hpp"

using namespace flexsplat;

TEST_CASE("set_views: a count, frames in order, one frame with a trailing comma, anything else refused",
          "[model][evaluate]") {
  model::EvalOptions o;
  model::set_views(o, "4");
  CHECK(o.view_count == 4);
  CHECK(o.view_list.empty());
  model::set_views(o, "9,26,3");
  CHECK(o.view_count == 0);
  CHECK(o.view_list == std::vector<int>{9, 26, 3});
  model::set_views(o, "9,");
  CHECK(o.view_list == std::vector<int>{9});
  model::set_views(o, "0,0");
  CHECK(o.view_list == std::vector<int>{0, 0});
  for (const char* bad : {"", ",", "9,,3", "x", "4x", "9,-2", ",9"})
    CHECK_THROWS_WITH(model::set_views(o, bad), Catch::Contains("expected a view count or comma-separated frame indices"));
  CHECK_THROWS_WITH(model::set_views(o, "0"), Catch::Contains("need at least one input view"));
}
