// A downstream program: includes the umbrella header (installed package) or the module headers it uses
// (subdirectory), writes and reads back a safetensors file, and runs a GEMM on the backend its configuration chose
// (FLEXSPLAT_CONSUMER_EXPECT_BLAS: the BLAS must be there).
#if defined(FLEXSPLAT_CONSUMER_UMBRELLA)
#include <flexsplat/flexsplat.hpp>
#else
#include <flexsplat/core/gemm.hpp>
#include <flexsplat/core/tensor.hpp>
#include <flexsplat/core/version.hpp>
#include <flexsplat/io/safetensors.hpp>
#endif

#include <cstdio>
#include <filesystem>
#include <vector>

int main() {
  namespace fs = flexsplat;
  fs::Tensor<float, 2> t({2, 3});
  for (fs::index_t i = 0; i < t.size(); ++i) t.data()[i] = static_cast<float>(i);
  fs::safetensors::Writer w;
  w.set_metadata("kind", "consumer");
  w.add("t", t);
  const auto path = std::filesystem::temp_directory_path() / "flexsplat_consumer.safetensors";
  w.write(path);
  const auto file = fs::safetensors::File::open(path);
  const auto back = file.get<double, 2>("t");
  std::filesystem::remove(path);
  if (back(1, 2) != 5.0 || file.metadata("kind") != "consumer") return 1;
#if defined(FLEXSPLAT_CONSUMER_EXPECT_BLAS)
  const bool expect_blas = true;
#else
  const bool expect_blas = false;
#endif
  if (fs::have_blas != expect_blas) return 2;
  // 64^3 multiply-adds: above gemm_blas_min_madds, so a BLAS build really calls cblas_sgemm (linked via the target).
  const fs::index_t n = 64;
  std::vector<float> a(n * n, 0.5f), b(n * n, 0.25f), c(n * n, -1.0f);
  fs::gemm(fs::Trans::no, fs::Trans::yes, n, n, n, 1.0f, a.data(), n, b.data(), n, 0.0f, c.data(), n);
  for (float v : c)
    if (v != 8.0f) return 3;
  std::printf("consumer ok: flexsplat %s, gemm on %s\n", fs::version_string, fs::gemm_backend_name().c_str());
  return 0;
}
