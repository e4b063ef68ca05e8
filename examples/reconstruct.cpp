// The library's main job in one file: load a FlexSplat model, read a few uncalibrated photos, predict cameras and
// Gaussians, write a .glb (KHR_gaussian_splatting) with the predicted cameras.
//   reconstruct [--model M.safetensors] -o out.glb IMAGE...
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "flexsplat/export/file.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/model/predict.hpp"

using namespace flexsplat;

int main(int argc, char** argv) try {
  std::string model_path = FLEXSPLAT_DEFAULT_MODEL, output = "out.glb";
  std::vector<std::string> files;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--model" && i + 1 < argc) model_path = argv[++i];
    else if (a == "-o" && i + 1 < argc) output = argv[++i];
    else files.push_back(a);
  }
  if (files.empty()) {
    std::fprintf(stderr, "usage: reconstruct [--model M.safetensors] [-o out.glb] IMAGE...\n");
    return 2;
  }
  require(std::filesystem::exists(model_path), "no model at '", model_path, "'; pass --model");

  // 1. The model: configuration and weights from one safetensors file.
  const auto weights = model::load_flexsplat<float>(model_path);
  const model::FlexSplatConfig& config = weights->config();

  // 2. The photos as RGBA, then the model's input [V, 3, h, w]: composited on white, resized to the model's size.
  std::vector<Tensor<float, 3>> photos;
  for (const auto& f : files) photos.push_back(image::read_float<float>(f, 4));
  const Tensor<float, 4> input = model::model_input<float>(photos, config);

  // 3. One forward pass: cameras (in the first photo's frame), depth, and the Gaussians.
  model::PredictWorkspace<float> ws;
  const model::Prediction<float> p = model::predict<float>(ws, *weights, TensorView<const float, 4>(input.view()));

  // 4. Export with the predicted cameras as glTF camera nodes.
  gltf::WriteOptions options;
  options.cameras = model::input_cameras(p, files);
  gaussians::write_gaussians(p.gaussians, output, options);
  std::printf("%s: %lld Gaussians from %zu photos (%.0f ms geometry, %.0f ms decoder)\n", output.c_str(),
              static_cast<long long>(p.gaussians.size()), files.size(), p.geometry_ms, p.decoder_ms);
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "reconstruct: error: %s\n", e.what());
  return 1;
}
