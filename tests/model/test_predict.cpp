#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <memory>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/raster/render.hpp"
#include "skip.hpp"

using namespace flexsplat;

namespace {
data::SceneSample predict_scene(int inputs, int targets, std::uint64_t seed) {
  data::GeneratorConfig g;
  g.size = 28;
  g.supersample = 2;
  data::BatchOptions o;
  o.inputs = inputs;
  o.targets = targets;
  o.structured_inputs = false;
  return data::generate_batch(g, 1, seed, 0, o)[0];
}

// The tiny model with a 4-channel match head on random weights, and a 3-view example at its size.
struct MatchHeadCase {
  model::FlexSplatConfig c = [] {
    auto cfg = model::flexsplat_tiny_config();
    cfg.geometry.match_dim = 4;
    return cfg;
  }();
  std::unique_ptr<model::FlexSplatWeights<float>> w = model::FlexSplatWeights<float>::create(c, false);
  model::TrainExample<float> e = model::make_train_example<float>(predict_scene(3, 0, 4), c);
  MatchHeadCase() { w->init(8); }
};

template <class A, class B>
double max_rel_diff(const A* a, const B* b, std::size_t n) {
  double m = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const double x = static_cast<double>(a[i]), y = static_cast<double>(b[i]);
    m = std::max(m, std::abs(x - y) / (1.0 + std::abs(y)));
  }
  return m;
}
}  // namespace

TEST_CASE("predict gives the cameras, depth and Gaussians of the training path's forward", "[model][predict]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, true);
  w->init(11);
  const auto e = model::make_train_example<float>(predict_scene(3, 1, 4), c);
  model::StepConfig sc;
  sc.gaussians = 40;
  model::SceneWorkspace<float> tws;
  w->store().zero_grads();
  model::scene_gradient<float>(tws, *w, w->store().grads(), e, sc);
  const auto& tg = tws.geometry.result;
  const auto& tset = tws.objective.model.gaussians().back();

  model::PredictWorkspace<float> ws;
  const auto p = model::predict<float>(ws, *w, e.images.data(), e.views, 40);
  REQUIRE(p.views == 3);
  REQUIRE(p.gaussians.size() == 40);
  REQUIRE(p.pose_enc.size() == 27u);
  const auto& g = p.geometry;
  CHECK(max_rel_diff(g.extrinsics.data(), tg.extrinsics.data(), tg.extrinsics.size()) <= 1e-6);
  CHECK(max_rel_diff(g.K.data(), tg.K.data(), tg.K.size()) <= 1e-6);
  CHECK(max_rel_diff(g.depth.data(), tg.depth.data(), tg.depth.size()) <= 1e-6);
  CHECK(max_rel_diff(g.confidence.data(), tg.confidence.data(), tg.confidence.size()) <= 1e-6);
  CHECK(max_rel_diff(g.features.data(), tg.features.data(), tg.features.size()) <= 1e-6);
  const std::size_t last = static_cast<std::size_t>((tws.geometry.iterations - 1) * 27);
  CHECK(max_rel_diff(p.pose_enc.data(), tws.geometry.pose_enc.data() + last, 27) <= 1e-6);
  const auto& s = p.gaussians;
  CHECK(max_rel_diff(s.means.data(), tset.means.data(), static_cast<std::size_t>(tset.means.size())) <= 1e-6);
  CHECK(max_rel_diff(s.quats.data(), tset.quats.data(), static_cast<std::size_t>(tset.quats.size())) <= 1e-6);
  CHECK(max_rel_diff(s.scales.data(), tset.scales.data(), static_cast<std::size_t>(tset.scales.size())) <= 1e-6);
  CHECK(max_rel_diff(s.opacities.data(), tset.opacities.data(), static_cast<std::size_t>(tset.opacities.size())) <= 1e-6);
  CHECK(max_rel_diff(s.sh.data(), tset.sh.data(), static_cast<std::size_t>(tset.sh.size())) <= 1e-6);

  // A second call on the same workspace gives the same result (the geometry buffers were handed to the first).
  const auto q = model::predict<float>(ws, *w, e.images.data(), e.views, 40);
  CHECK(max_rel_diff(q.gaussians.means.data(), s.means.data(), static_cast<std::size_t>(s.means.size())) == 0);
  CHECK(q.geometry.extrinsics == g.extrinsics);
}

TEST_CASE("predict under bf16 with kept packed weights is bitwise the per-call bf16 prediction", "[model][predict]") {
  if constexpr (!have_bf16_gemm) FLEXSPLAT_SKIP("this build has no oneDNN: GemmBackend::bf16 is not available");
  auto w = model::load_flexsplat<float>(std::filesystem::path(FLEXSPLAT_SOURCE_DIR) / "models/flexsplat-small.safetensors");
  const auto& c = w->config();
  Tensor<float, 4> images(Shape<4>{4, 3, c.image_h, c.image_w});
  for (index_t i = 0; i < images.size(); ++i) images.data()[i] = float((i * 2654435761u) % 1000) / 999.0f;
  struct Restore {
    GemmBackend backend = default_gemm_backend();
    ~Restore() { set_default_gemm_backend(backend); }
  } restore;
  set_default_gemm_backend(GemmBackend::bf16);
  model::PredictWorkspace<float> per_call, kept;
  kept.keep_packed_weights = true;
  const auto a = model::predict<float>(per_call, *w, images.data(), 4);
  CHECK(per_call.packed_weights == nullptr);
  const auto b = model::predict<float>(kept, *w, images.data(), 4);
  REQUIRE(kept.packed_weights != nullptr);
  const std::size_t bytes = kept.packed_weights->packed_bytes();
  CHECK(bytes > 0);
  const auto b2 = model::predict<float>(kept, *w, images.data(), 4);
  CHECK(kept.packed_weights->packed_bytes() == bytes);  // reused
  auto same = [](const auto& x, const auto& y) {
    return x.size() == y.size() && std::memcmp(x.data(), y.data(), static_cast<std::size_t>(x.size()) * sizeof(float)) == 0;
  };
  for (const auto* p : {&b, &b2}) {
    CHECK(same(p->geometry.depth, a.geometry.depth));
    CHECK(same(p->geometry.extrinsics, a.geometry.extrinsics));
    CHECK(same(p->gaussians.means, a.gaussians.means));
    CHECK(same(p->gaussians.sh, a.gaussians.sh));
    CHECK(same(p->gaussians.opacities, a.gaussians.opacities));
  }
}

TEST_CASE("predict refuses wrong view counts, sizes, values and non-finite weights", "[model][predict]") {
  const auto c = model::flexsplat_tiny_config();
  auto w = model::FlexSplatWeights<float>::create(c, false);
  w->init(2);
  model::PredictWorkspace<float> ws;
  Tensor<float, 4> images(Shape<4>{5, 3, 28, 28}, 0.5f);
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, images.data(), 0), Catch::Contains("0 input views; the model takes 1 to 4"));
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, TensorView<const float, 4>(images.view())),
                    Catch::Contains("5 input views; the model takes 1 to 4"));
  Tensor<float, 4> wrong(Shape<4>{2, 3, 35, 35}, 0.5f);
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, TensorView<const float, 4>(wrong.view())),
                    Catch::Contains("[2, 3, 35, 35]") && Catch::Contains("the model takes [V, 3, 28, 28]"));
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, images.data(), 2, 65), Catch::Contains("65 Gaussians requested"));
  images.data()[7] = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, images.data(), 2), Catch::Contains("at flat index 7"));
  images.data()[7] = 0.5f;
  // NaN in the decoder's weights (VGGT checks its own outputs): the Gaussians are checked before they leave.
  const auto& seg = w->store().segment(model::appearance_segment);
  w->appearance()[seg.size - 1] = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, images.data(), 2), Catch::Contains("non-finite"));
  std::fill(w->appearance(), w->appearance() + seg.size, std::numeric_limits<float>::quiet_NaN());
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, images.data(), 2), Catch::Contains("non-finite"));
  w->store().param("camera_head.pose_branch.fc2.bias")[0] = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH(model::predict<float>(ws, *w, images.data(), 2), Catch::Contains("not finite"));
}

TEST_CASE("model views of the shared renders equal the data module's full-image training views", "[model][predict]") {
  const auto objects = data::load_objects({std::filesystem::path(FLEXSPLAT_SHARED_DIR) / "data/objects/spot"});
  const auto& rec = objects[0];
  REQUIRE(rec.input_views.size() == 4u);
  data::BatchOptions o;
  o.inputs = 4;
  o.targets = 0;
  o.crop = 28;
  o.scale_min = o.scale_max = 28.0 / rec.width;  // the window is the whole image
  const auto s = data::sample_batch(objects, 1, 0, 0, o)[0];
  std::vector<Tensor<float, 3>> rgba;
  for (int v : rec.input_views) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
  auto c = model::flexsplat_tiny_config();
  std::vector<model::ViewMapping> maps;
  const auto x = model::model_input<float>(rgba, c, &maps);
  REQUIRE(x.shape() == Shape<4>{4, 3, 28, 28});
  for (index_t v = 0; v < 4; ++v) {
    for (index_t y = 0; y < 28; ++y)
      for (index_t xx = 0; xx < 28; ++xx)
        for (int ch = 0; ch < 3; ++ch) REQUIRE(x(v, ch, y, xx) == s.inputs.rgb(v, y, xx, ch));
    double K[9];
    const auto& cam = rec.frames[static_cast<std::size_t>(rec.input_views[static_cast<std::size_t>(v)])].camera;
    for (int r = 0; r < 3; ++r)
      for (int col = 0; col < 3; ++col) K[3 * r + col] = cam.K[col][r];
    maps[static_cast<std::size_t>(v)].intrinsics(K);
    const auto& sk = s.inputs.cameras[static_cast<std::size_t>(v)].K;
    for (int r = 0; r < 3; ++r)
      for (int col = 0; col < 3; ++col) CHECK(K[3 * r + col] == Approx(sk[col][r]).epsilon(1e-12));
  }
  // A wide picture keeps its centred square; the crop moves the principal point.
  const model::ViewMapping m = model::view_mapping(300, 200, 28, 28);
  CHECK(m.x0 == 50);
  CHECK(m.y0 == 0);
  CHECK(m.width == 200);
  CHECK(m.height == 200);
  double K[9] = {100, 0, 150, 0, 100, 100, 0, 0, 1};
  m.intrinsics(K);
  CHECK(K[0] == Approx(14.0));
  CHECK(K[2] == Approx(14.0));
  CHECK(K[5] == Approx(14.0));
  Tensor<float, 3> rgb(Shape<3>{10, 10, 3}, 0.5f);
  CHECK_THROWS_WITH(model::model_input<float>({rgb}, c), Catch::Contains("image 0 of 1") && Catch::Contains("RGBA"));
}

TEST_CASE("photo targets carry the model's intrinsics to the refinement size through the model's window",
          "[model][predict]") {
  auto c = model::flexsplat_tiny_config();  // 28 x 28
  // A 300 x 200 picture: its centred 200 x 200 window is what the model saw.
  Tensor<float, 3> rgba(Shape<3>{200, 300, 4});
  for (index_t y = 0; y < 200; ++y)
    for (index_t x = 0; x < 300; ++x) {
      rgba(y, x, 0) = static_cast<float>(x) / 299.0f, rgba(y, x, 1) = static_cast<float>(y) / 199.0f;
      rgba(y, x, 2) = 0.25f, rgba(y, x, 3) = x < 150 ? 1.0f : 0.5f;
    }
  const std::vector<Tensor<float, 3>> photos{rgba, rgba};
  const std::array<index_t, 2> native = model::refine_size(photos, c);
  CHECK(native == std::array<index_t, 2>{200, 200});
  CHECK(model::refine_size(photos, c, 64) == std::array<index_t, 2>{64, 64});
  // The photo's camera seen by the model, carried back to the window at its own size and at 64 x 64.
  const double K_photo[9] = {180, 2, 160, 0, 170, 95, 0, 0, 1};
  double K_model[9];
  std::copy(K_photo, K_photo + 9, K_model);
  model::view_mapping(300, 200, 28, 28).intrinsics(K_model);
  std::vector<float> Km;
  for (int k = 0; k < 2; ++k) Km.insert(Km.end(), K_model, K_model + 9);
  const auto at_native = model::photo_targets<float>(photos, c, Km.data(), 200, 200);
  const double expect_native[9] = {180, 2, 110, 0, 170, 95, 0, 0, 1};  // x shifted by the window's 50 pixels
  for (int i = 0; i < 9; ++i) CHECK(at_native.K[static_cast<std::size_t>(9 + i)] == Approx(expect_native[i]).margin(1e-4));
  // From the photo's own K the same: the round trip through the model's window is the identity (to_source).
  const std::vector<double> own{K_photo, K_photo + 9};
  std::vector<double> both = own;
  both.insert(both.end(), own.begin(), own.end());
  const auto direct = model::photo_targets<float>(photos, both, 200, 200);
  for (int i = 0; i < 9; ++i) CHECK(direct.K[static_cast<std::size_t>(i)] == Approx(expect_native[i]).margin(1e-4));
  CHECK_THROWS_WITH(model::photo_targets<float>(photos, own, 200, 200),
                    Catch::Contains("9 intrinsics values for 2 photos"));
  const auto at_64 = model::photo_targets<float>(photos, c, Km.data(), 64, 64);
  const double s = 64.0 / 200.0;
  const double expect_64[9] = {180 * s, 2 * s, 110 * s, 0, 170 * s, 95 * s, 0, 0, 1};
  for (int i = 0; i < 9; ++i) CHECK(at_64.K[static_cast<std::size_t>(i)] == Approx(expect_64[i]).margin(1e-4));
  // At the model's size the targets are the model's input, in HWC.
  const auto at_model = model::photo_targets<float>(photos, c, Km.data(), 28, 28);
  const auto x = model::model_input<float>(photos, c);
  REQUIRE(at_model.images.size() == static_cast<std::size_t>(2 * 28 * 28 * 3));
  for (index_t v = 0; v < 2; ++v)
    for (index_t y = 0; y < 28; ++y)
      for (index_t xx = 0; xx < 28; ++xx)
        for (int ch = 0; ch < 3; ++ch)
          REQUIRE(at_model.images[static_cast<std::size_t>(((v * 28 + y) * 28 + xx) * 3 + ch)] == x(v, ch, y, xx));
  // At the window's own size the targets are its pixels composited on white (no resampling).
  for (index_t y : {0, 77, 199})
    for (index_t xx : {0, 99, 199}) {
      const float a = rgba(y, xx + 50, 3);
      CHECK(at_native.images[static_cast<std::size_t>((y * 200 + xx) * 3)] == Approx(rgba(y, xx + 50, 0) * a + (1 - a)));
    }
}

TEST_CASE("the evaluation protocol undoes a known similarity and scores ground-truth Gaussians above white",
          "[model][predict][eval]") {
  const auto objects = data::load_objects({std::filesystem::path(FLEXSPLAT_SHARED_DIR) / "data/objects/spot"});
  const auto& rec = objects[0];
  model::EvalOptions o;
  o.max_targets = 4;
  o.white_baseline = true;
  o.grid_targets = 2;
  std::vector<int> in, targets;
  model::eval_views(rec, o, in, targets);
  REQUIRE(in == rec.input_views);
  REQUIRE(targets.size() == 4u);
  // A "prediction" in another frame: the ground-truth cameras and surface points moved by a similarity.
  model::Similarity sim;
  sim.R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  sim.scale = 0.37;
  sim.t = Eigen::Vector3d(0.3, -1.2, 2.0);
  std::vector<float> pred_w2c;
  std::vector<std::array<float, 6>> points;
  for (int v : in) {
    const auto& fr = rec.frames[static_cast<std::size_t>(v)];
    double K[9], E[12];
    camera_arrays(fr.camera, K, E);
    model::transform_camera(E, sim);
    for (double e : E) pred_w2c.push_back(static_cast<float>(e));
    const auto depth = image::read_depth_png<double>(fr.depth, rec.depth_scale);
    const auto rgb = image::read_rgb<float>(fr.image);
    const auto& c = fr.camera;
    for (index_t y = 0; y < depth.shape(0); y += 4)
      for (index_t x = 0; x < depth.shape(1); x += 4) {
        const double z = depth(y, x);
        if (!(z > 0)) continue;
        const glm::dvec3 p = c.to_world({(x + 0.5 - c.K[2][0]) / c.K[0][0] * z, (y + 0.5 - c.K[2][1]) / c.K[1][1] * z, z});
        const Eigen::Vector3d q = sim.apply(Eigen::Vector3d(p.x, p.y, p.z));
        points.push_back({static_cast<float>(q.x()), static_cast<float>(q.y()), static_cast<float>(q.z()), rgb(y, x, 0),
                          rgb(y, x, 1), rgb(y, x, 2)});
      }
  }
  const index_t N = static_cast<index_t>(points.size());
  GaussianSet<float> g;
  g.means = Tensor<float, 2>(Shape<2>{N, 3});
  g.quats = Tensor<float, 2>(Shape<2>{N, 4});
  g.scales = Tensor<float, 2>(Shape<2>{N, 3});
  g.opacities = Tensor<float, 1>(Shape<1>{N}, 0.95f);
  g.sh = Tensor<float, 3>(Shape<3>{N, 1, 3});
  for (index_t i = 0; i < N; ++i) {
    const auto& pt = points[static_cast<std::size_t>(i)];
    for (int k = 0; k < 3; ++k) {
      g.means(i, k) = pt[static_cast<std::size_t>(k)];
      g.scales(i, k) = static_cast<float>(0.02 * sim.scale);
      g.sh(i, 0, k) = static_cast<float>((pt[static_cast<std::size_t>(3 + k)] - sh_color_offset) / sh_c0);
    }
    g.quats(i, 0) = 1, g.quats(i, 1) = g.quats(i, 2) = g.quats(i, 3) = 0;
  }
  model::EvalWorkspace ws;
  const auto r = model::score_prediction(rec, in, targets, pred_w2c.data(), g, 64, 64, o, ws);
  CHECK(r.rotation_error_deg < 0.01);
  CHECK(r.center_error_rel < 1e-5);
  CHECK(r.alignment.scale == Approx(1.0 / sim.scale).epsilon(1e-5));
  CHECK(r.object_size > 1.5);
  CHECK(r.object_size < 3.5);  // the mesh's bounding box spans [-1, 1] on its largest side
  CHECK(std::isnan(r.model.lpips));
  CHECK(r.model.psnr > r.white.psnr + 5);
  CHECK(r.model.ssim > r.white.ssim);
  REQUIRE(r.grid_gt.size() == 2u);
  // The white baseline by hand: mean over targets of 10 log10(1 / MSE(white, resized ground truth)).
  double expected = 0;
  std::vector<float> chw(3 * 64 * 64);
  for (int t : targets) {
    model::model_view<float>(chw.data(), TensorView<const float, 3>(image::read_float<float>(rec.frames[static_cast<std::size_t>(t)].image, 4).view()), 64, 64);
    double se = 0;
    for (float v : chw) se += (1.0 - v) * (1.0 - v);
    expected += 10 * std::log10(static_cast<double>(chw.size()) / se);
  }
  CHECK(r.white.psnr == Approx(expected / 4).epsilon(1e-9));

  // Counts and lists of input views.
  model::EvalOptions two;
  two.view_count = 2;
  model::eval_views(rec, two, in, targets);
  CHECK(in == std::vector<int>{0, 16});
  CHECK(targets.size() == 30u);
  two.view_list = {3, 3};
  CHECK_THROWS_WITH(model::eval_views(rec, two, in, targets), Catch::Contains("input view 3 is listed twice"));
  two.view_list = {40};
  CHECK_THROWS_WITH(model::eval_views(rec, two, in, targets), Catch::Contains("input view 40 is not a frame"));
}

TEST_CASE("true input cameras are the folder's, relative to the first input, in the predicted depth's units",
          "[model][predict][eval]") {
  const auto objects = data::load_objects({std::filesystem::path(FLEXSPLAT_SHARED_DIR) / "data/objects/spot"});
  const auto& rec = objects[0];
  const std::vector<int> in{3, 12, 25};  // three elevations
  const index_t h = 56, w = 56;
  model::GeometryResult<float> g;
  g.resize(3, h, w, 1, 1, 1);
  // A "predicted" depth half the true one on the surface, 1 on the background (no true depth there: not counted).
  for (index_t v = 0; v < 3; ++v) {
    const auto& fr = rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])];
    const auto depth = image::read_depth_png<double>(fr.depth, rec.depth_scale);
    const index_t H = depth.shape(0), W = depth.shape(1);
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x) {
        const double z = depth((y * H + H / 2) / h, (x * W + W / 2) / w);  // the pixel centre's nearest source pixel
        g.depth[static_cast<std::size_t>((v * h + y) * w + x)] = z > 0 ? static_cast<float>(0.5 * z) : 1.0f;
      }
  }
  const double s = model::true_input_cameras(rec, in, g);
  CHECK(s == Approx(0.5).epsilon(1e-6));
  for (int i = 0; i < 12; ++i)
    CHECK(g.extrinsics[static_cast<std::size_t>(i)] == Approx(i % 5 == 0 ? 1.0 : 0.0).margin(1e-6));
  const auto& K = rec.frames[12].camera.K;
  CHECK(g.K[9] == Approx(K[0][0] * 56.0 / rec.width).epsilon(1e-6));
  CHECK(g.K[9 + 2] == Approx(K[2][0] * 56.0 / rec.width).epsilon(1e-6));
  // The evaluation's alignment finds them exact, at twice the scale.
  model::EvalOptions o;
  std::vector<int> targets{0};
  const GaussianSet<float> none = make_gaussian_set<float>(0, 0);
  model::EvalWorkspace ws;
  const auto r = model::score_prediction(rec, in, targets, g.extrinsics.data(), none, h, w, o, ws);
  CHECK(r.rotation_error_deg < 0.05);  // the angle's acos of a float trace resolves no finer (about 0.03 deg)
  CHECK(r.center_error_rel < 1e-5);
  CHECK(r.alignment.scale == Approx(2.0).epsilon(1e-5));
  // No positive predicted depth where the object is: the scale is undefined.
  std::fill(g.depth.begin(), g.depth.end(), 0.0f);
  CHECK_THROWS_WITH(model::true_input_cameras(rec, in, g), Catch::Contains("the depth scale is undefined"));
  CHECK_THROWS_WITH(model::true_input_cameras(rec, std::vector<int>{3, 12}, g),
                    Catch::Contains("2 input views and a prediction of 3"));
}

TEST_CASE("with VGGT's two frame-token sets and two decoder view slots, reordering views 2..V reorders the cameras "
          "and leaves the renders unchanged",
          "[model][predict][permutation]") {
  auto c = model::flexsplat_tiny_config();
  c.appearance.decoder.view_slots = 2;
  c.appearance.decoder.max_queries = 128;  // 64 Gaussians of one view read rows 0, 2, ..., 126
  REQUIRE(c.geometry.aggregator.frame_tokens == 2);
  const index_t V = 4;
  c.appearance.decoder.max_views = V;
  c.validate();
  auto w = model::FlexSplatWeights<float>::create(c, false);
  w->init(23);
  const auto e = model::make_train_example<float>(predict_scene(int(V), 1, 9), c);
  const index_t plane = 3 * c.image_h * c.image_w;
  const index_t order[V] = {0, 3, 1, 2};  // the reference view stays first
  std::vector<float> permuted(e.images.size());
  for (index_t v = 0; v < V; ++v)
    std::copy(e.images.data() + order[v] * plane, e.images.data() + (order[v] + 1) * plane, permuted.data() + v * plane);
  model::PredictWorkspace<float> ws;
  const auto a = model::predict<float>(ws, *w, e.images.data(), V, 64);
  const auto b = model::predict<float>(ws, *w, permuted.data(), V, 64);
  for (index_t v = 0; v < V; ++v) {
    CAPTURE(v);
    CHECK(max_rel_diff(b.geometry.extrinsics.data() + 12 * v, a.geometry.extrinsics.data() + 12 * order[v], 12) <= 1e-4);
    CHECK(max_rel_diff(b.geometry.K.data() + 9 * v, a.geometry.K.data() + 9 * order[v], 9) <= 1e-4);
    const index_t px = c.image_h * c.image_w;
    CHECK(max_rel_diff(b.geometry.depth.data() + px * v, a.geometry.depth.data() + px * order[v],
                       static_cast<std::size_t>(px)) <= 1e-4);
  }
  // Each set rendered from every predicted camera of the first run: the same pictures.
  raster::RenderWorkspace<float> rws;
  raster::RenderOutputs<float> ra, rb;
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  double worst = 0, ink = 0;
  for (index_t v = 0; v < V; ++v) {
    raster::View<float> cam;
    const float* E = a.geometry.extrinsics.data() + 12 * v;
    const float* K = a.geometry.K.data() + 9 * v;
    for (int i = 0; i < 12; ++i) cam.world_to_camera[i] = E[i];
    cam.world_to_camera[12] = cam.world_to_camera[13] = cam.world_to_camera[14] = 0, cam.world_to_camera[15] = 1;
    cam.fx = K[0], cam.fy = K[4], cam.cx = K[2], cam.cy = K[5];
    cam.width = int(c.image_w), cam.height = int(c.image_h);
    raster::render_forward(a.gaussians, cam, ro, rws, ra);
    raster::render_forward(b.gaussians, cam, ro, rws, rb);
    for (index_t i = 0; i < ra.image.size(); ++i) {
      worst = std::max(worst, double(std::abs(ra.image.data()[i] - rb.image.data()[i])));
      ink = std::max(ink, 1.0 - double(ra.image.data()[i]));
    }
  }
  INFO("max pixel difference " << worst << ", darkest pixel below white " << ink);
  REQUIRE(ink > 0.05);  // the renders show Gaussians, not only the background
  CHECK(worst <= 1e-3);

  // With one decoder slot per view (the shipped model's design) the same reorder changes the Gaussians.
  auto per_view = c;
  per_view.appearance.decoder.view_slots = 0;
  auto w2 = model::FlexSplatWeights<float>::create(per_view, false);
  w2->init(23);
  model::PredictWorkspace<float> ws2;
  const auto a2 = model::predict<float>(ws2, *w2, e.images.data(), V, 64);
  const auto b2 = model::predict<float>(ws2, *w2, permuted.data(), V, 64);
  CHECK(max_rel_diff(a2.gaussians.means.data(), b2.gaussians.means.data(),
                     static_cast<std::size_t>(a2.gaussians.means.size())) > 1e-4);
}

TEST_CASE("with the match head, predict takes each view's camera from the view pairs' matches when placed and the "
          "camera head's otherwise", "[model][predict]") {
  const MatchHeadCase m;
  const auto& [c, w0, e] = m;
  // Random weights place a view from its matches or not by their seed: init 8 places neither view (no pair finds an
  // inlier match), init 4 places both (70 and 27 inliers here), so both branches run.
  for (const auto& [seed, placed] : {std::pair<unsigned, index_t>{8, 0}, {4, 2}}) {
    CAPTURE(seed);
    auto w = model::FlexSplatWeights<float>::create(c, false);
    w->init(seed);
    model::PredictWorkspace<float> ws;
    const auto p = model::predict<float>(ws, *w, e.images.data(), 3);
    REQUIRE(p.camera_matches.size() == 3);
    CHECK(p.camera_matches[0] == 0);
    // The same solve, by hand, from the geometry stage's outputs.
    const auto& o = ws.geometry.outputs;
    std::vector<float> solved(36);
    bool ok[3];
    index_t found[3];
    geometry::cameras_from_matches<float>(solved.data(), o.descriptors.data(), o.foreground.data(), o.depth.data(),
                                          o.intrinsics.data(), 3, c.image_h, c.image_w, 4, ok, found);
    index_t from_matches = 0;
    for (index_t v = 1; v < 3; ++v) {
      CAPTURE(v);
      CHECK(p.camera_matches[static_cast<std::size_t>(v)] == (ok[v] ? found[v] : 0));
      const float* want = ok[v] ? solved.data() + 12 * v : o.extrinsics.data() + 12 * v;
      for (int i = 0; i < 12; ++i) CHECK(p.geometry.extrinsics[static_cast<std::size_t>(12 * v + i)] == want[i]);
      if (ok[v]) {  // the solved camera is not the camera head's, so the check above tells the branches apart
        CHECK(found[v] > 0);
        CHECK(max_rel_diff(solved.data() + 12 * v, o.extrinsics.data() + 12 * v, 12) > 1e-3);
      }
      from_matches += ok[v];
    }
    CHECK(from_matches == placed);
    for (int i = 0; i < 12; ++i) CHECK(p.geometry.extrinsics[static_cast<std::size_t>(i)] == o.extrinsics.data()[i]);
  }
  (void)w0;
}

TEST_CASE("with camera source orbit, predict places the views by the orbit search on its own silhouettes, depth, "
          "intrinsics and pixels, the depth trusted to predicted_depth_search's range", "[model][predict]") {
  const MatchHeadCase m;
  const auto& [c, w, e] = m;
  model::PredictWorkspace<float> ws;
  ws.cameras = model::CameraSource::orbit_search;
  CHECK(ws.orbit.depth_range == model::predicted_depth_search().depth_range);
  CHECK(ws.orbit.depth_range > 0);
  const auto p = model::predict<float>(ws, *w, e.images.data(), 3);
  // The same search, by hand, from the geometry stage's outputs.
  const auto& o = ws.geometry.outputs;
  std::vector<float> solved(36);
  bool ok[3];
  geometry::cameras_from_orbit_search<float>(solved.data(), e.images.data(), o.foreground.data(), o.depth.data(),
                                             o.intrinsics.data(), 3, c.image_h, c.image_w, model::predicted_depth_search(),
                                             ok, nullptr, {o.descriptors.data(), c.geometry.match_dim});
  index_t placed = 0, moved = 0;
  for (index_t v = 0; v < 3; ++v) {
    placed += v > 0 && ok[v];
    for (int i = 0; i < 12; ++i) {
      CHECK(p.geometry.extrinsics[static_cast<std::size_t>(12 * v + i)] == solved[static_cast<std::size_t>(12 * v + i)]);
      moved += v > 0 && solved[static_cast<std::size_t>(12 * v + i)] != o.extrinsics.data()[12 * v + i];
    }
  }
  index_t object = 0;
  for (std::size_t i = 0; i < static_cast<std::size_t>(o.foreground.size()); ++i) object += o.foreground.data()[i] >= 0.5f;
  INFO("views placed by the search on random weights: " << placed << " (object pixels " << object << " of "
       << o.foreground.size() << "), entries unlike the camera head's: " << moved);
  CHECK(placed == 2);
  CHECK(moved > 0);
  // A model without the match head has no object probability to search with.
  auto plain = model::FlexSplatWeights<float>::create(model::flexsplat_tiny_config(), false);
  plain->init(8);
  model::PredictWorkspace<float> ws2;
  ws2.cameras = model::CameraSource::orbit_search;
  CHECK_THROWS_WITH(model::predict<float>(ws2, *plain, e.images.data(), 3), Catch::Contains("match_dim 0"));
}

TEST_CASE("input_cameras gives each predicted view's camera at the model's size, named", "[model][predict]") {
  model::Prediction<float> p;
  p.views = 2, p.h = 24, p.w = 32;
  p.geometry.resize(2, 24, 32, 1, 1, 1);
  for (index_t v = 0; v < 2; ++v) {
    const Camera c = look_at({3.0, 1.0 + v, 0.5}, {0, 0, 0}, 32, 24, intrinsics_from_fov(32, 24, 40.0 + 5 * v));
    camera_arrays(c, p.geometry.K.data() + 9 * v, p.geometry.extrinsics.data() + 12 * v);
  }
  const std::vector<Camera> cams = model::input_cameras(p, {"a.png", "b.png"});
  REQUIRE(cams.size() == 2);
  for (index_t v = 0; v < 2; ++v) {
    const Camera& c = cams[static_cast<std::size_t>(v)];
    CHECK(c.name == (v == 0 ? "a.png" : "b.png"));
    CHECK(c.width == 32);
    CHECK(c.height == 24);
    float K[9], E[12];
    camera_arrays(c, K, E);
    for (int i = 0; i < 9; ++i) CHECK(K[i] == p.geometry.K[static_cast<std::size_t>(9 * v + i)]);
    for (int i = 0; i < 12; ++i) CHECK(E[i] == p.geometry.extrinsics[static_cast<std::size_t>(12 * v + i)]);
  }
  CHECK(model::input_cameras(p)[1].name.empty());
  CHECK_THROWS_WITH(model::input_cameras(p, {"only-one.png"}), Catch::Contains("1 names for 2 views"));
}
