// Given cameras: a Gaussian set moved by a similarity renders as before from the moved camera (centres, scales,
// rotations and SH band 1); the scale search finds a capture's units from depth and silhouettes; and the shipped
// posed model, given the bundled spot's cameras as a COLMAP text model, a COLMAP binary model and a transforms.json,
// makes the same splat in the capture's world, which a held-out camera of the capture sees well above a white image.
#include <catch2/catch.hpp>

#include <cmath>
#include <filesystem>
#include <random>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/io/capture_cameras.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/raster/render.hpp"
#include "temp_dir.hpp"

using namespace flexsplat;

namespace given_cameras_test {

const std::filesystem::path spot = std::filesystem::path(FLEXSPLAT_SOURCE_DIR) / "examples/data/spot";

Tensor<float, 3> render(const GaussianSet<float>& s, const Camera& cam) {
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  raster::RenderWorkspace<float> ws;
  raster::RenderOutputs<float> out;
  raster::render_forward(s, raster::camera_view<float>(cam), ro, ws, out);
  return out.image;
}

// A camera that sees the scene moved by x -> scale R x + t as `cam` saw it.
Camera moved_camera(const Camera& cam, const glm::dmat3& R, const glm::dvec3& t, double scale) {
  Camera c = cam;
  c.R = cam.R * glm::transpose(R);
  c.t = -(c.R * (scale * (R * cam.centre()) + t));
  return c;
}

}  // namespace given_cameras_test

using namespace given_cameras_test;

TEST_CASE("transform_gaussians: the moved set renders from the moved camera as the set did", "[model][given]") {
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-1, 1);
  GaussianSet<float> s = make_gaussian_set<float>(300, 1);
  for (index_t i = 0; i < s.size(); ++i) {
    for (int k = 0; k < 3; ++k) s.means(i, k) = 0.5f * u(rng), s.scales(i, k) = 0.03f + 0.02f * u(rng);
    for (int k = 0; k < 4; ++k) s.quats(i, k) = u(rng);
    s.opacities(i) = 0.6f + 0.3f * u(rng);
    for (int k = 0; k < 4; ++k)
      for (int ch = 0; ch < 3; ++ch) s.sh(i, k, ch) = (k == 0 ? 0.8f : 0.6f) * u(rng);  // a strong band 1
  }
  const Camera cam = look_at({0.4, -2.5, 0.9}, {0, 0, 0}, 64, 64, intrinsics_from_fov(64, 64, 45.0));
  const Tensor<float, 3> before = render(s, cam);
  const glm::dmat3 R = glm::mat3_cast(glm::normalize(glm::dquat(0.3, -0.5, 0.7, 0.4)));
  const glm::dvec3 t(1.5, -4.0, 2.25);
  const double scale = 3.7;
  GaussianSet<float> moved = s;
  transform_gaussians(moved, R, t, scale);
  const Tensor<float, 3> after = render(moved, moved_camera(cam, R, t, scale));
  double worst = 0, signal = 0;
  for (index_t i = 0; i < before.size(); ++i) {
    worst = std::max(worst, static_cast<double>(std::abs(before.data()[i] - after.data()[i])));
    signal = std::max(signal, static_cast<double>(std::abs(before.data()[i] - 1.0f)));
  }
  // float rounding of the moved centres and rotations; a band 1 left unrotated changes pixels by ~0.1-0.5
  CHECK(worst < 2e-3);
  CHECK(signal > 0.3);  // the picture is not blank
  // Without the band-1 rotation the renders differ: the check above can fail.
  GaussianSet<float> no_sh = s;
  transform_gaussians(no_sh, R, t, scale);
  for (index_t i = 0; i < s.size(); ++i)
    for (int k = 1; k < 4; ++k)
      for (int ch = 0; ch < 3; ++ch) no_sh.sh(i, k, ch) = s.sh(i, k, ch);
  const Tensor<float, 3> wrong = render(no_sh, moved_camera(cam, R, t, scale));
  double wrong_worst = 0;
  for (index_t i = 0; i < before.size(); ++i)
    wrong_worst = std::max(wrong_worst, static_cast<double>(std::abs(before.data()[i] - wrong.data()[i])));
  CHECK(wrong_worst > 0.05);
  // Degree 2 cannot be rotated and is refused, not silently left alone.
  GaussianSet<float> d2 = make_gaussian_set<float>(1, 2);
  d2.quats(0, 0) = 1;
  CHECK_THROWS_WITH(transform_gaussians(d2, R, t, scale), Catch::Contains("SH degree 2 cannot be rotated"));
}

TEST_CASE("given_frame finds a capture's scale from true depth and silhouettes", "[model][given]") {
  const data::ObjectRecord rec = data::load_object(spot);
  model::FlexSplatConfig c;
  c.image_h = c.image_w = 56;
  c.geometry.aggregator.patch_size = 7;
  for (const std::vector<int>& in : {std::vector<int>{8, 10, 12, 14}, std::vector<int>{1, 9, 26}, std::vector<int>{8, 12}}) {
    std::vector<Tensor<float, 3>> rgba;
    std::vector<Camera> cams;
    const double units = 3.7;  // the capture's world is the renders' times this
    for (int f : in) {
      rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(f)].image, 4));
      Camera cam = rec.frames[static_cast<std::size_t>(f)].camera;
      cam.t *= units;
      cams.push_back(cam);
    }
    const model::GivenCameras<float> gc = model::given_cameras<float>(rgba, cams, c);
    const model::ModelPhotos<float> photos = model::model_photos<float>(rgba, c);
    const std::vector<float>& silhouettes = photos.silhouettes;
    REQUIRE(!silhouettes.empty());
    // Depth at the model's size in "model units": the renders' metres times 0.8, so the scale to find is units / 0.8.
    const index_t V = static_cast<index_t>(in.size()), h = 56, w = 56;
    std::vector<float> depth(static_cast<std::size_t>(V * h * w)), images(static_cast<std::size_t>(V * 3 * h * w), 1.0f);
    std::copy(photos.images.data(), photos.images.data() + photos.images.size(), images.begin());
    for (index_t v = 0; v < V; ++v) {
      const Tensor<double, 2> d = image::read_depth_png<double>(rec.frames[static_cast<std::size_t>(in[static_cast<std::size_t>(v)])].depth, rec.depth_scale);
      for (index_t y = 0; y < h; ++y)
        for (index_t x = 0; x < w; ++x)
          depth[static_cast<std::size_t>((v * h + y) * w + x)] =
              static_cast<float>(0.8 * d(y * d.shape(0) / h + d.shape(0) / (2 * h), x * d.shape(1) / w + d.shape(1) / (2 * w)));
    }
    const model::GivenFrame f = model::given_frame(gc, images.data(), depth.data(), silhouettes.data(), h, w);
    INFO("views " << V << ": scale " << f.frame.scale << " against " << units / 0.8);
    CHECK(f.from_views);
    // The first guess (the axes' meeting point against the median depth) is off by the object's radius, 10-30 %.
    CHECK(std::abs(f.frame.scale / (units / 0.8) - 1) < 0.03);
  }
}

TEST_CASE("reconstruct with given cameras: three formats, one splat, in the capture's world", "[model][given]") {
  const std::filesystem::path model_file = std::filesystem::path(FLEXSPLAT_SOURCE_DIR) / "models/flexsplat-posed.safetensors";
  REQUIRE(std::filesystem::exists(model_file));
  const auto w = model::load_flexsplat<float>(model_file);
  const data::ObjectRecord rec = data::load_object(spot);
  // The capture's world: the renders' moved and in centimetres, so that a splat left in the model's frame is far off.
  const glm::dmat3 R = glm::mat3_cast(glm::normalize(glm::dquat(0.9, 0.1, -0.3, 0.2)));
  const glm::dvec3 t(12.0, -30.0, 5.0);
  const double cm = 100.0;
  std::vector<Camera> capture;
  for (const auto& fr : rec.frames) {
    Camera cam = moved_camera(fr.camera, R, t, cm);
    cam.name = std::filesystem::path(fr.image).filename().string();
    capture.push_back(cam);
  }
  flexsplat_test::TempDir dir("given_cameras_formats");
  io::write_colmap_text(dir.path / "text", capture);
  io::write_colmap_binary(dir.path / "bin", capture);
  io::write_transforms_json(dir.path / "transforms.json", capture);
  const std::vector<int> in{9, 15, 26, 4};  // two elevations, not in azimuth order
  std::vector<std::string> photos;
  std::vector<Tensor<float, 3>> rgba;
  std::vector<std::array<int, 2>> sizes;
  for (int f : in) {
    photos.push_back(rec.frames[static_cast<std::size_t>(f)].image.string());
    rgba.push_back(image::read_float<float>(photos.back(), 4));
    sizes.push_back({static_cast<int>(rgba.back().shape(1)), static_cast<int>(rgba.back().shape(0))});
  }
  std::vector<GaussianSet<float>> sets;
  for (const auto& path : {dir.path / "text", dir.path / "bin", dir.path / "transforms.json"}) {
    const std::vector<Camera> cams = io::cameras_for_photos(path, photos, sizes);
    model::PredictWorkspace<float> ws;
    model::Prediction<float> p = model::predict_posed<float>(ws, *w, rgba, cams);
    REQUIRE(p.given.has_value());
    CHECK(p.given->from_views);
    model::to_capture_world(p);
    sets.push_back(p.gaussians);
  }
  for (std::size_t k = 1; k < sets.size(); ++k) {
    double worst = 0;
    for (index_t i = 0; i < sets[0].means.size(); ++i)
      worst = std::max(worst, static_cast<double>(std::abs(sets[k].means.data()[i] - sets[0].means.data()[i])));
    CHECK(worst < 1e-3 * cm);  // float rounding of the cameras through the formats; the object is ~100 units wide
  }
  // Held-out views of the capture (the other elevations' frames) against a white image, at the photos' 256 x 256.
  double psnr = 0, white = 0;
  const std::vector<int> held{0, 19, 30};
  for (int f : held) {
    const Tensor<float, 3> gt_rgba = image::read_float<float>(rec.frames[static_cast<std::size_t>(f)].image, 4);
    Tensor<float, 3> gt(Shape<3>{gt_rgba.shape(0), gt_rgba.shape(1), 3}), blank(gt.shape(), 1.0f);
    for (index_t y = 0; y < gt.shape(0); ++y)
      for (index_t x = 0; x < gt.shape(1); ++x)
        for (int ch = 0; ch < 3; ++ch)
          gt(y, x, ch) = gt_rgba(y, x, ch) * gt_rgba(y, x, 3) + (1 - gt_rgba(y, x, 3));
    const Tensor<float, 3> r = render(sets[0], capture[static_cast<std::size_t>(f)]);
    psnr += loss::psnr(r.data(), gt.data(), gt.size()) / static_cast<double>(held.size());
    white += loss::psnr(blank.data(), gt.data(), gt.size()) / static_cast<double>(held.size());
  }
  INFO("held-out PSNR " << psnr << " dB, white " << white << " dB");
  // A splat left in the model's frame, or at a wrong scale, renders nothing where the object is: about the white score.
  CHECK(psnr > white + 3.0);
}
