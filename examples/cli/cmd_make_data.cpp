// make-data: renders procedural objects into folders in the layout of the shared Blender renders.
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <vector>
#include <cstdio>
#include <string>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/resample.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

// A picture for docs/data.md: rows of generated objects over a row of the shared Blender renders, all seen from
// elevation 20, azimuth 45 (shared view 9), composited on white, tiles of 128 pixels with 4-pixel gaps.
void write_make_data_grid(const std::string& path, const std::string& shared, int count, std::uint64_t seed,
                          const data::GeneratorConfig& cfg) {
  namespace fs = std::filesystem;
  constexpr int tile = 128, gap = 4, columns = 7;
  std::vector<Tensor<float, 3>> tiles;  // RGB HWC at 256, resized below
  auto add_tile = [&](const Tensor<float, 3>& rgba) {
    const index_t h = rgba.shape(0), w = rgba.shape(1);
    Tensor<float, 3> planar(Shape<3>{3, h, w});
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x)
        for (index_t c = 0; c < 3; ++c) planar(c, y, x) = rgba(y, x, c) * rgba(y, x, 3) + (1 - rgba(y, x, 3));
    tiles.push_back(interpolate_bicubic_antialias<float>(TensorView<const float, 3>(planar.view()), tile, tile));
  };
  const Camera cam = data::orbit_camera(20, 45, 3.0, 45, 256, 256);
  for (int i = 0; i < count; ++i) {
    const data::ProceduralObject obj = data::make_object(data::object_seed(seed, static_cast<std::uint64_t>(i)), cfg.object);
    data::RenderOutput out;
    data::RenderWorkspace ws;
    data::render_mesh(obj.mesh, cam, data::object_render_options(obj, cfg.supersample), out, ws);
    add_tile(out.rgba);
  }
  const int generated_rows = (count + columns - 1) / columns;
  std::vector<fs::path> shared_dirs;
  for (const auto& e : fs::directory_iterator(shared))
    if (e.is_directory()) shared_dirs.push_back(e.path());
  std::sort(shared_dirs.begin(), shared_dirs.end());
  require(!shared_dirs.empty(), "make-data --grid: no object folders in '", shared, "'");
  for (const fs::path& d : shared_dirs) {
    const data::ObjectRecord rec = data::load_object(d);
    require(rec.frames.size() > 9, "make-data --grid: '", d.string(), "' has no view 9");
    add_tile(image::read_float<float>(rec.frames[9].image, 4));
  }
  const int shared_rows = (static_cast<int>(shared_dirs.size()) + columns - 1) / columns;
  const int rows = generated_rows + shared_rows;
  const int width = columns * tile + (columns + 1) * gap, height = rows * tile + (rows + 1) * gap + 2 * gap;
  Tensor<float, 3> canvas(Shape<3>{height, width, 3}, 0.55f);
  for (std::size_t i = 0; i < tiles.size(); ++i) {
    const bool is_shared = static_cast<int>(i) >= count;
    const int k = is_shared ? static_cast<int>(i) - count : static_cast<int>(i);
    const int row = (is_shared ? generated_rows : 0) + k / columns, col = k % columns;
    const int y0 = gap + row * (tile + gap) + (is_shared ? 2 * gap : 0), x0 = gap + col * (tile + gap);
    for (int y = 0; y < tile; ++y)
      for (int x = 0; x < tile; ++x)
        for (int c = 0; c < 3; ++c) canvas(y0 + y, x0 + x, c) = std::clamp(tiles[i](c, y, x), 0.0f, 1.0f);
  }
  image::write_png(path, canvas);
  std::printf("%s: %d generated objects (top) and %zu shared renders (bottom), elevation 20, azimuth 45\n", path.c_str(),
              count, shared_dirs.size());
}

int make_data_command(Args args) {
  std::string count = "100", views = "32", size = "256", seed = "0", out, supersample = "2", segments = "32";
  take_option(args, "--count", count);
  take_option(args, "--views", views);
  take_option(args, "--size", size);
  take_option(args, "--seed", seed);
  take_option(args, "--supersample", supersample);
  take_option(args, "--segments", segments);
  std::string grid, shared = "../shared/data/objects";
  const bool want_grid = take_option(args, "--grid", grid);
  take_option(args, "--shared", shared);
  require(take_option(args, "--out", out) || want_grid, "make-data needs --out DIR (or --grid PNG)");
  std::string blobs = "0";
  take_option(args, "--blobs", blobs);
  const bool attached = take_flag(args, "--attached");
  const bool soft = take_flag(args, "--soft-textures");
  const bool unstructured = take_flag(args, "--no-structured");
  const bool quiet = take_flag(args, "--quiet");
  require(args.empty(), "make-data: unexpected argument '", args.empty() ? "" : args[0], "'");
  data::MakeDataOptions opt;
  opt.count = static_cast<int>(parse_integer(count, "--count", 1, 100000000));
  opt.generator.views = static_cast<int>(parse_integer(views, "--views", 1, 1000));
  opt.generator.size = static_cast<int>(parse_integer(size, "--size", 8, 4096));
  opt.generator.supersample = static_cast<int>(parse_integer(supersample, "--supersample", 1, 8));
  opt.generator.object.segments = static_cast<int>(parse_integer(segments, "--segments", 3, 4096));
  const double blob_fraction = parse_number(blobs, "--blobs", true);
  require(blob_fraction <= 1, "--blobs '", blobs, "' must be at most 1 (the share of parts that are blobs)");
  opt.generator.object.blob_fraction = static_cast<float>(blob_fraction);
  opt.generator.object.attached = attached;
  opt.generator.object.soft_textures = soft;
  opt.generator.structured = !unstructured;
  opt.seed = parse_seed(seed, "--seed");

  if (want_grid) {
    write_make_data_grid(grid, shared, opt.count, opt.seed, opt.generator);
    if (out.empty()) return 0;
  }
  const auto start = std::chrono::steady_clock::now();
  int last_width = 0;
  auto progress = [&](int done, int total) {
    if (quiet) return;
    const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    const int bar = 30, filled = static_cast<int>(static_cast<long long>(bar) * done / total);
    std::string line = "\r[" + std::string(static_cast<std::size_t>(filled), '#') +
                       std::string(static_cast<std::size_t>(bar - filled), ' ') + "] ";
    char tail[96];
    std::snprintf(tail, sizeof tail, "%d/%d objects, %.1f s", done, total, secs);
    line += tail;
    if (static_cast<int>(line.size()) < last_width) line += std::string(static_cast<std::size_t>(last_width) - line.size(), ' ');
    last_width = static_cast<int>(line.size());
    std::fputs(line.c_str(), stderr);
    if (done == total) std::fputc('\n', stderr);
    std::fflush(stderr);
  };
  const data::MakeDataReport report = data::make_dataset(out, opt, progress);
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("%s: %d objects written, %d already present (skipped), %d views of %dx%d each, %.1f s\n", out.c_str(),
              report.written, report.skipped, opt.generator.views, opt.generator.size, opt.generator.size, secs);
  return 0;
}

const RegisterCommand registered_cmd_make_data(
    "make-data", {"render procedural training objects into folders like ../shared/data/objects (resumable)",
                  "--out DIR [--count N=100] [--views V=32] [--size S=256] [--seed X=0] [--supersample 2] "
                  "[--segments 32] [--blobs F=0] [--attached] [--soft-textures] [--no-structured] [--quiet]\n"
                  "  [--grid PNG [--shared DIR]]\n"
                  "  --blobs F: each part is a blob (a sphere bent by smooth waves) with probability F; --attached:\n"
                  "  parts after the first sit on its surface (organic objects; both off: loose unions of primitives);\n"
                  "  --soft-textures: solid, noise and gradient materials only, without forced contrast\n"
                  "  writes DIR/obj_NNNNNN/{images/NNN.png, depth/NNN.png, cameras.json}; views 0-3 are the structured\n"
                  "  set (elevation 20, azimuth 0/90/180/270) unless --no-structured; existing objects are skipped, each\n"
                  "  object appears atomically; DIR/make_data.json pins the settings a rerun must repeat\n"
                  "  --grid PNG: a picture of the first N objects above the renders in --shared (default\n"
                  "  ../shared/data/objects), all from elevation 20, azimuth 45; --out is then optional",
                  make_data_command});

}  // namespace
}  // namespace flexsplat::cli
