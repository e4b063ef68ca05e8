#include <catch2/catch.hpp>

#include <filesystem>
#include <fstream>

#include "flexsplat/geometry/dpt_head.hpp"
#include "heads_bundle.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

struct CaseInputs {
  index_t S = 0, H = 0, W = 0, tokens = 0;
  std::vector<std::vector<float>> layers;
};

CaseInputs load_case(std::size_t k, index_t depth) {
  CaseInputs c;
  const auto cs = heads_test::bundle_cases()[k];
  c.S = cs[0];
  c.H = cs[1];
  c.W = cs[2];
  const std::string p = "case" + std::to_string(k) + ".";
  for (index_t i = 0; i < depth; ++i) c.layers.push_back(heads_test::read<float>(p + "aggregator.out." + std::to_string(i)));
  c.tokens = heads_test::bundle().info(p + "aggregator.out.0").shape[2];
  return c;
}

template <class T>
std::vector<std::vector<T>> cast_layers(const CaseInputs& c) {
  std::vector<std::vector<T>> out;
  for (auto& l : c.layers) out.emplace_back(l.begin(), l.end());
  return out;
}

template <class T>
void run_dpt_bundle_cases() {
  const auto json = heads_test::bundle_config();
  const DptHeadConfig cfg = dpt_head_config_from_vggt_json(json);
  io::ParamSource<T> src(heads_test::bundle(), "param.");
  const auto weights = load_dpt_head_weights(src, cfg);
  if constexpr (std::is_same_v<T, float>) CHECK(src.converted_bytes() == 0);
  const index_t depth = json.at("depth").get<index_t>();
  const auto cases = heads_test::bundle_cases();
  REQUIRE(cases.size() == 3);
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const CaseInputs in = load_case(k, depth);
    const auto layers_t = cast_layers<T>(in);
    std::vector<const T*> layers;
    for (auto& l : layers_t) layers.push_back(l.data());
    const index_t ph = in.H / cfg.patch_size, pw = in.W / cfg.patch_size;
    std::vector<T> ws(static_cast<std::size_t>(dpt_head_workspace_size(cfg, ph, pw)));
    std::vector<T> depth_map(in.S * in.H * in.W), conf(in.S * in.H * in.W);
    DptHeadOutputs<T> out;
    out.preds = depth_map.data();
    out.conf = conf.data();
    dpt_head_forward<T>(out, cfg, weights, layers, in.S, in.tokens, in.tokens - ph * pw, in.H, in.W, ws);
    const std::string p = "case" + std::to_string(k) + ".";
    heads_test::check_close(p + "depth", depth_map, heads_test::read<float>(p + "depth"));
    heads_test::check_close(p + "depth_conf", conf, heads_test::read<float>(p + "depth_conf"));
    const double rel = heads_test::max_elementwise_rel(depth_map, heads_test::read<float>(p + "depth"), 0.0);
    INFO("depth element-wise relative error " << rel);
    CHECK(rel <= 1e-4);
  }
}

}  // namespace

TEST_CASE("DPT head reproduces the bundle's depth and confidence (float)", "[dpt_head]") { run_dpt_bundle_cases<float>(); }

TEST_CASE("DPT head reproduces the bundle's depth and confidence (double)", "[dpt_head]") { run_dpt_bundle_cases<double>(); }

TEST_CASE("DPT head exposes the map that output_conv2 turns into depth", "[dpt_head]") {
  const auto json = heads_test::bundle_config();
  const DptHeadConfig cfg = dpt_head_config_from_vggt_json(json);
  io::ParamSource<double> src(heads_test::bundle(), "param.");
  const auto w = load_dpt_head_weights(src, cfg);
  const CaseInputs in = load_case(0, json.at("depth").get<index_t>());
  const auto layers_t = cast_layers<double>(in);
  std::vector<const double*> layers;
  for (auto& l : layers_t) layers.push_back(l.data());
  const index_t ph = in.H / 14, pw = in.W / 14, full = in.H * in.W, Fh = cfg.head_features();
  std::vector<double> ws(static_cast<std::size_t>(dpt_head_workspace_size(cfg, ph, pw)));
  std::vector<double> depth_map(in.S * full), conf(in.S * full), features(in.S * Fh * full),
      fused(in.S * Fh * 64 * ph * pw);
  DptHeadOutputs<double> out{depth_map.data(), conf.data(), features.data(), fused.data()};
  dpt_head_forward<double>(out, cfg, w, layers, in.S, in.tokens, in.tokens - ph * pw, in.H, in.W, ws);
  // Naive output_conv2 (3x3 conv, ReLU, 1x1 conv) + exp on the exposed features, at a few pixels of each frame.
  const index_t Hd = DptHeadConfig::head_hidden;
  for (index_t f = 0; f < in.S; ++f)
    for (index_t y : {index_t(0), in.H / 2, in.H - 1})
      for (index_t x : {index_t(0), in.W / 3, in.W - 1}) {
        const double* feat = features.data() + f * Fh * full;
        double logit = w.output_conv2_2.bias[0];
        for (index_t o = 0; o < Hd; ++o) {
          double h = w.output_conv2_0.bias[o];
          for (index_t c = 0; c < Fh; ++c)
            for (index_t i = 0; i < 3; ++i)
              for (index_t j = 0; j < 3; ++j) {
                const index_t yy = y + i - 1, xx = x + j - 1;
                if (yy < 0 || yy >= in.H || xx < 0 || xx >= in.W) continue;
                h += w.output_conv2_0.weight[((o * Fh + c) * 3 + i) * 3 + j] * feat[(c * in.H + yy) * in.W + xx];
              }
          logit += w.output_conv2_2.weight[o] * std::max(h, 0.0);
        }
        CHECK(std::exp(logit) == Approx(depth_map[f * full + y * in.W + x]).epsilon(1e-12));
      }
  // The fused map is finite and not all zero.
  double norm = 0;
  for (double v : fused) norm += v * v;
  CHECK(std::isfinite(norm));
  CHECK(norm > 0);
}

TEST_CASE("DPT head parameter names match the VGGT-1B state_dict layout", "[dpt_head]") {
  const auto expected = heads_test::vggt1b_layout_shapes("depth_head.");
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, DptHeadConfig{});
  const auto ours = heads_test::spec_shapes(specs);
  CHECK(ours.size() == specs.size());
  CHECK(expected.size() > 50);
  CHECK(ours == expected);
}

TEST_CASE("DPT head loading lists every missing, mis-shaped and unexpected tensor", "[dpt_head]") {
  const DptHeadConfig cfg = dpt_head_config_from_vggt_json(heads_test::bundle_config());
  safetensors::Writer writer;
  for (const auto& t : heads_test::bundle().tensors()) {
    if (t.name.rfind("param.depth_head.", 0) != 0) continue;
    if (t.name == "param.depth_head.scratch.layer2_rn.weight") continue;  // missing
    if (t.name == "param.depth_head.projects.1.bias") {                   // wrong shape
      std::vector<float> v(33, 0.0f);
      writer.add_raw(t.name, safetensors::Dtype::F32, {33}, v.data(), v.size() * 4);
      continue;
    }
    writer.add_raw(t.name, t.dtype, t.shape, heads_test::bundle().bytes(t), t.end - t.begin);
  }
  const float one = 1.0f;
  writer.add_raw("param.depth_head.scratch.extra.weight", safetensors::Dtype::F32, {1}, &one, 4);
  const auto path = std::filesystem::temp_directory_path() / ("flexsplat_dpt_bad_" + std::to_string(::getpid()) + ".safetensors");
  writer.write(path);
  io::ParamSource<float> src(safetensors::File::open(path), "param.");
  try {
    load_dpt_head_weights(src, cfg);
    FAIL("loading should have failed");
  } catch (const Error& e) {
    const std::string msg = e.what();
    INFO(msg);
    CHECK_THAT(msg, Catch::Contains("1 missing") && Catch::Contains("param.depth_head.scratch.layer2_rn.weight [32, 32, 3, 3]"));
    CHECK_THAT(msg, Catch::Contains("1 with the wrong shape") &&
                        Catch::Contains("param.depth_head.projects.1.bias is [33], expected [32]"));
    CHECK_THAT(msg, Catch::Contains("1 unexpected") && Catch::Contains("param.depth_head.scratch.extra.weight"));
  }
  std::filesystem::remove(path);
}

TEST_CASE("DPT head rejects inconsistent inputs with clear errors", "[dpt_head]") {
  const auto json = heads_test::bundle_config();
  const DptHeadConfig cfg = dpt_head_config_from_vggt_json(json);
  io::ParamSource<float> src(heads_test::bundle(), "param.");
  const auto w = load_dpt_head_weights(src, cfg);
  const CaseInputs in = load_case(2, json.at("depth").get<index_t>());
  std::vector<const float*> layers;
  for (auto& l : in.layers) layers.push_back(l.data());
  const index_t ph = 4, pw = 4;
  std::vector<float> ws(static_cast<std::size_t>(dpt_head_workspace_size(cfg, ph, pw)));
  std::vector<float> depth_map(in.H * in.W), conf(in.H * in.W);
  DptHeadOutputs<float> out{depth_map.data(), conf.data()};
  CHECK_THROWS_WITH(dpt_head_forward<float>(out, cfg, w, layers, 1, in.tokens, 5, 70, 56, ws),
                    Catch::Contains("21 tokens per frame") && Catch::Contains("5x4 grid"));
  CHECK_THROWS_WITH(dpt_head_forward<float>(out, cfg, w, std::span<const float* const>(layers.data(), 2), 1, in.tokens,
                                            5, in.H, in.W, ws),
                    Catch::Contains("intermediate layer 2"));
  CHECK_THROWS_WITH(dpt_head_forward<float>(out, cfg, w, layers, 1, in.tokens, 5, in.H, in.W,
                                            std::span<float>(ws.data(), ws.size() / 2)),
                    Catch::Contains("workspace"));
  CHECK_THROWS_WITH(dpt_head_forward<float>(out, cfg, w, layers, 1, in.tokens, 5, 10, 56, ws),
                    Catch::Contains("smaller than one"));
  DptHeadConfig bad = cfg;
  bad.features = 30;  // features/2 = 15 cannot carry the sin/cos embedding
  CHECK_THROWS_WITH(bad.validate(), Catch::Contains("divisible by 4"));
  CHECK_THROWS_WITH(dpt_head_config_from_vggt_json(nlohmann::json{{"out_channels", {1, 2}}}),
                    Catch::Contains("out_channels"));
}
