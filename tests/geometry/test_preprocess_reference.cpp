#include <catch2/catch.hpp>

#include <filesystem>
#include <string>

#include <unistd.h>

#include "flexsplat/geometry/preprocess_reference.hpp"

using namespace flexsplat;

namespace {

const std::string bundle_dir = std::string(FLEXSPLAT_SHARED_DIR) + "/reference/preprocess";
const std::string bundle_path = bundle_dir + "/preprocess_reference.safetensors";

// Copy of the shared bundle with absolute file paths and tensor `victim` changed by `edit`.
template <class Edit>
std::string edited_bundle(const std::string& victim, Edit edit, const std::string& files_json = "") {
  const auto src = safetensors::File::open(bundle_path);
  safetensors::Writer w;
  for (const auto& [k, v] : src.metadata()) w.set_metadata(k, v);
  std::string files = "[";
  for (const char* f : {"square_rgba.png", "wide_rgb.png", "tall_rgba.png"})
    files += std::string(files.size() > 1 ? ", " : "") + "\"" + bundle_dir + "/" + f + "\"";
  w.set_metadata("files", files_json.empty() ? files + "]" : files_json);
  for (const auto& t : src.tensors()) {
    auto data = src.get<std::uint8_t, 4>(t.name);
    if (t.name == victim) edit(data);
    w.add(t.name, data);
  }
  const auto path = std::filesystem::temp_directory_path() /
                    ("flexsplat_preprocess_bundle_" + std::to_string(::getpid()) + "_" + victim + ".safetensors");
  w.write(path);
  return path.string();
}

const TensorComparison& row(const ReferenceReport& r, const std::string& name) {
  for (const auto& x : r.rows)
    if (x.name == name) return x;
  FAIL("no row " << name);
  return r.rows.front();
}

}  // namespace

TEST_CASE("preprocess reference bundle: exact match on the shared files", "[preprocess][reference]") {
  const auto bundle = safetensors::File::open(bundle_path);
  ReferenceReport report;
  check_preprocess_reference(bundle, report);
  REQUIRE(report.rows.size() == 8);
  for (const auto& r : report.rows) {
    INFO(r.name << " " << r.note);
    CHECK(r.pass);
    CHECK(r.max_abs_error == 0.0);
  }
}

TEST_CASE("preprocess reference checker fails when it should", "[preprocess][reference]") {
  SECTION("one value off by 2") {
    const auto path = edited_bundle("crop.single1", [](Tensor<std::uint8_t, 4>& t) {
      t(0, 1, 100, 100) = static_cast<std::uint8_t>(t(0, 1, 100, 100) < 128 ? t(0, 1, 100, 100) + 2 : t(0, 1, 100, 100) - 2);
    });
    ReferenceReport report;
    check_preprocess_reference(safetensors::File::open(path), report);
    CHECK_FALSE(row(report, "crop.single1").pass);
    CHECK(row(report, "crop.single1").max_abs_error == 2.0);
    CHECK(row(report, "pad.all").pass);
    std::filesystem::remove(path);
  }
  SECTION("every value off by 1: max within tolerance, mean is not") {
    const auto path = edited_bundle("pad.all", [](Tensor<std::uint8_t, 4>& t) {
      for (auto& v : t.span()) v = static_cast<std::uint8_t>(v < 128 ? v + 1 : v - 1);
    });
    ReferenceReport report;
    check_preprocess_reference(safetensors::File::open(path), report);
    const auto& r = row(report, "pad.all");
    CHECK(r.max_abs_error == 1.0);
    CHECK_FALSE(r.pass);
    CHECK_THAT(r.note, Catch::Contains("mean_abs 1"));
    std::filesystem::remove(path);
  }
  SECTION("files in another order: shapes or values no longer match") {
    const auto path = edited_bundle("none", [](Tensor<std::uint8_t, 4>&) {},
                                    "[\"" + bundle_dir + "/wide_rgb.png\", \"" + bundle_dir + "/square_rgba.png\", \"" +
                                        bundle_dir + "/tall_rgba.png\"]");
    ReferenceReport report;
    check_preprocess_reference(safetensors::File::open(path), report);
    CHECK_FALSE(row(report, "crop.single0").pass);
    CHECK_FALSE(row(report, "crop.all").pass);
    CHECK(row(report, "crop.single2").pass);
    std::filesystem::remove(path);
  }
  SECTION("a missing file is an error naming it") {
    const auto path = edited_bundle("none", [](Tensor<std::uint8_t, 4>&) {}, "[\"no_such_file.png\"]");
    ReferenceReport report;
    CHECK_THROWS_WITH(check_preprocess_reference(safetensors::File::open(path), report),
                      Catch::Contains("no_such_file.png"));
    std::filesystem::remove(path);
  }
}
