// Timing of the resampling kernels and of the whole VGGT preprocessing on the shared reference PNGs.
// Prints one row per case: median of N runs (ms), with the SIMD path and the scalar path.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "flexsplat/core/simd.hpp"
#include "flexsplat/geometry/preprocess.hpp"
#include "flexsplat/image/resample.hpp"

using namespace flexsplat;

template <class F>
double median_ms(int runs, F&& f) {
  std::vector<double> t;
  for (int i = 0; i < runs; ++i) {
    const auto a = std::chrono::steady_clock::now();
    f();
    t.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - a).count());
  }
  std::sort(t.begin(), t.end());
  return t[t.size() / 2];
}

int main(int argc, char** argv) {
  const std::string shared = argc > 1 ? argv[1] : "/work/shared";
  std::printf("threads %d, compiled SIMD arch %s\n", global_pool().size(), simd::compiled_arch_name());
  std::mt19937 rng(1);
  std::uniform_int_distribution<int> byte(0, 255);
  std::printf("%-52s %10s %10s\n", "case", "simd ms", "scalar ms");

  struct PillowCase { int w, h, ow, oh; };
  for (const PillowCase c : {PillowCase{256, 256, 518, 518}, {320, 200, 518, 322}, {1920, 1080, 518, 294}}) {
    std::vector<std::uint8_t> img(std::size_t(c.w) * c.h * 3), out(std::size_t(c.ow) * c.oh * 3);
    for (auto& v : img) v = static_cast<std::uint8_t>(byte(rng));
    PillowResampleWorkspace ws;
    double ms[2];
    for (int s = 0; s < 2; ++s) {
      ws.use_simd = s == 0;
      ms[s] = median_ms(21, [&] { resize_pillow_bicubic(img.data(), c.w, c.h, 3, out.data(), c.ow, c.oh, ws); });
    }
    const std::string name = "pillow bicubic RGB " + std::to_string(c.w) + "x" + std::to_string(c.h) + " -> " +
                             std::to_string(c.ow) + "x" + std::to_string(c.oh);
    std::printf("%-52s %10.3f %10.3f\n", name.c_str(), ms[0], ms[1]);
  }

  struct AaCase { index_t c, h, w, oh, ow; };
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  for (const AaCase c : {AaCase{1024, 37, 37, 23, 37}, {1024, 37, 37, 74, 74}, {1024, 37, 37, 16, 21}}) {
    std::vector<float> x(std::size_t(c.c * c.h * c.w)), y(std::size_t(c.c * c.oh * c.ow));
    for (auto& v : x) v = unit(rng);
    AntialiasWorkspace<float> ws;
    double ms[2];
    for (int s = 0; s < 2; ++s) {
      ws.use_simd = s == 0;
      ms[s] = median_ms(21, [&] { interpolate_bicubic_antialias<float>(x.data(), c.c, c.h, c.w, y.data(), c.oh, c.ow, ws); });
    }
    // Float rounding of the float32 kernel, measured against the float64 instantiation on the same input.
    std::vector<double> xd(x.begin(), x.end()), yd(y.size());
    AntialiasWorkspace<double> wsd;
    interpolate_bicubic_antialias<double>(xd.data(), c.c, c.h, c.w, yd.data(), c.oh, c.ow, wsd);
    double max_dev = 0;
    for (std::size_t i = 0; i < y.size(); ++i) max_dev = std::max(max_dev, std::abs(double(y[i]) - yd[i]));
    const std::string name = "torch bicubic aa f32 [" + std::to_string(c.c) + "," + std::to_string(c.h) + "," +
                             std::to_string(c.w) + "] -> " + std::to_string(c.oh) + "x" + std::to_string(c.ow);
    std::printf("%-52s %10.3f %10.3f   max |f32 - f64| %.3g\n", name.c_str(), ms[0], ms[1], max_dev);
  }

  const std::string dir = shared + "/reference/preprocess/";
  const std::vector<std::string> files{dir + "square_rgba.png", dir + "wide_rgb.png", dir + "tall_rgba.png"};
  std::vector<InterleavedImage> images;
  for (const auto& f : files) images.push_back(decode_image_like_pillow(f));
  for (const auto mode : {VggtPreprocessMode::crop, VggtPreprocessMode::pad}) {
    const double ms = median_ms(11, [&] { vggt_preprocess_images(images, mode); });
    const double ms_files = median_ms(11, [&] { vggt_load_and_preprocess_images(files, mode); });
    std::printf("vggt preprocess %-4s 3 decoded images (simd)            %10.3f\n", vggt_preprocess_mode_name(mode), ms);
    std::printf("vggt preprocess %-4s 3 PNG files incl. decode (simd)    %10.3f\n", vggt_preprocess_mode_name(mode),
                ms_files);
  }
  return 0;
}
