#include <catch2/catch.hpp>

#include <filesystem>
#include <fstream>

#include "flexsplat/geometry/camera_head.hpp"
#include "heads_bundle.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

template <class T>
void run_camera_bundle_cases() {
  const auto json = heads_test::bundle_config();
  const CameraHeadConfig cfg = camera_head_config_from_vggt_json(json);
  io::ParamSource<T> src(heads_test::bundle(), "param.");
  const auto w = load_camera_head_weights(src, cfg);
  const index_t depth = json.at("depth").get<index_t>();
  const auto cases = heads_test::bundle_cases();
  REQUIRE(cases.size() == 3);
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const index_t S = cases[k][0];
    const std::string p = "case" + std::to_string(k) + ".";
    const std::string last = p + "aggregator.out." + std::to_string(depth - 1);
    const auto tokens = heads_test::read<T>(last);
    const index_t n_tok = heads_test::bundle().info(last).shape[2];
    std::vector<T> ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, S)));
    std::vector<T> enc(cfg.iterations * S * pose_encoding_dim);
    camera_head_forward<T>(enc.data(), cfg, w, tokens.data(), S, n_tok, ws);
    for (index_t it = 0; it < cfg.iterations; ++it) {
      const std::string name = p + "camera_head.pose_enc." + std::to_string(it);
      std::vector<T> one(enc.begin() + it * S * 9, enc.begin() + (it + 1) * S * 9);
      heads_test::check_close(name, one, heads_test::read<float>(name));
    }
  }
}

}  // namespace

TEST_CASE("camera head reproduces every refinement iteration of the bundle (float)", "[camera_head]") {
  run_camera_bundle_cases<float>();
}

TEST_CASE("camera head reproduces every refinement iteration of the bundle (double)", "[camera_head]") {
  run_camera_bundle_cases<double>();
}

TEST_CASE("camera head parameter names match the VGGT-1B state_dict layout", "[camera_head]") {
  const auto expected = heads_test::vggt1b_layout_shapes("camera_head.");
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, CameraHeadConfig{});
  const auto ours = heads_test::spec_shapes(specs);
  CHECK(ours.size() == specs.size());
  CHECK(expected.size() > 50);
  CHECK(ours == expected);
}

TEST_CASE("camera head loading lists every missing, mis-shaped and unexpected tensor", "[camera_head]") {
  const CameraHeadConfig cfg = camera_head_config_from_vggt_json(heads_test::bundle_config());
  safetensors::Writer writer;
  for (const auto& t : heads_test::bundle().tensors()) {
    if (t.name.rfind("param.camera_head.", 0) != 0) continue;
    if (t.name == "param.camera_head.trunk.1.ls2.gamma" || t.name == "param.camera_head.embed_pose.bias") continue;
    if (t.name == "param.camera_head.pose_branch.fc2.weight") {
      std::vector<float> v(8 * 64, 0.0f);
      writer.add_raw(t.name, safetensors::Dtype::F32, {8, 64}, v.data(), v.size() * 4);
      continue;
    }
    writer.add_raw(t.name, t.dtype, t.shape, heads_test::bundle().bytes(t), t.end - t.begin);
  }
  const float one = 1.0f;
  writer.add_raw("param.camera_head.trunk.2.norm1.weight", safetensors::Dtype::F32, {1}, &one, 4);
  const auto path = std::filesystem::temp_directory_path() / ("flexsplat_cam_bad_" + std::to_string(::getpid()) + ".safetensors");
  writer.write(path);
  io::ParamSource<float> src(safetensors::File::open(path), "param.");
  try {
    load_camera_head_weights(src, cfg);
    FAIL("loading should have failed");
  } catch (const Error& e) {
    const std::string msg = e.what();
    INFO(msg);
    CHECK_THAT(msg, Catch::Contains("2 missing") && Catch::Contains("param.camera_head.trunk.1.ls2.gamma [128]") &&
                        Catch::Contains("param.camera_head.embed_pose.bias [128]"));
    CHECK_THAT(msg, Catch::Contains("param.camera_head.pose_branch.fc2.weight is [8, 64], expected [9, 64]"));
    CHECK_THAT(msg, Catch::Contains("1 unexpected") && Catch::Contains("param.camera_head.trunk.2.norm1.weight"));
  }
  std::filesystem::remove(path);
}

TEST_CASE("camera head rejects bad inputs", "[camera_head]") {
  const auto json = heads_test::bundle_config();
  const CameraHeadConfig cfg = camera_head_config_from_vggt_json(json);
  io::ParamSource<float> src(heads_test::bundle(), "param.");
  const auto w = load_camera_head_weights(src, cfg);
  const auto tokens = heads_test::read<float>("case2.aggregator.out.2");
  std::vector<float> enc(cfg.iterations * 9);
  std::vector<float> ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, 1)));
  CHECK_THROWS_WITH(camera_head_forward<float>(enc.data(), cfg, w, tokens.data(), 1, 21, std::span<float>(ws.data(), 10)),
                    Catch::Contains("workspace"));
  CHECK_THROWS_WITH(camera_head_forward<float>(enc.data(), cfg, w, tokens.data(), 0, 21, ws), Catch::Contains("frame"));
  CameraHeadConfig deeper = cfg;
  deeper.trunk_depth = 3;
  std::vector<float> ws3(static_cast<std::size_t>(camera_head_workspace_size(deeper, 1)));
  CHECK_THROWS_WITH(camera_head_forward<float>(enc.data(), deeper, w, tokens.data(), 1, 21, ws3),
                    Catch::Contains("2 trunk blocks"));
  CHECK_THROWS_WITH(camera_head_config_from_vggt_json(nlohmann::json{{"embed_dim", 64}, {"cam_heads", 3}}),
                    Catch::Contains("num_heads 3"));
}
