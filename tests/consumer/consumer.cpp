// A downstream program: includes the umbrella header, writes and reads back a safetensors file.
#include <flexsplat/flexsplat.hpp>

#include <cstdio>
#include <filesystem>

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
  std::printf("consumer ok: flexsplat %s\n", fs::version_string);
  return 0;
}
