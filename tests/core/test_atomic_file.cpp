#include <catch2/catch.hpp>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>

#include "flexsplat/core/atomic_file.hpp"
#include "temp_dir.hpp"

using namespace flexsplat;
namespace fs = std::filesystem;

namespace {

int siblings(const fs::path& dir) {
  int n = 0;
  for (const auto& e : fs::directory_iterator(dir)) n += e.path().filename().string().find(".tmp") != std::string::npos;
  return n;
}

}  // namespace

TEST_CASE("write_file_atomic replaces the file whole and leaves no temporary", "[core][atomic_file]") {
  flexsplat_test::TempDir dir("atomic_file");
  const fs::path p = dir.path / "out.bin";
  write_file_atomic(p, "test", std::string("first"));
  CHECK(flexsplat_test::file_bytes(p) == "first");
  write_file_atomic(p, "test", [](std::ostream& out) { out << "second" << ' ' << 2; });
  CHECK(flexsplat_test::file_bytes(p) == "second 2");
  CHECK(siblings(dir.path) == 0);
}

TEST_CASE("a failing writer keeps the old file and removes its temporary", "[core][atomic_file]") {
  flexsplat_test::TempDir dir("atomic_file");
  const fs::path p = dir.path / "keep.txt";
  write_file_atomic(p, "test", std::string("old"));
  CHECK_THROWS_WITH(write_file_atomic(p, "test",
                                      [](std::ostream& out) {
                                        out << "half";
                                        throw std::runtime_error("encoder failed");
                                      }),
                    Catch::Contains("encoder failed"));
  CHECK(flexsplat_test::file_bytes(p) == "old");
  CHECK(siblings(dir.path) == 0);
  CHECK_THROWS_WITH(write_file_atomic(dir.path / "no_such_folder" / "x.txt", "glb writer", std::string("x")),
                    Catch::Contains("glb writer: cannot create") && Catch::Contains("no_such_folder"));
}

TEST_CASE("remove_stale_temp_files removes only dead writers' temporaries", "[core][atomic_file]") {
  flexsplat_test::TempDir dir("atomic_file");
  const fs::path p = dir.path / "state.safetensors";
  // Above Linux's largest pid_max (2^22): no such process.
  const fs::path dead = dir.path / "state.safetensors.tmp4194399_0";
  const fs::path mine = dir.path / ("state.safetensors.tmp" + std::to_string(::getpid()) + "_7");
  const fs::path other = dir.path / "other.safetensors.tmp4194399_0";
  const fs::path odd = dir.path / "state.safetensors.tmpabc_0";
  for (const fs::path& f : {dead, mine, other, odd}) std::ofstream(f) << "partial";
  remove_stale_temp_files(p);
  CHECK_FALSE(fs::exists(dead));
  CHECK(fs::exists(mine));
  CHECK(fs::exists(other));
  CHECK(fs::exists(odd));
}
