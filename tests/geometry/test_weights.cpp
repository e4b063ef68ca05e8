#include <catch2/catch.hpp>

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <set>

#include <nlohmann/json.hpp>

#include "flexsplat/geometry/weights.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

bool ignored_head(const std::string& name) { return name.rfind("point_head.", 0) == 0 || name.rfind("track_head.", 0) == 0; }

// A safetensors file with a header only: the data section is a hole, so 5 GB of F32 cost no disk and no memory.
std::filesystem::path write_sparse_vggt1b(const std::string& dtype, std::size_t element_bytes) {
  std::ifstream in(std::string(FLEXSPLAT_SHARED_DIR) + "/reference/vggt1b_state_dict_layout.json");
  REQUIRE(in);
  const auto layout = nlohmann::json::parse(in);
  nlohmann::json header = nlohmann::json::object();
  std::uint64_t offset = 0;
  for (const auto& t : layout.at("tensors")) {
    std::uint64_t bytes = element_bytes;
    for (auto e : t.at("shape")) bytes *= e.get<std::uint64_t>();
    header[t.at("name").get<std::string>()] = {{"dtype", dtype}, {"shape", t.at("shape")}, {"data_offsets", {offset, offset + bytes}}};
    offset += bytes;
  }
  std::string text = header.dump();
  while (text.size() % 8) text.push_back(' ');
  const auto path = std::filesystem::temp_directory_path() /
                    ("flexsplat_vggt1b_sparse_" + dtype + "_" + std::to_string(::getpid()) + ".safetensors");
  {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    const std::uint64_t len = text.size();
    out.write(reinterpret_cast<const char*>(&len), 8);
    out.write(text.data(), static_cast<std::streamsize>(text.size()));
  }
  std::filesystem::resize_file(path, 8 + text.size() + offset);
  return path;
}

struct RemoveOnExit {
  std::filesystem::path path;
  ~RemoveOnExit() {
    std::error_code ec;
    std::filesystem::remove(path, ec);
  }
};

}  // namespace

TEST_CASE("the VGGT-1B checkpoint layout maps completely, zero-copy, from a sparse 5 GB file", "[geometry][weights]") {
  const RemoveOnExit file{write_sparse_vggt1b("F32", 4)};
  CHECK(std::filesystem::file_size(file.path) > std::uintmax_t(5'000'000'000));
  const VggtConfig cfg;  // VGGT-1B defaults
  auto source = io::ParamSource<float>(safetensors::File::open(file.path));

  // The spec table is exactly the checkpoint minus the point and track heads.
  std::set<std::string> layout_names, spec_names;
  for (const auto& t : source.file().tensors())
    if (!ignored_head(t.name)) layout_names.insert(t.name);
  for (const auto& s : vggt_parameter_specs(cfg)) spec_names.insert(s.name);
  CHECK(layout_names.size() == spec_names.size());
  CHECK(layout_names == spec_names);

  const auto weights = load_vggt_weights(source, cfg);
  CHECK(source.converted_bytes() == 0);
  CHECK(weights.aggregator.frame_blocks.size() == 24);
  CHECK(weights.aggregator.global_blocks.size() == 24);
  CHECK(weights.dino.blocks.size() == 24);
  CHECK(weights.camera.trunk.size() == 4);
  // Every bound pointer lies inside the mapping at its tensor's offset.
  const auto& f = source.file();
  CHECK(weights.aggregator.global_blocks[23].fc2_weight ==
        reinterpret_cast<const float*>(f.bytes(f.info("aggregator.global_blocks.23.mlp.fc2.weight"))));
  CHECK(weights.depth.output_conv2_2.bias ==
        reinterpret_cast<const float*>(f.bytes(f.info("depth_head.scratch.output_conv2.2.bias"))));
  CHECK(weights.dino.pos_embed == reinterpret_cast<const float*>(f.bytes(f.info("aggregator.patch_embed.pos_embed"))));
}

TEST_CASE("one error lists every missing, mis-shaped and unexpected tensor, ignoring point/track heads", "[geometry][weights]") {
  const auto bundle = safetensors::File::open(vggt_bundle_path());
  const VggtConfig cfg = vggt_config_from_json(bundle.metadata("config"));
  safetensors::Writer writer;
  for (const auto& t : bundle.tensors()) {
    if (t.name.rfind("param.", 0) != 0) continue;
    const std::string name = t.name.substr(6);
    if (name == "aggregator.frame_blocks.1.attn.proj.bias") continue;  // missing
    std::vector<index_t> shape = t.shape;
    if (name == "camera_head.embed_pose.weight") shape = {shape[1], shape[0]};  // mis-shaped
    writer.add_raw(name, t.dtype, shape, bundle.bytes(t), t.end - t.begin);
  }
  const float extra[2] = {1, 2};
  writer.add_raw("depth_head.scratch.extra_conv.weight", safetensors::Dtype::F32, {2}, extra, sizeof extra);
  writer.add_raw("point_head.norm.weight", safetensors::Dtype::F32, {2}, extra, sizeof extra);
  writer.add_raw("track_head.anything", safetensors::Dtype::F32, {2}, extra, sizeof extra);
  const RemoveOnExit file{std::filesystem::temp_directory_path() /
                          ("flexsplat_vggt_broken_" + std::to_string(::getpid()) + ".safetensors")};
  writer.write(file.path);
  io::ParamSource<float> src(safetensors::File::open(file.path));
  std::string message;
  try {
    load_vggt_weights(src, cfg);
  } catch (const Error& e) {
    message = e.what();
  }
  INFO(message);
  CHECK_THAT(message, Catch::Contains("aggregator.frame_blocks.1.attn.proj.bias"));
  CHECK_THAT(message, Catch::Contains("camera_head.embed_pose.weight is [9, 128], expected [128, 9]"));
  CHECK_THAT(message, Catch::Contains("depth_head.scratch.extra_conv.weight"));
  CHECK_THAT(message, !Catch::Contains("point_head"));
  CHECK_THAT(message, !Catch::Contains("track_head"));
}

TEST_CASE("BF16 and F16 checkpoints are converted once to float", "[geometry][weights]") {
  const auto bundle = safetensors::File::open(vggt_bundle_path());
  const VggtConfig cfg = vggt_config_from_json(bundle.metadata("config"));
  const bool use_bf16 = GENERATE(true, false);
  safetensors::Writer writer;
  std::size_t floats = 0;
  for (const auto& t : bundle.tensors()) {
    if (t.name.rfind("param.", 0) != 0) continue;
    std::vector<float> v(static_cast<std::size_t>(t.numel()));
    bundle.convert(t, v.data());
    if (t.name != "param.aggregator.patch_embed.mask_token") floats += v.size();  // stored, never read
    std::vector<std::uint16_t> half(v.size());
    for (std::size_t i = 0; i < v.size(); ++i) half[i] = use_bf16 ? bf16(v[i]).bits : f16(v[i]).bits;
    writer.add_raw(t.name, use_bf16 ? safetensors::Dtype::BF16 : safetensors::Dtype::F16, t.shape, half.data(),
                   half.size() * 2);
  }
  const RemoveOnExit file{std::filesystem::temp_directory_path() /
                          ("flexsplat_vggt_half_" + std::to_string(::getpid()) + ".safetensors")};
  writer.write(file.path);
  io::ParamSource<float> src(safetensors::File::open(file.path), "param.");
  const auto weights = load_vggt_weights(src, cfg);
  CHECK(src.converted_bytes() == floats * sizeof(float));
  // A second lookup returns the same converted buffer instead of converting again.
  const index_t C = cfg.aggregator.embed_dim;
  CHECK(src.get("aggregator.camera_token", {1, 2, 1, C}) == weights.aggregator.camera_token);
  CHECK(src.converted_bytes() == floats * sizeof(float));
  const auto original = bundle.get<float, 4>("param.aggregator.camera_token");
  for (index_t i = 0; i < original.size(); ++i) {
    const float expected = use_bf16 ? static_cast<float>(bf16(original.data()[i])) : static_cast<float>(f16(original.data()[i]));
    REQUIRE(weights.aggregator.camera_token[i] == expected);
  }
}
