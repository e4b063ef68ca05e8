#include <catch2/catch.hpp>

#include <map>

#include "flexsplat/geometry/dpt_head.hpp"
#include "heads_bundle.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

// Converted copies of the bundle's depth_head parameters.
template <class T>
struct BundleDptWeights {
  std::map<std::string, std::vector<T>> storage;
  DptHeadWeights<T> weights;
  explicit BundleDptWeights(const DptHeadConfig& cfg) {
    weights = bind_dpt_head_weights<T>(cfg, [&](const std::string& name, const std::vector<index_t>& shape) {
      const auto& info = heads_test::bundle().info("param.depth_head." + name);
      REQUIRE(info.shape == shape);
      auto& v = storage[name];
      v.resize(static_cast<std::size_t>(info.numel()));
      heads_test::bundle().convert(info, v.data());
      return static_cast<const T*>(v.data());
    });
  }
};

template <class T>
void run_bundle_cases() {
  const auto json = heads_test::bundle_config();
  const DptHeadConfig cfg = dpt_head_config_from_vggt_json(json);
  const BundleDptWeights<T> w(cfg);
  const index_t depth = json.at("depth").get<index_t>();
  const auto cases = heads_test::bundle_cases();
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const auto [S, H, W] = cases[k];
    const std::string p = "case" + std::to_string(k) + ".";
    std::vector<std::vector<T>> outs;
    std::vector<const T*> layers;
    for (index_t i = 0; i < depth; ++i) outs.push_back(heads_test::read<T>(p + "aggregator.out." + std::to_string(i)));
    for (auto& o : outs) layers.push_back(o.data());
    const auto& info = heads_test::bundle().info(p + "aggregator.out.0");
    const index_t tokens = info.shape[2];
    REQUIRE(info.shape[3] == cfg.dim_in);
    const index_t ph = H / cfg.patch_size, pw = W / cfg.patch_size;
    std::vector<T> ws(static_cast<std::size_t>(dpt_head_workspace_size(cfg, ph, pw)));
    std::vector<T> depth_map(S * H * W), conf(S * H * W);
    DptHeadOutputs<T> out;
    out.preds = depth_map.data();
    out.conf = conf.data();
    dpt_head_forward<T>(out, cfg, w.weights, layers, S, tokens, tokens - ph * pw, H, W, ws);
    heads_test::check_close(p + "depth", depth_map, heads_test::read<float>(p + "depth"));
    heads_test::check_close(p + "depth_conf", conf, heads_test::read<float>(p + "depth_conf"));
    const double rel = heads_test::max_elementwise_rel(depth_map, heads_test::read<float>(p + "depth"), 0.0);
    INFO("depth element-wise relative error " << rel);
    CHECK(rel <= 1e-4);
  }
}

}  // namespace

TEST_CASE("DPT head reproduces the bundle's depth and confidence (float)", "[dpt_head]") { run_bundle_cases<float>(); }

TEST_CASE("DPT head reproduces the bundle's depth and confidence (double)", "[dpt_head]") { run_bundle_cases<double>(); }
