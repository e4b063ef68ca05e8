#include <catch2/catch.hpp>

#include <cstdio>

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
