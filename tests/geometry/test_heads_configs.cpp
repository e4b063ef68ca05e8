// The heads on configurations other than the bundle's: float and double runs of the same random weights agree,
// every output is finite, and nothing depends on VGGT-1B's sizes.
#include <catch2/catch.hpp>

#include <random>

#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/geometry/dpt_head.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

namespace {

template <class T>
void add_random(io::ParamSource<T>& src, const std::vector<io::TensorSpec>& specs, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  for (const auto& s : specs) {
    index_t n = 1;
    for (index_t e : s.shape) n *= e;
    const double scale = s.shape.size() >= 2 ? 1.0 / std::sqrt(static_cast<double>(n / s.shape[0])) : 0.3;
    std::vector<T> v(static_cast<std::size_t>(n));
    for (auto& x : v) x = static_cast<T>(scale * normal(rng));
    src.add(s.name, s.shape, std::move(v));
  }
}

std::vector<double> random_tokens(std::size_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  std::vector<double> v(n);
  for (auto& x : v) x = normal(rng);
  return v;
}

template <class T>
std::vector<double> run_camera(const CameraHeadConfig& cfg, const std::vector<double>& tokens, index_t S, index_t n_tok) {
  std::vector<io::TensorSpec> specs;
  append_camera_head_specs(specs, cfg);
  io::ParamSource<T> src;
  add_random(src, specs, 99);
  const auto w = load_camera_head_weights(src, cfg);
  const std::vector<T> in(tokens.begin(), tokens.end());
  std::vector<T> ws(static_cast<std::size_t>(camera_head_workspace_size(cfg, S))), enc(cfg.iterations * S * 9);
  camera_head_forward<T>(enc.data(), cfg, w, in.data(), S, n_tok, ws);
  return {enc.begin(), enc.end()};
}

template <class T>
std::vector<double> run_dpt(const DptHeadConfig& cfg, const std::vector<double>& tokens, index_t layers_n, index_t S,
                            index_t H, index_t W, index_t patch_start) {
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, cfg);
  io::ParamSource<T> src;
  add_random(src, specs, 77);
  const auto w = load_dpt_head_weights(src, cfg);
  const std::vector<T> in(tokens.begin(), tokens.end());
  const index_t ph = H / cfg.patch_size, pw = W / cfg.patch_size, n_tok = patch_start + ph * pw;
  std::vector<const T*> layers;
  for (index_t i = 0; i < layers_n; ++i) layers.push_back(in.data() + i * S * n_tok * cfg.dim_in);
  std::vector<T> ws(static_cast<std::size_t>(dpt_head_workspace_size(cfg, ph, pw)));
  const index_t full = ph * cfg.patch_size * pw * cfg.patch_size;
  std::vector<T> preds(S * full * (cfg.output_dim - 1)), conf(S * full);
  dpt_head_forward<T>({preds.data(), conf.data()}, cfg, w, layers, S, n_tok, patch_start, H, W, ws);
  std::vector<double> out(preds.begin(), preds.end());
  out.insert(out.end(), conf.begin(), conf.end());
  return out;
}

void check_agree(const std::vector<double>& a, const std::vector<double>& b, double tol) {
  REQUIRE(a.size() == b.size());
  double max_abs = 0, max_err = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    REQUIRE(std::isfinite(a[i]));
    REQUIRE(std::isfinite(b[i]));
    max_abs = std::max(max_abs, std::abs(b[i]));
    max_err = std::max(max_err, std::abs(a[i] - b[i]));
  }
  INFO("max abs error " << max_err << " of max abs " << max_abs);
  CHECK(max_abs > 0);
  CHECK(max_err <= tol * max_abs);
}

}  // namespace

TEST_CASE("camera head on other configs: float agrees with double", "[camera_head][configs]") {
  for (index_t trunk_depth : {0, 1, 3}) {
    CameraHeadConfig cfg;
    cfg.dim = 48;
    cfg.num_heads = 3;
    cfg.trunk_depth = trunk_depth;
    cfg.iterations = 2 + trunk_depth;
    cfg.mlp_ratio = 2.0;
    const index_t S = 5, n_tok = 7;
    const auto tokens = random_tokens(S * n_tok * cfg.dim, 3);
    const auto f = run_camera<float>(cfg, tokens, S, n_tok);
    const auto d = run_camera<double>(cfg, tokens, S, n_tok);
    CHECK(f.size() == static_cast<std::size_t>(cfg.iterations * S * 9));
    check_agree(f, d, 1e-5);
  }
}

TEST_CASE("DPT head on other configs: float agrees with double", "[dpt_head][configs]") {
  DptHeadConfig cfg;
  cfg.dim_in = 24;
  cfg.patch_size = 7;
  cfg.features = 24;  // head features 12
  cfg.out_channels = {8, 12, 16, 20};
  cfg.intermediate_layer_idx = {2, 0, 1, 2};
  cfg.output_dim = 3;  // two prediction channels and the confidence
  cfg.activation = DptActivation::inv_log;
  cfg.conf_activation = DptConfActivation::sigmoid;
  const index_t S = 2, H = 35, W = 21, patch_start = 3, layers_n = 3;  // 5 x 3 patch grid: odd sizes everywhere
  const auto tokens = random_tokens(layers_n * S * (patch_start + 15) * cfg.dim_in, 5);
  const auto f = run_dpt<float>(cfg, tokens, layers_n, S, H, W, patch_start);
  const auto d = run_dpt<double>(cfg, tokens, layers_n, S, H, W, patch_start);
  check_agree(f, d, 1e-5);
  // Sizes that are not multiples of the patch give maps of the covered area (as VGGT does).
  const auto g = run_dpt<double>(cfg, tokens, layers_n, S, H + 4, W + 6, patch_start);
  CHECK(g.size() == d.size());
  bool any_diff = false;  // the embedding's aspect ratio follows the full image size
  for (std::size_t i = 0; i < g.size(); ++i) any_diff = any_diff || g[i] != d[i];
  CHECK(any_diff);
}
