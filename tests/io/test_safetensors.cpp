#include <catch2/catch.hpp>

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "flexsplat/io/safetensors.hpp"

using namespace flexsplat;

namespace {

std::filesystem::path temp_path(const std::string& name) {
  return std::filesystem::temp_directory_path() / ("flexsplat_test_st_" + std::to_string(::getpid()) + "_" + name);
}

// Writes 8-byte length + header + data exactly as given, so the length can lie.
std::filesystem::path write_raw(const std::string& name, const std::string& header, std::size_t data_bytes,
                                std::uint64_t header_len) {
  const auto path = temp_path(name);
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(&header_len), 8);
  out.write(header.data(), static_cast<std::streamsize>(header.size()));
  std::vector<char> data(data_bytes, 0);
  out.write(data.data(), static_cast<std::streamsize>(data.size()));
  return path;
}
std::filesystem::path write_raw(const std::string& name, const std::string& header, std::size_t data_bytes) {
  return write_raw(name, header, data_bytes, header.size());
}

// Opening must fail with a message naming the file and containing every fragment.
void expect_rejected(const std::filesystem::path& path, const std::vector<std::string>& fragments) {
  INFO("file " << path.string());
  try {
    (void)safetensors::File::open(path);
    FAIL("opened a corrupt file without an error");
  } catch (const Error& e) {
    const std::string message = e.what();
    INFO("message: " << message);
    CHECK(message.find(path.string()) != std::string::npos);
    for (auto& f : fragments) CHECK(message.find(f) != std::string::npos);
  }
  std::filesystem::remove(path);
}

}  // namespace

TEST_CASE("safetensors round trip keeps values, dtypes and metadata", "[safetensors]") {
  Tensor<double, 2> a({3, 2});
  for (index_t i = 0; i < a.size(); ++i) a.data()[i] = 0.5 * static_cast<double>(i) - 1.0;
  Tensor<std::int64_t, 1> ids({4});
  for (index_t i = 0; i < 4; ++i) ids(i) = -2 + i;
  Tensor<std::uint8_t, 1> bytes({3});
  bytes(0) = 0; bytes(1) = 128; bytes(2) = 255;
  Tensor<f16, 1> halves({2});
  halves(0) = f16(0.5f); halves(1) = f16(-3.0f);
  Tensor<bf16, 1> brains({2});
  brains(0) = bf16(1.5f); brains(1) = bf16(-0.25f);
  Tensor<float, 2> empty({0, 3});
  safetensors::Writer w;
  w.set_metadata("kind", "test");
  w.add("a", a);
  w.add("ids", ids);
  w.add("bytes", bytes);
  w.add("halves", halves);
  w.add("brains", brains);
  w.add("empty", empty);
  w.add("a_column", a.view().reshape(Shape<1>{6}));
  const auto path = temp_path("roundtrip.safetensors");
  w.write(path);
  const auto f = safetensors::File::open(path);
  CHECK(f.metadata("kind") == "test");
  CHECK(f.tensors().size() == 7);
  const auto back = f.get<float, 2>("a");
  CHECK(back(2, 1) == 1.5f);
  const auto view = f.view<double, 2>("a");
  CHECK(view(0, 0) == -1.0);
  CHECK(reinterpret_cast<std::uintptr_t>(view.data()) % 8 == 0);
  CHECK(f.get<double, 1>("ids")(0) == -2.0);
  CHECK(f.get<std::int32_t, 1>("ids")(3) == 1);
  CHECK(f.get<float, 1>("bytes")(2) == 255.0f);
  CHECK(f.get<double, 1>("halves")(1) == -3.0);
  CHECK(f.get<float, 1>("brains")(0) == 1.5f);
  CHECK(f.get<float, 2>("empty").shape() == Shape<2>{0, 3});
  CHECK(f.view<float, 2>("empty").size() == 0);
  CHECK_THROWS_WITH((f.get<float, 3>("a")), Catch::Contains("expected rank 3") && Catch::Contains(path.string()));
  CHECK_THROWS_WITH((f.get<float, 2>("missing")), Catch::Contains("no tensor 'missing'"));
  CHECK_THROWS_WITH((f.view<float, 2>("a")), Catch::Contains("'a' has dtype F64"));
  CHECK_THROWS_WITH((f.get<std::int32_t, 2>("a")), Catch::Contains("floating dtype F64"));
  CHECK_THROWS_WITH((f.get<std::uint8_t, 1>("ids")), Catch::Contains("'ids' element 0 = -2 does not fit"));
  CHECK_THROWS_WITH(f.metadata("nope"), Catch::Contains("no __metadata__ entry 'nope'"));
  std::filesystem::remove(path);
}

TEST_CASE("safetensors writer rejects bad tensors and replaces files atomically", "[safetensors]") {
  safetensors::Writer w;
  Tensor<float, 1> t({2});
  w.add("t", t);
  CHECK_THROWS_WITH(w.add("t", t), Catch::Contains("duplicate tensor 't'"));
  CHECK_THROWS_WITH(w.add("__metadata__", t), Catch::Contains("reserved"));
  float x = 0;
  CHECK_THROWS_WITH(w.add_raw("bad", safetensors::Dtype::F32, {3}, &x, 4), Catch::Contains("'bad' byte count 4"));
  CHECK_THROWS_WITH(w.add_raw("neg", safetensors::Dtype::F32, {-1}, &x, 4), Catch::Contains("negative"));
  CHECK_THROWS_WITH(w.add_raw("huge", safetensors::Dtype::F32, {index_t(1) << 40, index_t(1) << 40}, &x, 4),
                    Catch::Contains("overflows"));
  const auto path = temp_path("atomic.safetensors");
  { std::ofstream(path) << "old contents"; }
  w.write(path);
  CHECK(safetensors::File::open(path).contains("t"));
  for (auto& entry : std::filesystem::directory_iterator(path.parent_path()))
    CHECK(entry.path().filename().string().find(path.filename().string() + ".tmp") == std::string::npos);
  std::filesystem::remove(path);
  CHECK_THROWS_WITH(w.write("/nonexistent_dir_flexsplat/x.safetensors"), Catch::Contains("/nonexistent_dir_flexsplat"));
}

TEST_CASE("safetensors reader rejects missing, empty and truncated files", "[safetensors]") {
  CHECK_THROWS_WITH(safetensors::File::open("/nonexistent_flexsplat.safetensors"),
                    Catch::Contains("/nonexistent_flexsplat.safetensors") && Catch::Contains("cannot open"));
  CHECK_THROWS_WITH(safetensors::File::open(std::filesystem::temp_directory_path()),
                    Catch::Contains("not a regular file"));
  expect_rejected(write_raw("empty_header", "", 0, 0), {"not valid JSON"});
  {
    const auto path = temp_path("short");
    std::ofstream(path, std::ios::binary) << "abc";
    expect_rejected(path, {"3 bytes, shorter than the 8-byte header length"});
  }
  const std::string ok = R"({"x":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}})";
  expect_rejected(write_raw("truncated_data", ok, 10), {"tensor 'x'", "more than the 10-byte data section"});
  // Truncated in the middle of the header: the length now runs past the end.
  expect_rejected(write_raw("truncated_header", ok.substr(0, 20), 0, ok.size()), {"runs past the end of the file"});
}

TEST_CASE("safetensors reader rejects lying header lengths and bad JSON", "[safetensors]") {
  const std::string ok = R"({"x":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}})";
  expect_rejected(write_raw("len_too_long", ok, 16, ok.size() + 100), {"header length 155 runs past the end"});
  expect_rejected(write_raw("len_huge", ok, 16, std::uint64_t(1) << 62), {"exceeds the limit"});
  expect_rejected(write_raw("len_short", ok, 16, ok.size() - 5), {"not valid JSON"});
  expect_rejected(write_raw("not_json", "hello world!", 0), {"not valid JSON"});
  expect_rejected(write_raw("array_header", "[1, 2, 3]", 0), {"not a JSON object but array"});
  expect_rejected(write_raw("string_header", "\"text\"", 0), {"not a JSON object but string"});
}

TEST_CASE("safetensors reader rejects bad offsets", "[safetensors]") {
  expect_rejected(write_raw("overlap",
                            R"({"a":{"dtype":"F32","shape":[4],"data_offsets":[0,16]},)"
                            R"("b":{"dtype":"F32","shape":[4],"data_offsets":[8,24]}})", 24),
                  {"tensor 'b'", "overlaps tensor 'a'"});
  expect_rejected(write_raw("hole",
                            R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},)"
                            R"("b":{"dtype":"F32","shape":[2],"data_offsets":[16,24]}})", 24),
                  {"tensor 'b'", "hole"});
  expect_rejected(write_raw("out_of_range", R"({"a":{"dtype":"F32","shape":[4],"data_offsets":[16,32]}})", 24),
                  {"tensor 'a'", "past the data section"});
  expect_rejected(write_raw("reversed", R"({"a":{"dtype":"F32","shape":[0],"data_offsets":[8,0]}})", 8),
                  {"tensor 'a'", "reversed"});
  expect_rejected(write_raw("trailing", R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}})", 12),
                  {"12 bytes but the tensors cover only 8", "'a'"});
  expect_rejected(write_raw("negative_offset", R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[-8,0]}})", 8),
                  {"tensor 'a'", "data_offsets"});
  expect_rejected(write_raw("missing_offsets", R"({"a":{"dtype":"F32","shape":[2]}})", 8),
                  {"tensor 'a'", "data_offsets must be two"});
}

TEST_CASE("safetensors reader rejects bad dtypes and shapes", "[safetensors]") {
  expect_rejected(write_raw("bad_dtype", R"({"a":{"dtype":"F8_E4M3","shape":[2],"data_offsets":[0,2]}})", 2),
                  {"tensor 'a'", "unknown dtype 'F8_E4M3'"});
  expect_rejected(write_raw("no_dtype", R"({"a":{"shape":[2],"data_offsets":[0,2]}})", 2),
                  {"tensor 'a'", "missing dtype"});
  expect_rejected(write_raw("shape_mismatch", R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,8]}})", 8),
                  {"tensor 'a'", "byte length 8 does not match shape [1]"});
  expect_rejected(write_raw("huge_shape",
                            R"({"a":{"dtype":"F32","shape":[4611686018427387904,4611686018427387904],)"
                            R"("data_offsets":[0,8]}})", 8),
                  {"tensor 'a'", "overflows"});
  // Product wraps to a small number modulo 2^64: must still be refused.
  expect_rejected(write_raw("wrapping_shape",
                            R"({"a":{"dtype":"U8","shape":[4294967296,4294967296,2],"data_offsets":[0,0]}})", 0),
                  {"tensor 'a'", "overflows"});
  // A zero extent hides the product but the other extents still may not overflow.
  expect_rejected(write_raw("zero_hides_overflow",
                            R"({"a":{"dtype":"U8","shape":[0,18446744073709551615],"data_offsets":[0,0]}})", 0),
                  {"tensor 'a'", "overflows"});
  expect_rejected(write_raw("shape_too_big_for_file", R"({"a":{"dtype":"F64","shape":[1000],"data_offsets":[0,8]}})", 8),
                  {"tensor 'a'", "more than the 8-byte data section"});
  expect_rejected(write_raw("negative_extent", R"({"a":{"dtype":"F32","shape":[-2],"data_offsets":[0,8]}})", 8),
                  {"tensor 'a'", "shape entry -2"});
  expect_rejected(write_raw("float_extent", R"({"a":{"dtype":"F32","shape":[2.5],"data_offsets":[0,8]}})", 8),
                  {"tensor 'a'", "shape entry 2.5"});
  expect_rejected(write_raw("entry_not_object", R"({"a":[1,2]})", 0), {"tensor 'a'", "not an object"});
}

TEST_CASE("safetensors reader rejects bad metadata and duplicate names", "[safetensors]") {
  expect_rejected(write_raw("meta_not_object", R"({"__metadata__":[1]})", 0), {"__metadata__ is not an object"});
  expect_rejected(write_raw("meta_value_number", R"({"__metadata__":{"kind":3}})", 0),
                  {"__metadata__ entry 'kind' is not a string"});
  expect_rejected(write_raw("duplicate",
                            R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]},)"
                            R"("a":{"dtype":"F32","shape":[1],"data_offsets":[4,8]}})", 8),
                  {"tensor 'a' appears more than once"});
}

TEST_CASE("safetensors reader accepts zero-size tensors, rank-0 tensors and metadata-only files", "[safetensors]") {
  const auto path = write_raw("zero_size",
                              R"({"__metadata__":{"kind":"k"},"e":{"dtype":"F32","shape":[0,3],"data_offsets":[0,0]},)"
                              R"("s":{"dtype":"F32","shape":[],"data_offsets":[0,4]},)"
                              R"("z":{"dtype":"I64","shape":[2,0],"data_offsets":[4,4]}})", 4);
  const auto f = safetensors::File::open(path);
  CHECK(f.info("e").numel() == 0);
  CHECK(f.info("s").numel() == 1);
  CHECK(f.info("s").shape.empty());
  CHECK(f.get<double, 2>("z").size() == 0);
  std::filesystem::remove(path);
  const auto meta_only = write_raw("meta_only", R"({"__metadata__":{"kind":"k"}})", 0);
  CHECK(safetensors::File::open(meta_only).tensors().empty());
  std::filesystem::remove(meta_only);
}
