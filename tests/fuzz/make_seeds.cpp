// Writes the fuzzers' seed corpus with the project's own writers (run from the repository root):
//   g++ -std=c++20 -O1 -Iinclude -I/usr/include/eigen3 -I/usr/include/stb tests/fuzz/make_seeds.cpp \
//       -o build-fuzz/make_seeds -lstb -ltinygltf -pthread && build-fuzz/make_seeds tests/fuzz/corpus
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/io/cameras_json.hpp"
#include "flexsplat/export/gltf.hpp"
#include "flexsplat/export/ply.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/optim/checkpoint.hpp"

using namespace flexsplat;
namespace fs = std::filesystem;

namespace {

void write_bytes(const fs::path& path, const void* data, std::size_t size) {
  fs::create_directories(path.parent_path());
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(static_cast<const char*>(data), static_cast<std::streamsize>(size));
  require(out.good(), "cannot write ", path.string());
}
void write_text(const fs::path& path, const std::string& text) { write_bytes(path, text.data(), text.size()); }
std::string read_text(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  require(in.good(), "cannot read ", path.string());
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

// Small deterministic set: values from a fixed formula, unit quaternions, scales in (0, 1).
GaussianSet<float> small_set(index_t n, int degree) {
  auto set = make_gaussian_set<float>(n, degree);
  for (index_t i = 0; i < n; ++i) {
    const double a = 0.7 * static_cast<double>(i) + 0.3;
    const double q[4] = {std::cos(a), std::sin(a) * 0.6, std::sin(a) * 0.8, 0.0};
    for (int c = 0; c < 4; ++c) set.quats(i, c) = static_cast<float>(q[c]);
    for (int c = 0; c < 3; ++c) {
      set.means(i, c) = static_cast<float>(std::sin(a * (c + 1)));
      set.scales(i, c) = static_cast<float>(0.05 + 0.1 * c + 0.01 * static_cast<double>(i));
    }
    set.opacities(i) = static_cast<float>(0.2 + 0.3 * static_cast<double>(i % 3));
    for (index_t k = 0; k < set.sh.shape(1); ++k)
      for (int c = 0; c < 3; ++c) set.sh(i, k, c) = static_cast<float>(0.1 * std::cos(a + k + c));
  }
  return set;
}

// 16-bit PNG (grey or RGB) assembled by hand: stb writes only 8-bit PNG. Deflate is stb's, exported by libstb.
std::vector<unsigned char> png16(int width, int height, int channels) {
  std::vector<unsigned char> raw;
  for (int y = 0; y < height; ++y) {
    raw.push_back(0);  // filter: none
    for (int x = 0; x < width * channels; ++x) {
      const int v = (y * 7919 + x * 4099) % 65536;
      raw.push_back(static_cast<unsigned char>(v >> 8));
      raw.push_back(static_cast<unsigned char>(v & 255));
    }
  }
  int zlen = 0;
  unsigned char* z = stbi_zlib_compress(raw.data(), static_cast<int>(raw.size()), &zlen, 8);
  std::vector<unsigned char> out = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  auto be32 = [](std::vector<unsigned char>& v, std::uint32_t x) {
    for (int s = 24; s >= 0; s -= 8) v.push_back(static_cast<unsigned char>(x >> s));
  };
  auto chunk = [&](const char* type, const std::vector<unsigned char>& body) {
    be32(out, static_cast<std::uint32_t>(body.size()));
    std::vector<unsigned char> typed(type, type + 4);
    typed.insert(typed.end(), body.begin(), body.end());
    std::uint32_t crc = 0xffffffffu;
    for (unsigned char b : typed) {
      crc ^= b;
      for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xedb88320u & (0u - (crc & 1u)));
    }
    out.insert(out.end(), typed.begin(), typed.end());
    be32(out, crc ^ 0xffffffffu);
  };
  std::vector<unsigned char> ihdr;
  be32(ihdr, static_cast<std::uint32_t>(width));
  be32(ihdr, static_cast<std::uint32_t>(height));
  ihdr.insert(ihdr.end(), {16, static_cast<unsigned char>(channels == 1 ? 0 : 2), 0, 0, 0});
  chunk("IHDR", ihdr);
  chunk("IDAT", std::vector<unsigned char>(z, z + zlen));
  chunk("IEND", {});
  std::free(z);
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  const fs::path root = argc > 1 ? argv[1] : "tests/fuzz/corpus";
  for (const char* t : {"safetensors", "ply", "glb", "image", "cameras_json", "vggt_config", "dataset", "checkpoint", "train_config"})
    fs::create_directories(root / t);

  // safetensors: every dtype, rank 0 to 2, an empty tensor, metadata; and a one-tensor file.
  {
    safetensors::Writer w;
    w.set_metadata("kind", "raster");
    w.set_metadata("config", R"({"width": 4})");
    Tensor<float, 2> f32({2, 3});
    for (index_t i = 0; i < f32.size(); ++i) f32.data()[i] = 0.25f * static_cast<float>(i) - 0.5f;
    w.add("a.f32", f32);
    Tensor<double, 1> f64({2});
    f64(0) = -1.5; f64(1) = 3.0;
    w.add("b.f64", f64);
    Tensor<std::int64_t, 1> i64({3});
    i64(0) = -7; i64(1) = 0; i64(2) = 1LL << 40;
    w.add("c.i64", i64);
    Tensor<std::int32_t, 2> i32({2, 2});
    for (index_t i = 0; i < 4; ++i) i32.data()[i] = static_cast<std::int32_t>(i * 100 - 150);
    w.add("d.i32", i32);
    Tensor<std::uint8_t, 1> u8({3});
    u8(0) = 0; u8(1) = 128; u8(2) = 255;
    w.add("e.u8", u8);
    Tensor<f16, 1> h({2});
    h(0) = f16(0.5f); h(1) = f16(-2.0f);
    w.add("f.f16", h);
    Tensor<bf16, 1> b({1});
    b(0) = bf16(1.25f);
    w.add("g.bf16", b);
    Tensor<float, 2> empty({0, 4});
    w.add("h.empty", empty);
    w.write(root / "safetensors" / "all_dtypes.safetensors");
    safetensors::Writer one;
    Tensor<float, 1> v({4});
    for (index_t i = 0; i < 4; ++i) v(i) = static_cast<float>(i);
    one.add("weight", v);
    one.write(root / "safetensors" / "one_tensor.safetensors");
  }

  // PLY: binary at SH degrees 0 and 1, and ASCII.
  {
    for (int degree : {0, 1}) {
      const auto bytes = ply::encode_ply(small_set(degree == 0 ? 3 : 2, degree));
      write_bytes(root / "ply" / ("binary_degree" + std::to_string(degree) + ".ply"), bytes.data(), bytes.size());
    }
    std::string ascii = "ply\nformat ascii 1.0\nelement vertex 2\n";
    const auto names = ply::property_names(0);
    for (const auto& name : names) ascii += "property float " + name + "\n";
    ascii += "element face 0\nproperty list uchar int vertex_indices\nend_header\n";
    for (int i = 0; i < 2; ++i) {
      for (std::size_t k = 0; k < names.size(); ++k) {
        const std::string& name = names[k];
        const double v = name == "rot_0" ? 1.0 : name.rfind("scale_", 0) == 0 ? -2.5 : 0.125 * (i + 1);
        ascii += (k ? " " : "") + std::to_string(v);
      }
      ascii += "\n";
    }
    write_text(root / "ply" / "ascii_degree0.ply", ascii);
  }

  // glb: float attributes with cameras; quantised attributes at SH degree 1 without the colour fallback.
  {
    gltf::WriteOptions with_cameras;
    auto cams = io::load_cameras_json("examples/data/spot/cameras.json");
    cams.resize(2);
    with_cameras.cameras = cams;
    auto bytes = gltf::encode_glb(small_set(3, 0), with_cameras);
    write_bytes(root / "glb" / "float_cameras.glb", bytes.data(), bytes.size());
    gltf::WriteOptions quantised;
    quantised.rotation = gltf::RotationEncoding::Int8Normalized;
    quantised.scale = gltf::UnitEncoding::UInt16Normalized;
    quantised.opacity = gltf::UnitEncoding::UInt8Normalized;
    quantised.color_fallback = false;
    bytes = gltf::encode_glb(small_set(2, 1), quantised);
    write_bytes(root / "glb" / "quantised_degree1.glb", bytes.data(), bytes.size());
  }

  // Images: 8-bit PNG with 1, 3 and 4 channels, 16-bit PNG with 1 and 3, and a baseline JPEG.
  {
    for (int c : {1, 3}) {
      const auto bytes = png16(5, 3, c);
      write_bytes(root / "image" / ("png16_c" + std::to_string(c) + ".png"), bytes.data(), bytes.size());
    }
    for (int c : {1, 3, 4}) {
      Tensor<std::uint8_t, 3> img({3, 4, c});
      for (index_t i = 0; i < img.size(); ++i) img.data()[i] = static_cast<std::uint8_t>(i * 37 % 256);
      image::write_png(root / "image" / ("png8_c" + std::to_string(c) + ".png"), img);
      if (c == 3) {
        std::vector<unsigned char> jpg;
        stbi_write_jpg_to_func(
            [](void* ctx, void* data, int size) {
              auto* out = static_cast<std::vector<unsigned char>*>(ctx);
              out->insert(out->end(), static_cast<unsigned char*>(data), static_cast<unsigned char*>(data) + size);
            },
            &jpg, 4, 3, 3, img.data(), 90);
        write_bytes(root / "image" / "baseline.jpg", jpg.data(), jpg.size());
      }
    }
  }

  // cameras.json: the bundled spot file cut to two frames.
  {
    std::ifstream in("examples/data/spot/cameras.json");
    nlohmann::json doc = nlohmann::json::parse(in);
    doc["frames"] = nlohmann::json::array({doc["frames"][0], doc["frames"][1]});
    write_text(root / "cameras_json" / "spot_two_frames.json", doc.dump(1));
  }

  // VGGT config: the tiny configuration of tests/geometry/test_vggt.cpp and VGGT-1B's keys.
  {
    write_text(root / "vggt_config" / "tiny.json",
               R"({"img_size": 98, "patch_size": 14, "embed_dim": 64, "depth": 3, "num_heads": 2, "dino_depth": 2,)"
               R"( "dino_heads": 2, "trunk_depth": 2, "cam_heads": 2, "features": 32, "out_channels": [16, 32, 64, 64],)"
               R"( "intermediate_layer_idx": [0, 1, 1, 2]})");
    write_text(root / "vggt_config" / "vggt1b.json",
               R"({"img_size": 518, "patch_size": 14, "embed_dim": 1024, "depth": 24, "num_heads": 16,)"
               R"( "mlp_ratio": 4.0, "num_register_tokens": 4, "qk_norm": true, "rope_freq": 100, "init_values": 0.01,)"
               R"( "aa_block_size": 1, "aa_order": ["frame", "global"], "dino_depth": 24, "dino_heads": 16,)"
               R"( "dino_mlp_ratio": 4.0, "trunk_depth": 4, "cam_heads": 16, "features": 256,)"
               R"( "out_channels": [256, 512, 1024, 1024], "intermediate_layer_idx": [4, 11, 17, 23]})");
  }
  // Dataset folder (fuzz_dataset.cpp's format: files joined by "\n--8<--\n"): a procedural object of 2 views at
  // 8 x 8, written by data::write_object, and the same cut to one frame.
  {
    data::GeneratorConfig g;
    g.size = 8, g.views = 2, g.structured = false, g.supersample = 1;
    const fs::path dir = root / "dataset" / ".tmp_object";
    fs::remove_all(dir);
    data::write_object(dir, data::generate_object(3, 0, g));
    const std::string sep = "\n--8<--\n";
    nlohmann::json doc = nlohmann::json::parse(read_text(dir / "cameras.json"));
    doc.erase("generator");
    std::string two = doc.dump(1);
    for (const char* f : {"images/000.png", "depth/000.png", "images/001.png", "depth/001.png"}) two += sep + read_text(dir / f);
    write_text(root / "dataset" / "two_views_8px.bin", two);
    doc["frames"] = nlohmann::json::array({doc["frames"][0]});
    write_text(root / "dataset" / "one_view_8px.bin",
               doc.dump(1) + sep + read_text(dir / "images/000.png") + sep + read_text(dir / "depth/000.png"));
    fs::remove_all(dir);
  }

  // Checkpoints of fuzz_checkpoint.cpp's small store: a training state and a model file with its expected
  // configuration, and a training state whose configuration is the tiny FlexSplat model (for model::load_flexsplat).
  {
    train::ParamStore<float> store;
    store.add_segment("a", {{"layer.weight", {2, 3}}, {"layer.bias", {3}}});
    store.add_segment("b", {{"norm.weight", {4}}, {"scalar", {}}});
    store.allocate(true);
    for (index_t i = 0; i < store.size(); ++i) {
      store.params()[i] = 0.125f * static_cast<float>(i) - 1.0f;
      store.adam_m()[i] = 0.01f * static_cast<float>(i);
      store.adam_v()[i] = 0.001f * static_cast<float>(i);
    }
    const nlohmann::json config = {{"kind", "fuzz"}};
    const train::TrainingState state{12, train::rng_state_string(std::mt19937_64(7))};
    train::save_training_state(root / "checkpoint" / "training_state.safetensors", store, config, state);
    train::save_model(root / "checkpoint" / "model.safetensors", store, config, 3);
    train::save_training_state(root / "checkpoint" / "tiny_config_state.safetensors", store,
                               model::to_json(model::flexsplat_tiny_config()), train::TrainingState{1, "x"});
  }

  // Train configs: the ctest's tiny run, and one with the FlexSplat model as an object.
  {
    write_text(root / "train_config" / "train_tiny.json", read_text("tests/cli/train_tiny.json"));
    nlohmann::json cfg = {{"model", model::to_json(model::flexsplat_tiny_config())}, {"batch", 1}, {"inputs", {1, 2}},
                          {"stages", {{{"name", "geometry"}, {"steps", 3}, {"appearance", false}, {"camera_weight", 1.0}},
                                      {{"name", "joint"}, {"steps", 5}, {"lr", 2e-4}, {"warmup", 2},
                                       {"objective", {{"render", 1.0}, {"lpips", 0.0}}}}}}};
    write_text(root / "train_config" / "model_object.json", cfg.dump(1));
  }
  return 0;
}
