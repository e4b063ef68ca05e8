#include <catch2/catch.hpp>

#include <filesystem>

#include "flexsplat/io/safetensors.hpp"

using namespace flexsplat;

TEST_CASE("safetensors round trip keeps values, dtypes and metadata", "[safetensors]") {
  Tensor<double, 2> a({3, 2});
  for (index_t i = 0; i < a.size(); ++i) a.data()[i] = 0.5 * static_cast<double>(i) - 1.0;
  safetensors::Writer w;
  w.set_metadata("kind", "test");
  w.add("a", a);
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_test_roundtrip.safetensors";
  w.write(path);
  const auto f = safetensors::File::open(path);
  CHECK(f.metadata("kind") == "test");
  const auto back = f.get<float, 2>("a");
  CHECK(back(2, 1) == Approx(1.5));
  const auto view = f.view<double, 2>("a");
  CHECK(view(0, 0) == -1.0);
  CHECK_THROWS_WITH((f.get<float, 3>("a")), Catch::Contains("expected rank 3"));
  CHECK_THROWS_WITH((f.get<float, 2>("missing")), Catch::Contains("no tensor 'missing'"));
  std::filesystem::remove(path);
}
