#include <catch2/catch.hpp>

#include <cstdint>
#include <numeric>

#include "flexsplat/decoder/param_names.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/optim/params.hpp"
#include "optim_test_util.hpp"

using namespace flexsplat;
using train_test::tiny_model_config;

TEST_CASE("decoder names cover ModelParamLayout exactly, in order and at its offsets", "[train][params]") {
  for (index_t levels : {1, 2}) {
    auto cfg = tiny_model_config();
    cfg.unet.levels = levels;
    std::vector<io::TensorSpec> specs;
    decoder::append_model_specs(specs, cfg);
    std::vector<index_t> offsets;
    index_t at = 0;
    for (const auto& s : specs) {
      offsets.push_back(at);
      at += std::accumulate(s.shape.begin(), s.shape.end(), index_t{1}, std::multiplies<>());
    }
    const decoder::ModelParamLayout L(cfg);
    REQUIRE(at == L.size);
    auto offset_of = [&](const std::string& name) {
      for (std::size_t i = 0; i < specs.size(); ++i)
        if (specs[i].name == name) return offsets[i];
      FAIL("no tensor " << name);
      return index_t{-1};
    };
    // UNet: every convolution's weight and bias offset.
    const auto convs = decoder::unet_convs(cfg.unet);
    std::size_t k = 0;
    for (const auto& v : convs) {
      CHECK(offsets[k++] == L.unet + v.weight);
      CHECK(offsets[k++] == L.unet + v.bias);
    }
    CHECK(specs[2].name == "unet.encoder.0.down.weight");
    const decoder::FusionParamLayout F(cfg.fusion);
    CHECK(offset_of("fusion.depth_proj.weight") == L.fusion + F.proj_w);
    CHECK(offset_of("fusion.depth_proj.bias") == L.fusion + F.proj_b);
    CHECK(offset_of("fusion.refine.weight") == L.fusion + F.refine_w);
    CHECK(offset_of("fusion.refine.bias") == L.fusion + F.refine_b);
    CHECK(offset_of("fusion.reduce.weight") == L.fusion + F.reduce_w);
    CHECK(offset_of("fusion.reduce.bias") == L.fusion + F.reduce_b);
    CHECK(offset_of("fusion.rgb_head.weight") == L.fusion + F.rgb_w);
    CHECK(offset_of("fusion.rgb_head.bias") == L.fusion + F.rgb_b);
    const decoder::DecoderParamLayout D(cfg.decoder);
    CHECK(offset_of("decoder.query_embeddings") == L.decoder + D.embeddings);
    CHECK(offset_of("decoder.init_head.weight") == L.decoder + D.init_head_w);
    CHECK(offset_of("decoder.init_head.bias") == L.decoder + D.init_head_b);
    const decoder::MVDeformParamLayout M(cfg.decoder.deform());
    const decoder::SelfAttentionParamLayout S(cfg.decoder.self_attention());
    for (index_t l = 0; l < cfg.decoder.layers; ++l) {
      const auto& o = D.layer[static_cast<std::size_t>(l)];
      const std::string p = "decoder.layers." + std::to_string(l) + ".";
      const index_t base = L.decoder;
      CHECK(offset_of(p + "deform_attn.value_proj.weight") == base + o.deform + M.value_w);
      CHECK(offset_of(p + "deform_attn.value_proj.bias") == base + o.deform + M.value_b);
      CHECK(offset_of(p + "deform_attn.sampling_offsets.weight") == base + o.deform + M.offset_w);
      CHECK(offset_of(p + "deform_attn.sampling_offsets.bias") == base + o.deform + M.offset_b);
      CHECK(offset_of(p + "deform_attn.attention_weights.weight") == base + o.deform + M.logit_w);
      CHECK(offset_of(p + "deform_attn.attention_weights.bias") == base + o.deform + M.logit_b);
      CHECK(offset_of(p + "deform_attn.output_proj.weight") == base + o.deform + M.out_w);
      CHECK(offset_of(p + "deform_attn.output_proj.bias") == base + o.deform + M.out_b);
      CHECK(offset_of(p + "norm1.weight") == base + o.ln1_g);
      CHECK(offset_of(p + "norm1.bias") == base + o.ln1_b);
      CHECK(offset_of(p + "self_attn.qkv.weight") == base + o.attn + S.qkv_w);
      CHECK(offset_of(p + "self_attn.qkv.bias") == base + o.attn + S.qkv_b);
      CHECK(offset_of(p + "self_attn.proj.weight") == base + o.attn + S.out_w);
      CHECK(offset_of(p + "self_attn.proj.bias") == base + o.attn + S.out_b);
      CHECK(offset_of(p + "norm2.weight") == base + o.ln2_g);
      CHECK(offset_of(p + "norm2.bias") == base + o.ln2_b);
      CHECK(offset_of(p + "ffn.fc1.weight") == base + o.ffn_w1);
      CHECK(offset_of(p + "ffn.fc1.bias") == base + o.ffn_b1);
      CHECK(offset_of(p + "ffn.fc2.weight") == base + o.ffn_w2);
      CHECK(offset_of(p + "ffn.fc2.bias") == base + o.ffn_b2);
      CHECK(offset_of(p + "norm3.weight") == base + o.ln3_g);
      CHECK(offset_of(p + "norm3.bias") == base + o.ln3_b);
      CHECK(offset_of(p + "head.weight") == base + o.head_w);
      CHECK(offset_of(p + "head.bias") == base + o.head_b);
    }
  }
}

TEST_CASE("weight decay rule: matrices decay, vectors, tokens and embeddings do not", "[train][params]") {
  using train::default_weight_decay;
  CHECK(default_weight_decay("aggregator.frame_blocks.0.attn.qkv.weight", {192, 64}));
  CHECK(default_weight_decay("aggregator.patch_embed.patch_embed.proj.weight", {64, 3, 14, 14}));
  CHECK(default_weight_decay("unet.stem.weight", {2, 3, 3, 3}));
  CHECK_FALSE(default_weight_decay("aggregator.frame_blocks.0.attn.qkv.bias", {192}));
  CHECK_FALSE(default_weight_decay("aggregator.frame_blocks.0.norm1.weight", {64}));
  CHECK_FALSE(default_weight_decay("aggregator.frame_blocks.0.ls1.gamma", {64}));
  CHECK_FALSE(default_weight_decay("aggregator.camera_token", {1, 2, 1, 64}));
  CHECK_FALSE(default_weight_decay("aggregator.register_token", {1, 2, 4, 64}));
  CHECK_FALSE(default_weight_decay("aggregator.patch_embed.pos_embed", {1, 50, 64}));
  CHECK_FALSE(default_weight_decay("aggregator.patch_embed.mask_token", {1, 64}));
  CHECK_FALSE(default_weight_decay("camera_head.empty_pose_tokens", {1, 1, 9}));
  CHECK_FALSE(default_weight_decay("decoder.query_embeddings", {7, 8}));
}

TEST_CASE("store: segments are 64-byte aligned and contiguous, tensors reachable by name", "[train][params]") {
  train::ParamStore<float> store;
  const index_t a = store.add_segment("first", {{"a.weight", {3, 5}}, {"a.bias", {3}}});
  const index_t b = store.add_segment("second", {{"b.weight", {2, 2}}});
  CHECK(a == 0);
  CHECK(b == 32);  // 18 elements rounded up to 16-float (64-byte) boundaries
  CHECK(store.info("a.bias").offset == 15);
  CHECK(store.size() == 36);
  CHECK(store.tensor_elements() == 22);
  CHECK_THROWS_WITH(store.add_segment("third", {{"a.bias", {1}}}), Catch::Contains("'a.bias' registered twice"));
  CHECK_THROWS_WITH(store.params(), Catch::Contains("not allocated"));
  store.allocate();
  CHECK(reinterpret_cast<std::uintptr_t>(store.params()) % 64 == 0);
  CHECK(reinterpret_cast<std::uintptr_t>(store.segment_params("second")) % 64 == 0);
  CHECK(store.param("b.weight").data() == store.params() + 32);
  CHECK(store.grad("a.bias").size() == 3);
  CHECK(store.tensors()[1].name == "a.bias");
  CHECK_THROWS_WITH(store.info("nope"), Catch::Contains("no tensor 'nope'"));
  CHECK_THROWS_WITH(store.add_segment("late", {}), Catch::Contains("after allocate()"));
}

TEST_CASE("geometry binds into the store without copies and runs as from the mmapped file", "[train][params]") {
  const auto cfg = train_test::tiny_vggt_config();
  const auto file = safetensors::File::open(train_test::vggt_bundle_path());
  train::ParamStore<float> store;
  store.add_segment("geometry", geometry::vggt_parameter_specs(cfg));
  std::vector<io::TensorSpec> model_specs;
  decoder::append_model_specs(model_specs, tiny_model_config());
  store.add_segment("model", model_specs);
  store.allocate(false);
  for (const auto& t : store.tensors())
    if (t.name.rfind("unet.", 0) != 0 && t.name.rfind("fusion.", 0) != 0 && t.name.rfind("decoder.", 0) != 0)
      file.convert(file.info("param." + t.name), store.params() + t.offset);

  io::ParamSource<float> views;
  store.bind_views(views, "geometry");
  const auto w = geometry::load_vggt_weights(views, cfg);
  CHECK(w.camera.trunk[0].qkv_weight == store.param("camera_head.trunk.0.attn.qkv.weight").data());
  CHECK(views.converted_bytes() == 0);

  auto from_file = geometry::VggtCheckpoint<float>::open(train_test::vggt_bundle_path(), cfg, "param.");
  const auto images = file.get<float, 5>("case2.images");
  geometry::VggtWorkspace<float> ws;
  const auto a = geometry::vggt_forward<float>(images.data(), 1, images.shape(3), images.shape(4), cfg, w, ws);
  const auto b =
      geometry::vggt_forward<float>(images.data(), 1, images.shape(3), images.shape(4), cfg, from_file->weights, ws);
  REQUIRE(a.depth.size() == b.depth.size());
  for (index_t i = 0; i < a.depth.size(); ++i) REQUIRE(a.depth.data()[i] == b.depth.data()[i]);
}
