// compact: what model::compact_splat drops from a prediction and what that costs. Per object: the Gaussians before and
// after, the .glb's bytes, the held-out views' PSNR before and after (eval's protocol at the photos' resolution) and
// the time to render every held-out view before and after.
//   build/bench/compact --model M [--views 9,26,3,20] [--cameras truth|model] [--min-pixels 2] [--carve-margin 0.01]
//                       OBJECT_DIR...
#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/export/gltf.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/eval/compact.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/model/predict.hpp"

using namespace flexsplat;

namespace {

double render_ms(const GaussianSet<float>& s, const data::ObjectRecord& rec, const std::vector<int>& targets,
                 const model::Similarity& to_world) {
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  raster::RenderWorkspace<float> ws;
  raster::RenderOutputs<float> out;
  const auto t0 = std::chrono::steady_clock::now();
  for (int f : targets) {
    double E[12], K[9];
    camera_arrays(rec.frames[static_cast<std::size_t>(f)].camera, K, E);
    model::Similarity inv;  // world -> the set's frame
    inv.R = to_world.R.transpose(), inv.scale = 1 / to_world.scale, inv.t = -inv.R * to_world.t / to_world.scale;
    model::transform_camera(E, inv);
    raster::render_forward(s, raster::camera_view<float>(camera_from_arrays(K, E, rec.width, rec.height)), ro, ws, out);
  }
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

int main(int argc, char** argv) {
  std::string model_path, views = "9,26,3,20", cameras = "truth";
  model::CompactOptions co;
  std::vector<std::string> objects;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return i + 1 < argc ? std::string(argv[++i]) : std::string(); };
    if (a == "--model") model_path = next();
    else if (a == "--views") views = next();
    else if (a == "--cameras") cameras = next();
    else if (a == "--min-pixels") co.min_pixels = std::stod(next());
    else if (a == "--carve-margin") co.carve_margin = std::stod(next());
    else objects.push_back(a);
  }
  if (model_path.empty() || objects.empty() || (cameras != "truth" && cameras != "model")) {
    std::fprintf(stderr, "usage: compact --model M [--views 9,26,3,20] [--cameras truth|model] [--min-pixels P] "
                         "[--carve-margin F] OBJECT_DIR...\n");
    return 2;
  }
  try {
    const auto w = model::load_flexsplat<float>(model_path);
    const model::FlexSplatConfig& c = w->config();
    std::printf("model %s, views %s, cameras %s, min_pixels %g, carve_margin %g\n", model_path.c_str(), views.c_str(),
                cameras.c_str(), co.min_pixels, co.carve_margin);
    std::printf("%-16s %8s %8s %10s %10s %8s %8s %8s %10s %10s\n", "object", "before", "after", "glb_before",
                "glb_after", "psnr", "psnr_c", "change", "render_ms", "render_c");
    double sum_before = 0, sum_after = 0, sum_change = 0;
    for (const auto& dir : objects) {
      const data::ObjectRecord rec = data::load_object(dir);
      model::EvalOptions o;
      model::set_views(o, views);
      std::vector<int> in, targets;
      model::eval_views(rec, o, in, targets);
      std::vector<Tensor<float, 3>> rgba;
      std::vector<Camera> truth;
      for (int v : in) {
        rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
        truth.push_back(rec.frames[static_cast<std::size_t>(v)].camera);
      }
      model::PredictWorkspace<float> ws;
      model::Prediction<float> p;
      std::vector<Camera> inputs;  // the input views at the photos' size, in the prediction's frame
      std::vector<float> alpha;    // their alpha
      if (cameras == "truth") {
        p = model::predict_posed<float>(ws, *w, rgba, truth);
        model::to_capture_world(p);
        inputs = truth;
      } else {
        const Tensor<float, 4> x = model::model_input<float>(rgba, c);
        p = model::predict<float>(ws, *w, TensorView<const float, 4>(x.view()));
      }
      const model::PhotoTargets<float> photos = model::photo_targets<float>(rgba, c, p.geometry.K.data(), rec.height, rec.width);
      alpha = photos.alpha;
      if (cameras == "model")
        for (index_t v = 0; v < p.views; ++v)
          inputs.push_back(camera_from_arrays(photos.K.data() + 9 * v, p.geometry.extrinsics.data() + 12 * v,
                                              rec.width, rec.height));
      std::vector<float> w2c(p.geometry.extrinsics.begin(), p.geometry.extrinsics.end());
      model::EvalWorkspace ews;
      const model::EvalResult before = model::score_prediction(rec, in, targets, w2c.data(), p.gaussians, rec.height, rec.width, o, ews);
      const double ms_before = render_ms(p.gaussians, rec, targets, before.alignment);
      const std::size_t glb_before = gltf::encode_glb(p.gaussians).size();
      GaussianSet<float> compact = p.gaussians;
      const model::CompactReport r = model::compact_splat(compact, inputs, alpha.data(), co);
      const model::EvalResult after = model::score_prediction(rec, in, targets, w2c.data(), compact, rec.height, rec.width, o, ews);
      const double ms_after = render_ms(compact, rec, targets, before.alignment);
      const std::size_t glb_after = gltf::encode_glb(compact).size();
      std::printf("%-16s %8lld %8lld %10zu %10zu %8.3f %8.3f %+8.3f %10.1f %10.1f\n", rec.name.c_str(),
                  static_cast<long long>(r.before), static_cast<long long>(r.after), glb_before, glb_after,
                  before.model.psnr, after.model.psnr, after.model.psnr - before.model.psnr, ms_before, ms_after);
      sum_before += static_cast<double>(r.before), sum_after += static_cast<double>(r.after);
      sum_change += after.model.psnr - before.model.psnr;
    }
    const double n = static_cast<double>(objects.size());
    std::printf("mean: %.1f -> %.1f Gaussians (%.1f %% fewer), PSNR change %+.3f dB\n", sum_before / n, sum_after / n,
                100 * (1 - sum_after / sum_before), sum_change / n);
  } catch (const Error& e) {
    std::fprintf(stderr, "compact: %s\n", e.what());
    return 1;
  }
  return 0;
}
