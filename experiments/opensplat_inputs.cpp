// An object folder's input views as a nerfstudio project for OpenSplat, the outside CPU 3D Gaussian Splatting trainer
// (experiments/opensplat_curve.py): the views composited on white as RGB PNGs, their true cameras as transforms.json, and
// points.ply, the start eval's posed fit uses (random_gaussians_in_views: that many points in the silhouettes' hull,
// coloured from the views) as a coloured point cloud, since OpenSplat starts from a point cloud.
// With --score PLY: the held-out PSNR of a splat in the object's world (OpenSplat's --keep-crs output) on every frame
// but the views, rendered over --background (OpenSplat composites over a fixed (0.613, 0.0101, 0.3984), never
// optimised; default white) at the frames' size, clamped to [0, 1] as OpenSplat's loss sees it, against the frames
// composited on white.
// Usage: opensplat_inputs OBJECT_DIR --views 9,26,3,20 --points 5120 [--seed 0] --out DIR
//        opensplat_inputs OBJECT_DIR --views 9,26,3,20 --score SPLAT.ply [--on-inputs] [--background r,g,b] [--near Z]
#include <algorithm>
#include <cstdio>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/export/file.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/io/transforms_json.hpp"
#include "flexsplat/loss/image.hpp"
#include "flexsplat/raster/render.hpp"

using namespace flexsplat;

int main(int argc, char** argv) try {
  std::string object, views_text = "9,26,3,20", out, score;
  long points = 5120, seed = 0;
  bool on_inputs = false;
  float background[3] = {1, 1, 1};
  double near_plane = raster::default_near;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      require(i + 1 < argc, "opensplat_inputs: ", a, " needs a value");
      return argv[++i];
    };
    if (a == "--views") views_text = next();
    else if (a == "--points") points = std::stol(next());
    else if (a == "--seed") seed = std::stol(next());
    else if (a == "--out") out = next();
    else if (a == "--score") score = next();
    else if (a == "--on-inputs") on_inputs = true;
    else if (a == "--near") near_plane = std::stod(next());
    else if (a == "--background") {
      require(std::sscanf(next().c_str(), "%f,%f,%f", &background[0], &background[1], &background[2]) == 3,
              "opensplat_inputs: --background takes r,g,b");
    }
    else object = a;
  }
  require(!object.empty() && (!out.empty() || !score.empty()), "usage: opensplat_inputs OBJECT_DIR --views i,j,.. --points N --out DIR");
  const data::ObjectRecord rec = data::load_object(object);
  model::EvalOptions o;
  model::set_views(o, views_text);
  std::vector<int> in, targets;
  model::eval_views(rec, o, in, targets);
  if (!score.empty()) {
    if (on_inputs) targets = in;
    const GaussianSet<float> splat = gaussians::read_gaussians(score);
    raster::RenderOptions ro;
    ro.background = {background[0], background[1], background[2]};
    ro.near_plane = near_plane;
    raster::RenderWorkspace<float> ws;
    raster::RenderOutputs<float> rendered;
    double psnr = 0;
    for (int t : targets) {
      const data::FrameRecord& fr = rec.frames[static_cast<std::size_t>(t)];
      const Tensor<float, 3> target = image::read_rgb<float>(fr.image);  // composited on white
      const index_t h = target.shape(0), w = target.shape(1);
      double K[9], E[12];
      camera_arrays(fr.camera, K, E);
      float Kf[9], Ef[12];
      std::copy(K, K + 9, Kf);
      std::copy(E, E + 12, Ef);
      raster::render_forward(splat, raster::view_from_arrays(Kf, Ef, static_cast<int>(w), static_cast<int>(h)), ro, ws,
                             rendered);
      // Shown as an image, as OpenSplat's loss sees it: clamped to [0, 1] (its white shell drifts above 1).
      for (index_t i = 0; i < 3 * h * w; ++i) rendered.image.data()[i] = std::min(rendered.image.data()[i], 1.0f);
      psnr += loss::psnr(rendered.image.data(), target.data(), 3 * h * w);
    }
    std::printf("%s %s: %lld Gaussians, PSNR %.2f dB on %zu targets\n", object.c_str(), score.c_str(),
                static_cast<long long>(splat.size()), psnr / static_cast<double>(targets.size()), targets.size());
    return 0;
  }
  const Camera& first = rec.frames[static_cast<std::size_t>(in[0])].camera;
  const index_t h = first.height, w = first.width;
  model::PosedViews views = model::posed_views(rec, in, h, w);
  const GaussianSet<float> start = model::random_gaussians_in_views<float>(
      points, 0, views.refine_views(), views.photos.alpha.data(), static_cast<std::uint64_t>(seed));

  namespace fs = std::filesystem;
  fs::create_directories(fs::path(out) / "images");
  std::vector<Camera> cameras;
  for (std::size_t v = 0; v < in.size(); ++v) {
    Tensor<float, 3> rgb(Shape<3>{h, w, 3});
    const float* src = views.photos.images.data() + v * static_cast<std::size_t>(h * w * 3);
    std::copy(src, src + h * w * 3, rgb.data());
    char name[32];
    std::snprintf(name, sizeof name, "images/%03d.png", in[v]);
    image::write_png(fs::path(out) / name, rgb);
    Camera c = rec.frames[static_cast<std::size_t>(in[v])].camera;
    c.name = name;
    cameras.push_back(c);
  }
  io::write_transforms_json(fs::path(out) / "transforms.json", cameras);
  {  // OpenSplat reads ply_file_path from transforms.json
    std::ifstream f(fs::path(out) / "transforms.json");
    nlohmann::json doc = nlohmann::json::parse(f);
    doc["ply_file_path"] = "points.ply";
    std::ofstream(fs::path(out) / "transforms.json") << doc.dump(1);
  }
  std::ofstream ply(fs::path(out) / "points.ply", std::ios::binary);
  ply << "ply\nformat binary_little_endian 1.0\nelement vertex " << start.size()
      << "\nproperty float x\nproperty float y\nproperty float z\n"
         "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n";
  for (index_t i = 0; i < start.size(); ++i) {
    const float xyz[3] = {start.means(i, 0), start.means(i, 1), start.means(i, 2)};
    ply.write(reinterpret_cast<const char*>(xyz), sizeof xyz);
    for (int k = 0; k < 3; ++k) {
      const float c = std::clamp(static_cast<float>(sh_color_offset) + static_cast<float>(sh_c0) * start.sh(i, 0, k),
                                 0.f, 1.f);
      const auto u = static_cast<std::uint8_t>(c * 255.f + 0.5f);
      ply.write(reinterpret_cast<const char*>(&u), 1);
    }
  }
  std::printf("%s: %zu views of %lld x %lld, %lld points -> %s\n", object.c_str(), in.size(),
              static_cast<long long>(w), static_cast<long long>(h), static_cast<long long>(start.size()), out.c_str());
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "opensplat_inputs: %s\n", e.what());
  return 1;
}
