#include <catch2/catch.hpp>

#include <cstdio>
#include <filesystem>
#include <string>

#include "flexsplat/raster/reference.hpp"

using namespace flexsplat;

TEST_CASE("reference: raster_31337 bundle passes at the float32 tolerances", "[raster][reference]") {
  const auto file = safetensors::File::open(std::string(FLEXSPLAT_SHARED_DIR) + "/reference/raster_31337.safetensors");
  ReferenceReport report;
  raster::check_raster_bundle(file, report);
  report.print(stdout);
  CHECK(report.rows.size() == 5 * 10);
  CHECK(report.all_pass());
}

TEST_CASE("reference: a bundle tensor the raster checker does not know fails the check", "[raster][reference]") {
  const auto file = safetensors::File::open(std::string(FLEXSPLAT_SHARED_DIR) + "/reference/raster_31337.safetensors");
  safetensors::Writer w;
  for (const auto& [key, value] : file.metadata()) w.set_metadata(key, value);
  for (const auto& t : file.tensors()) w.add_raw(t.name, t.dtype, t.shape, file.bytes(t), t.end - t.begin);
  w.add("case0.d_features", Tensor<float, 1>({2}, 1.f));  // an expected gradient the checker has no counterpart for
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_raster_unknown.safetensors";
  w.write(path);
  const auto extended = safetensors::File::open(path);
  ReferenceReport report;
  raster::check_raster_bundle(extended, report);
  std::filesystem::remove(path);
  CHECK_FALSE(report.all_pass());
  bool flagged = false;
  for (const auto& r : report.rows)
    flagged = flagged || (r.name == "case0.d_features" && !r.pass && r.note.find("not understood") != std::string::npos);
  CHECK(flagged);
}
