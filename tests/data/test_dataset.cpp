#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <unistd.h>

#include "flexsplat/data/dataset.hpp"
#include "temp_dir.hpp"

using namespace flexsplat;
using namespace flexsplat::data;
namespace fs = std::filesystem;

namespace {

const fs::path shared_objects = fs::path(FLEXSPLAT_SHARED_DIR) / "data/objects";

using flexsplat_test::file_bytes;
using flexsplat_test::TempDir;

void write_text(const fs::path& p, const std::string& text) {
  std::ofstream out(p, std::ios::binary | std::ios::trunc);
  out << text;
}

template <class T, std::size_t R>
bool same_bytes(const Tensor<T, R>& a, const Tensor<T, R>& b) {
  return a.shape() == b.shape() && std::memcmp(a.data(), b.data(), sizeof(T) * static_cast<std::size_t>(a.size())) == 0;
}

GeneratorConfig tiny_config(int views = 5) {
  GeneratorConfig cfg;
  cfg.size = 48;
  cfg.views = views;
  cfg.object.segments = 16;
  return cfg;
}

// A small valid object folder to corrupt.
fs::path make_one_object(const fs::path& root) {
  MakeDataOptions opt;
  opt.count = 1;
  opt.seed = 99;
  opt.generator = tiny_config(3);
  make_dataset(root, opt);
  return root / object_folder_name(0);
}

}  // namespace

TEST_CASE("16-bit PNGs written by write_png_u16 read back exactly", "[data]") {
  TempDir dir("png16");
  Tensor<std::uint16_t, 3> img(Shape<3>{5, 7, 2});
  for (index_t i = 0; i < img.size(); ++i) img.data()[i] = static_cast<std::uint16_t>((i * 7919) % 65536);
  image::write_png_u16(dir.path / "a.png", TensorView<const std::uint16_t, 3>(img.view()));
  const auto info = image::probe(dir.path / "a.png");
  CHECK(info.bit_depth == 16);
  CHECK(info.channels == 2);
  CHECK(same_bytes(image::read_u16(dir.path / "a.png"), img));
}

TEST_CASE("same seed gives identical bytes on 1 and 2 threads", "[data]") {
  ThreadPool one(1), two(2);
  const GeneratorConfig cfg = tiny_config(3);
  const GeneratedObject a = generate_object(5, 2, cfg, one), b = generate_object(5, 2, cfg, two);
  REQUIRE(a.views.size() == 3);
  for (std::size_t v = 0; v < a.views.size(); ++v) {
    CHECK(same_bytes(a.views[v].rgba, b.views[v].rgba));
    CHECK(same_bytes(a.views[v].depth, b.views[v].depth));
  }
  // A single render split over rows, and the written files.
  RenderOutput r1, r2;
  RenderWorkspace ws;
  RenderOptions opt = object_render_options(a.object, 2, true);
  render_mesh(a.object.mesh, a.cameras[1], opt, r1, ws, one);
  render_mesh(a.object.mesh, a.cameras[1], opt, r2, ws, two);
  CHECK(same_bytes(r1.rgba, r2.rgba));
  CHECK(same_bytes(r1.normals, r2.normals));
  TempDir dir("threads");
  write_object(dir.path / "one", a, one);
  write_object(dir.path / "two", b, two);
  for (const char* f : {"cameras.json", "images/000.png", "images/002.png", "depth/001.png"})
    CHECK(file_bytes(dir.path / "one" / f) == file_bytes(dir.path / "two" / f));
  BatchOptions bo;
  bo.inputs = 2;
  bo.targets = 1;
  bo.crop = 32;
  bo.scale_min = 0.8;
  bo.scale_max = 1.2;
  bo.background = BackgroundMode::random;
  const auto ba = generate_batch(cfg, 2, 11, 3, bo, one), bb = generate_batch(cfg, 2, 11, 3, bo, two);
  for (std::size_t s = 0; s < 2; ++s) {
    CHECK(same_bytes(ba[s].inputs.rgb, bb[s].inputs.rgb));
    CHECK(same_bytes(ba[s].targets.depth, bb[s].targets.depth));
  }
  // A different seed gives a different object.
  CHECK_FALSE(same_bytes(generate_object(6, 2, cfg, one).views[0].rgba, a.views[0].rgba));
}

TEST_CASE("make_dataset writes folders the reader loads back, and resumes", "[data]") {
  TempDir dir("make");
  MakeDataOptions opt;
  opt.count = 2;
  opt.seed = 3;
  opt.generator = tiny_config(5);
  int calls = 0;
  const MakeDataReport first = make_dataset(dir.path, opt, [&](int done, int total) { calls += done <= total; });
  CHECK(first.written == 2);
  CHECK(calls == 2);
  const auto objects = load_objects({dir.path});
  REQUIRE(objects.size() == 2);
  CHECK(objects[0].name == "obj_000000");
  CHECK(objects[1].frames.size() == 5);
  CHECK(objects[1].input_views == std::vector<int>{0, 1, 2, 3});
  CHECK(objects[1].depth_scale == kDepthPngScale);
  // Round trip against the in-memory object.
  const GeneratedObject g = generate_object(3, 1, opt.generator);
  for (std::size_t v = 0; v < 5; ++v) {
    const Camera& c = objects[1].frames[v].camera;
    for (int i = 0; i < 3; ++i) {
      CHECK(c.t[i] == g.cameras[v].t[i]);
      for (int j = 0; j < 3; ++j) CHECK(c.R[i][j] == g.cameras[v].R[i][j]);
    }
    const auto depth = image::read_depth_png<double>(objects[1].frames[v].depth, kDepthPngScale);
    const auto rgba = image::read_float<float>(objects[1].frames[v].image, 4);
    double depth_err = 0, rgba_err = 0;
    for (index_t i = 0; i < depth.size(); ++i) depth_err = std::max(depth_err, std::abs(depth.data()[i] - g.views[v].depth.data()[i]));
    for (index_t i = 0; i < rgba.size(); ++i) rgba_err = std::max(rgba_err, double(std::abs(rgba.data()[i] - g.views[v].rgba.data()[i])));
    CHECK(depth_err <= 0.5 * kDepthPngScale + 1e-6);
    CHECK(rgba_err <= 0.5 / 255 + 1e-6);
  }
  // Rerun: both complete objects are skipped; one more is added; an interrupted object's leftovers are removed.
  fs::create_directories(dir.path / ".tmp_obj_000002_12345/images");
  opt.count = 3;
  const MakeDataReport second = make_dataset(dir.path, opt);
  CHECK(second.skipped == 2);
  CHECK(second.written == 1);
  CHECK_FALSE(fs::exists(dir.path / ".tmp_obj_000002_12345"));
  CHECK(load_objects({dir.path}).size() == 3);
  opt.generator.size = 64;
  CHECK_THROWS_WITH(make_dataset(dir.path, opt), Catch::Contains("make_data.json") && Catch::Contains("different settings"));
}

TEST_CASE("make_dataset refuses an object config make_object cannot follow before it writes anything", "[data]") {
  TempDir dir("make_bad");
  MakeDataOptions opt;
  opt.count = 1;
  opt.generator = tiny_config(5);
  opt.generator.object.blob_fraction = 2.0f;
  CHECK_THROWS_WITH(make_dataset(dir.path / "out", opt), Catch::Contains("blob_fraction 2 outside [0, 1]"));
  CHECK_FALSE(fs::exists(dir.path / "out"));
}

TEST_CASE("the reader rejects each kind of corrupted folder and names the file", "[data]") {
  TempDir dir("corrupt");
  const fs::path good = make_one_object(dir.path / "src");
  REQUIRE_NOTHROW(load_object(good));
  int case_index = 0;
  auto corrupt = [&](auto&& damage) {
    const fs::path copy = dir.path / ("case" + std::to_string(case_index++));
    fs::copy(good, copy, fs::copy_options::recursive);
    damage(copy);
    return copy;
  };
  auto edit_json = [&](const fs::path& folder, auto&& change) {
    std::ifstream in(folder / "cameras.json");
    nlohmann::json doc = nlohmann::json::parse(in);
    change(doc);
    write_text(folder / "cameras.json", doc.dump());
  };
  // Missing image, missing depth, missing cameras.json.
  fs::path f = corrupt([](const fs::path& d) { fs::remove(d / "images/001.png"); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "images/001.png").string()) && Catch::Contains("missing"));
  f = corrupt([](const fs::path& d) { fs::remove(d / "depth/002.png"); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "depth/002.png").string()) && Catch::Contains("missing"));
  f = corrupt([](const fs::path& d) { fs::remove(d / "cameras.json"); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "cameras.json").string()) && Catch::Contains("missing"));
  // Size mismatch of an image and of a depth map; an 8-bit depth map.
  f = corrupt([](const fs::path& d) { image::write_png(d / "images/000.png", Tensor<std::uint8_t, 3>(Shape<3>{40, 48, 4})); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "images/000.png").string()) && Catch::Contains("48x40"));
  f = corrupt([](const fs::path& d) {
    const Tensor<std::uint16_t, 3> small(Shape<3>{48, 47, 1});
    image::write_png_u16(d / "depth/000.png", TensorView<const std::uint16_t, 3>(small.view()));
  });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "depth/000.png").string()) && Catch::Contains("47x48"));
  f = corrupt([](const fs::path& d) { image::write_png(d / "depth/001.png", Tensor<std::uint8_t, 3>(Shape<3>{48, 48, 1})); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "depth/001.png").string()) && Catch::Contains("8-bit"));
  // Bad JSON: truncated, and wrong structure.
  f = corrupt([](const fs::path& d) {
    const std::string text = file_bytes(d / "cameras.json");
    write_text(d / "cameras.json", text.substr(0, text.size() / 2));
  });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "cameras.json").string()) && Catch::Contains("not valid JSON"));
  f = corrupt([&](const fs::path& d) { edit_json(d, [](nlohmann::json& j) { j["frames"] = 3; }); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "cameras.json").string()) && Catch::Contains("'frames'"));
  // Non-finite matrix entries as Python's json writes them (NaN, Infinity), and a number overflowing to infinity.
  for (const char* bad : {"NaN", "-Infinity", "1e999"}) {
    f = corrupt([&](const fs::path& d) {
      std::string text = file_bytes(d / "cameras.json");
      const std::size_t at = text.find("\"w2c\"");
      const std::size_t num = text.find_first_of("-0123456789", at + 6);
      const std::size_t end = text.find_first_of(",]", num);
      write_text(d / "cameras.json", text.replace(num, end - num, bad));
    });
    CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "cameras.json").string()) && Catch::Contains("non-finite"));
  }
  // Not a rotation: one row of R scaled; a reflection.
  f = corrupt([&](const fs::path& d) {
    edit_json(d, [](nlohmann::json& j) {
      for (int c = 0; c < 3; ++c) j["frames"][1]["w2c"][0][c] = 2.0 * j["frames"][1]["w2c"][0][c].get<double>();
    });
  });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "cameras.json").string()) && Catch::Contains("frame 1") &&
                                        Catch::Contains("not a rotation"));
  f = corrupt([&](const fs::path& d) {
    edit_json(d, [](nlohmann::json& j) {
      for (int c = 0; c < 4; ++c) j["frames"][2]["w2c"][1][c] = -j["frames"][2]["w2c"][1][c].get<double>();
    });
  });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains("frame 2") && Catch::Contains("not a rotation"));
  // Bad depth scale: negative, zero, missing, a string.
  for (const nlohmann::json& bad : {nlohmann::json(-1e-4), nlohmann::json(0.0), nlohmann::json("1e-4"), nlohmann::json()}) {
    f = corrupt([&](const fs::path& d) {
      edit_json(d, [&](nlohmann::json& j) {
        if (bad.is_null()) j.erase("depth_png_scale_m");
        else j["depth_png_scale_m"] = bad;
      });
    });
    CHECK_THROWS_WITH(load_object(f), Catch::Contains((f / "cameras.json").string()) &&
                                          Catch::Contains("depth_png_scale_m"));
  }
  // Bad intrinsics and input_views.
  f = corrupt([&](const fs::path& d) { edit_json(d, [](nlohmann::json& j) { j["frames"][0]["K"][0][0] = -300; }); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains("frame 0 'K'"));
  f = corrupt([&](const fs::path& d) { edit_json(d, [](nlohmann::json& j) { j["input_views"] = {0, 7}; }); });
  CHECK_THROWS_WITH(load_object(f), Catch::Contains("'input_views' entry 7"));
  // A file name longer than the file system allows (ENAMETOOLONG): a flexsplat error naming it, not a
  // std::filesystem exception; through load_objects as well as load_object.
  const std::string long_name(300, 'x');
  f = corrupt([&](const fs::path& d) { edit_json(d, [&](nlohmann::json& j) { j["frames"][1]["depth"] = long_name; }); });
  CHECK_THROWS_AS(load_object(f), Error);
  CHECK_THROWS_WITH(load_objects({f}), Catch::Contains(long_name) && Catch::Contains("cannot be read"));
  CHECK_THROWS_WITH(load_objects({dir.path / long_name}), Catch::Contains("is not a folder"));
}

TEST_CASE("the shared Blender renders load, and the orbit ranges and structured views match them", "[data]") {
  const auto objects = load_objects({shared_objects});
  REQUIRE(objects.size() == 7);
  const OrbitRanges ranges;
  for (const ObjectRecord& rec : objects) {
    REQUIRE(rec.frames.size() == 32);
    CHECK(rec.depth_scale == 1e-4);
    for (const FrameRecord& fr : rec.frames) {
      const OrbitParameters p = orbit_parameters(fr.camera);
      CHECK(p.elevation_deg >= ranges.elevation_min);
      CHECK(p.elevation_deg <= ranges.elevation_max);
      CHECK(p.azimuth_deg >= ranges.azimuth_min - 1e-6);
      CHECK(p.azimuth_deg <= ranges.azimuth_max);
      CHECK(p.radius >= ranges.radius_min);
      CHECK(p.radius <= ranges.radius_max);
      CHECK(p.hfov_deg >= ranges.hfov_min);
      CHECK(p.hfov_deg <= ranges.hfov_max);
    }
    // The structured set reproduces the renders' input views (elevation 20, azimuth 0/90/180/270).
    REQUIRE(rec.input_views.size() == 4);
    const auto structured = structured_cameras(rec.width, rec.height);
    for (std::size_t i = 0; i < 4; ++i) {
      const Camera& a = structured[i];
      const Camera& b = rec.frames[static_cast<std::size_t>(rec.input_views[i])].camera;
      for (int c = 0; c < 3; ++c) {
        CHECK(std::abs(a.t[c] - b.t[c]) < 1e-6);
        for (int r = 0; r < 3; ++r) {
          CHECK(std::abs(a.R[c][r] - b.R[c][r]) < 1e-6);
          CHECK(std::abs(a.K[c][r] - b.K[c][r]) < 1e-9);
        }
      }
    }
  }
}

TEST_CASE("batches from folders: view choice, crops with zoom keep depth and K consistent", "[data]") {
  const auto objects = load_objects({shared_objects / "spot", shared_objects / "teapot"});
  BatchOptions o;
  o.inputs = 4;
  o.targets = 1;
  o.crop = 96;
  o.scale_min = 0.5;
  o.scale_max = 0.8;  // zoom out: a window of 120..192 pixels becomes 96
  o.background = BackgroundMode::random;
  const auto batch = sample_batch(objects, 2, 42, 0, o);
  REQUIRE(batch.size() == 2);
  for (const SceneSample& s : batch) {
    CHECK(s.inputs.rgb.shape() == Shape<4>{4, 96, 96, 3});
    CHECK(s.targets.depth.shape() == Shape<3>{1, 96, 96});
    const ObjectRecord& rec = s.name == "spot" ? objects[0] : objects[1];
    // Structured inputs: the inputs' cameras are the record's input views with K rescaled (same rotation).
    for (std::size_t i = 0; i < 4; ++i)
      CHECK(s.inputs.cameras[i].R == rec.frames[static_cast<std::size_t>(rec.input_views[i])].camera.R);
    // Every target pixel with depth unprojects (new K) onto a point that the full-size source depth confirms.
    for (std::size_t v = 0; v < 1; ++v) {
      const Camera& cam = s.targets.cameras[v];
      const FrameRecord* src = nullptr;
      for (const FrameRecord& fr : rec.frames)
        if (fr.camera.R == cam.R) src = &fr;
      REQUIRE(src != nullptr);
      const auto full = image::read_depth_png<double>(src->depth, rec.depth_scale);
      int checked = 0, agree = 0, empty = 0, background_ok = 0;
      for (int y = 0; y < 96; ++y)
        for (int x = 0; x < 96; ++x) {
          const float z = s.targets.depth(static_cast<index_t>(v), y, x);
          if (z <= 0) {
            if (s.targets.alpha(static_cast<index_t>(v), y, x) == 0) {
              ++empty;
              bool ok = true;
              for (int c = 0; c < 3; ++c) ok = ok && s.targets.rgb(static_cast<index_t>(v), y, x, c) == s.background[c];
              background_ok += ok;
            }
            continue;
          }
          const glm::dvec2 uv = src->camera.project(src->camera.to_camera(cam.to_world(cam.unproject({x + 0.5, y + 0.5}, z))));
          const int sx = static_cast<int>(std::floor(uv.x)), sy = static_cast<int>(std::floor(uv.y));
          ++checked;  // nearest-neighbour depth lands on a source pixel centre
          agree += sx >= 0 && sy >= 0 && sx < rec.width && sy < rec.height && std::abs(full(sy, sx) - z) < 1e-3;
        }
      CHECK(checked > 200);
      CHECK(agree == checked);
      CHECK(empty > 200);
      CHECK(background_ok == empty);
    }
  }
  // Deterministic in (seed, step); another step draws something else.
  o.inputs = 1;
  const auto first = sample_batch(objects, 1, 42, 0, o), again = sample_batch(objects, 1, 42, 0, o);
  CHECK(same_bytes(again[0].targets.rgb, first[0].targets.rgb));
  const auto next = sample_batch(objects, 1, 42, 1, o);
  CHECK_FALSE(same_bytes(next[0].targets.rgb, first[0].targets.rgb));
}

TEST_CASE("in-memory batches from the generator", "[data]") {
  GeneratorConfig cfg = tiny_config();
  cfg.size = 64;
  BatchOptions o;
  o.inputs = 4;
  o.targets = 3;
  o.background = BackgroundMode::fixed;
  o.background_color = {0.2f, 0.4f, 0.6f};
  const auto batch = generate_batch(cfg, 2, 8, 0, o);
  REQUIRE(batch.size() == 2);
  const auto structured = structured_cameras(64, 64);
  for (const SceneSample& s : batch) {
    CHECK(s.targets.rgb.shape() == Shape<4>{3, 64, 64, 3});
    for (std::size_t i = 0; i < 4; ++i) CHECK(s.inputs.cameras[i].R == structured[i].R);
    int background = 0, foreground = 0, background_ok = 0, foreground_ok = 0;
    for (index_t y = 0; y < 64; ++y)
      for (index_t x = 0; x < 64; ++x) {
        if (s.inputs.alpha(0, y, x) == 0) {
          ++background;
          background_ok += s.inputs.rgb(0, y, x, 1) == 0.4f && s.inputs.depth(0, y, x) == 0;
        } else if (s.inputs.alpha(0, y, x) == 1) {
          ++foreground;
          foreground_ok += s.inputs.depth(0, y, x) > 1.5f;
        }
      }
    CHECK(background > 100);
    CHECK(foreground > 100);
    CHECK(background_ok == background);
    CHECK(foreground_ok == foreground);
  }
  // The batch's scene 1 is object 1 of the dataset: same views as generate_object renders.
  cfg.views = 4;
  const GeneratedObject g = generate_object(8, 1, cfg);
  o.crop = 0;
  CHECK(std::memcmp(&batch[1].inputs.depth(2, 0, 0), g.views[2].depth.data(), sizeof(float) * 64 * 64) == 0);
}

TEST_CASE("generator views within a baseline of the first: azimuth within it, elevation within half of it, inside the "
          "ranges", "[data]") {
  GeneratorConfig cfg = tiny_config();
  cfg.size = 16;
  BatchOptions o;
  o.inputs = 5;
  o.targets = 3;
  o.structured_inputs = false;
  auto wrap = [](double d) { return std::remainder(d, 360.0); };
  for (double baseline : {10.0, 40.0}) {
    cfg.orbit.max_baseline_deg = baseline;
    double widest = 0;
    for (const SceneSample& s : generate_batch(cfg, 6, 3, 0, o)) {
      std::vector<Camera> cams = s.inputs.cameras;
      cams.insert(cams.end(), s.targets.cameras.begin(), s.targets.cameras.end());
      const OrbitParameters first = orbit_parameters(cams[0]);
      for (const Camera& c : cams) {
        const OrbitParameters p = orbit_parameters(c);
        // Orbit parameters are read back from the camera (its look-at point jitters), so allow a few degrees.
        CHECK(std::abs(wrap(p.azimuth_deg - first.azimuth_deg)) <= baseline + 3);
        CHECK(std::abs(p.elevation_deg - first.elevation_deg) <= baseline / 2 + 3);
        CHECK(p.elevation_deg >= cfg.orbit.elevation_min - 3);
        CHECK(p.elevation_deg <= cfg.orbit.elevation_max + 3);
        widest = std::max(widest, std::abs(wrap(p.azimuth_deg - first.azimuth_deg)));
      }
    }
    CHECK(widest > baseline / 2);  // the window is used, not collapsed onto the first view
  }
  cfg.orbit.max_baseline_deg = -1;
  CHECK_THROWS_WITH(generate_batch(cfg, 1, 3, 0, o), Catch::Contains("max_baseline_deg -1"));
}
