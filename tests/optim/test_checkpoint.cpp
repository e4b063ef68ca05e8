#include <catch2/catch.hpp>

#include <cstring>
#include <random>

#include "flexsplat/core/half.hpp"
#include "flexsplat/decoder/param_names.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/optim/checkpoint.hpp"
#include "optim_test_util.hpp"

using namespace flexsplat;
using train_test::TempPath;

namespace {
train::ParamStore<float> small_store(bool training = true) {
  train::ParamStore<float> store;
  std::vector<io::TensorSpec> specs;
  decoder::append_model_specs(specs, train_test::tiny_model_config());
  store.add_segment("head", {{"head.weight", {4, 3}}, {"head.bias", {4}}});
  store.add_segment("model", specs);
  store.allocate(training);
  return store;
}
void fill(train::ParamStore<float>& s, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> n;
  for (index_t i = 0; i < s.size(); ++i) {
    s.params()[i] = n(rng);
    if (s.training()) s.adam_m()[i] = n(rng), s.adam_v()[i] = std::abs(n(rng));
  }
}
bool same_bits(const float* a, const float* b, index_t n) { return std::memcmp(a, b, sizeof(float) * n) == 0; }
}  // namespace

TEST_CASE("checkpoint: training state round-trips bit-exactly with config, step and RNG", "[train][checkpoint]") {
  auto a = small_store();
  fill(a, 1);
  std::mt19937_64 rng(77);
  rng.discard(13);
  const nlohmann::json config = {{"decoder", {{"dim", 8}}}, {"lr", 1e-4}};
  const TempPath file("flexsplat_ckpt");
  train::save_training_state(file.path, a, config, {1234, train::rng_state_string(rng)});

  auto b = small_store();
  const auto info = train::load_checkpoint(file.path, b, true, &config);
  CHECK(info.format == "training_state");
  CHECK(info.config == config);
  CHECK(info.state.step == 1234);
  CHECK(info.optimizer_state);
  CHECK(same_bits(a.params(), b.params(), a.size()));
  CHECK(same_bits(a.adam_m(), b.adam_m(), a.size()));
  CHECK(same_bits(a.adam_v(), b.adam_v(), a.size()));
  std::mt19937_64 restored;
  train::restore_rng_state(restored, info.state.rng_state);
  CHECK(restored() == rng());

  // A model file loads params only; a training state also loads into an inference store.
  const TempPath model("flexsplat_model");
  train::save_model(model.path, a, config, 7);
  auto c = small_store(false);
  CHECK_FALSE(train::load_checkpoint(file.path, c).optimizer_state);
  CHECK(same_bits(a.params(), c.params(), a.size()));
  auto d = small_store();
  const auto model_info = train::load_checkpoint(model.path, d);
  CHECK(model_info.format == "model");
  CHECK(model_info.state.step == 7);
  CHECK_FALSE(model_info.optimizer_state);
  CHECK(same_bits(a.params(), d.params(), a.size()));
  const nlohmann::json other = {{"lr", 2e-4}};
  CHECK_THROWS_WITH(train::load_checkpoint(model.path, d, true, &other), Catch::Contains("configuration differs"));
}

TEST_CASE("checkpoint: one error lists every missing, mis-shaped and unexpected tensor", "[train][checkpoint]") {
  train::ParamStore<float> written;
  written.add_segment("s", {{"a", {2, 3}}, {"b", {4}}, {"extra", {1}}, {"c", {5}}});
  written.allocate();
  const TempPath file("flexsplat_bad");
  train::save_training_state(file.path, written, nlohmann::json::object(), {});

  train::ParamStore<float> store;
  store.add_segment("s", {{"a", {2, 3}}, {"b", {2, 2}}, {"missing_one", {3}}, {"c", {5}}});
  store.allocate();
  store.params()[0] = 42.f;
  try {
    train::load_checkpoint(file.path, store);
    FAIL("no error");
  } catch (const Error& e) {
    const std::string m = e.what();
    INFO(m);
    CHECK(m.find("3 missing:\n    missing_one [3]\n    optimizer.adam_m.missing_one [3]") != std::string::npos);
    CHECK(m.find("b is [4], expected [2, 2]") != std::string::npos);
    CHECK(m.find("optimizer.adam_v.b is [4], expected [2, 2]") != std::string::npos);
    CHECK(m.find("3 unexpected:\n    extra [1]\n    optimizer.adam_m.extra [1]\n    optimizer.adam_v.extra [1]") !=
          std::string::npos);
  }
  CHECK(store.params()[0] == 42.f);  // nothing written on error
  // A VGGT file is not a flexsplat checkpoint.
  CHECK_THROWS_WITH(train::load_checkpoint(train_test::vggt_bundle_path(), store), Catch::Contains("load_vggt_geometry"));
}

TEST_CASE("checkpoint: a VGGT-layout file (F16 and BF16, extra heads) initialises the geometry segment", "[train][checkpoint]") {
  const auto cfg = train_test::tiny_vggt_config();
  const auto bundle = safetensors::File::open(train_test::vggt_bundle_path());
  const auto specs = geometry::vggt_parameter_specs(cfg);
  // The bundle's tensors converted: F16 for the aggregator, BF16 elsewhere, plus point and track head tensors.
  safetensors::Writer w;
  for (const auto& s : specs) {
    const auto& info = bundle.info("param." + s.name);
    std::vector<float> v(static_cast<std::size_t>(info.numel()));
    bundle.convert(info, v.data());
    if (s.name.rfind("aggregator.", 0) == 0) {
      std::vector<f16> h;
      for (float x : v) h.emplace_back(x);
      w.add_raw(s.name, safetensors::Dtype::F16, s.shape, h.data(), h.size() * 2);
    } else {
      std::vector<bf16> h;
      for (float x : v) h.emplace_back(x);
      w.add_raw(s.name, safetensors::Dtype::BF16, s.shape, h.data(), h.size() * 2);
    }
  }
  const float junk[3] = {1, 2, 3};
  w.add_raw("track_head.fnet.weight", safetensors::Dtype::F32, {3}, junk, sizeof junk);
  w.add_raw("point_head.scratch.weight", safetensors::Dtype::F32, {3}, junk, sizeof junk);
  const TempPath file("flexsplat_vggt_half");
  w.write(file.path);

  train::ParamStore<float> store;
  store.add_segment("geometry", specs);
  std::vector<io::TensorSpec> model_specs;
  decoder::append_model_specs(model_specs, train_test::tiny_model_config());
  store.add_segment("model", model_specs);
  store.allocate();
  train::load_vggt_geometry(file.path, store);
  const auto f = safetensors::File::open(file.path);
  for (const auto& s : specs) {
    const auto p = store.param(s.name);
    std::vector<float> expected(p.size());
    f.convert(f.info(s.name), expected.data());
    REQUIRE(std::memcmp(p.data(), expected.data(), p.size_bytes()) == 0);
  }
  for (float x : store.param("decoder.query_embeddings")) REQUIRE(x == 0.f);  // decoder untouched

  // The bundle itself, with its "param." prefix and reference tensors under other names.
  train::load_vggt_geometry(train_test::vggt_bundle_path(), store, "geometry", "param.");
  const auto qkv = bundle.get<float, 2>("param.aggregator.frame_blocks.0.attn.qkv.weight");
  CHECK(std::memcmp(store.param("aggregator.frame_blocks.0.attn.qkv.weight").data(), qkv.data(), qkv.size() * 4) == 0);

  // A store whose geometry differs from the file: every problem at once.
  auto wrong = specs;
  wrong.erase(wrong.begin() + 3);
  wrong[5].shape = {1};
  wrong.push_back({"depth_head.not_in_file", {2}});
  train::ParamStore<float> other;
  other.add_segment("geometry", wrong);
  other.allocate(false);
  try {
    train::load_vggt_geometry(file.path, other);
    FAIL("no error");
  } catch (const Error& e) {
    const std::string m = e.what();
    INFO(m);
    CHECK(m.find("1 missing:\n    depth_head.not_in_file [2]") != std::string::npos);
    CHECK(m.find("1 with the wrong shape:\n    " + specs[6].name) != std::string::npos);
    CHECK(m.find("1 unexpected:\n    " + specs[3].name) != std::string::npos);
    CHECK(m.find("track_head") == std::string::npos);
  }
}
