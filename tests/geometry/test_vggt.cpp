#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "flexsplat/geometry/reference.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "geometry_test_util.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

TEST_CASE("the vggt checker passes the shared bundle at 1e-4 of each tensor's max abs", "[geometry][vggt]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  ReferenceReport report;
  check_vggt_reference(file, report);
  // 3 cases x (dino + 3 aggregator outputs + 4 pose encodings + 5 camera/depth/point tensors)
  CHECK(report.rows.size() == 3 * 13);
  for (const auto& row : report.rows) {
    INFO(row.name << " max_rel " << row.max_rel_error << " " << row.note);
    CHECK(row.pass);
  }
}

TEST_CASE("a 1% change of one LayerScale is caught by the comparison", "[geometry][vggt]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const VggtConfig cfg = vggt_config_from_json(file.metadata("config"));
  const std::string name = "aggregator.global_blocks.1.ls2.gamma";
  const auto original = file.get<float, 1>("param." + name);
  const auto images = file.get<float, 5>("case2.images");
  const auto expected = file.get<float, 5>("case2.depth");
  ReferenceReport report;
  const auto depth_row = [&](float factor) {
    io::ParamSource<float> src(file, "param.");
    std::vector<float> changed(original.data(), original.data() + original.size());
    for (auto& v : changed) v *= factor;
    src.add(name, {original.shape(0)}, changed);
    const auto weights = load_vggt_weights(src, cfg);
    VggtWorkspace<float> ws;
    const auto out = vggt_forward<float>(images.data(), 1, images.shape(3), images.shape(4), cfg, weights, ws);
    return report.compare<float, float>("depth", out.depth.span(), expected.span(),
                                        {ToleranceKind::relative_to_max_abs, vggt_reference_tolerance});
  };
  // The same path with the bundle's own value passes, so the failure below is the change's.
  CHECK(depth_row(1.0f).pass);
  // A value mismatch of the compared depth: same size, finite, the error above the tolerance.
  const auto row = depth_row(1.01f);
  INFO(row.name << " max_rel " << row.max_rel_error << " note '" << row.note << "'");
  CHECK_FALSE(row.pass);
  CHECK(row.note.empty());
  CHECK(std::isfinite(row.max_rel_error));
  CHECK(row.max_rel_error > vggt_reference_tolerance);
}

TEST_CASE("vggt_forward rejects images that are not whole patches or not finite", "[geometry][vggt]") {
  const auto file = safetensors::File::open(vggt_bundle_path());
  const VggtConfig cfg = vggt_config_from_json(file.metadata("config"));
  io::ParamSource<float> src(file, "param.");
  const auto weights = load_vggt_weights(src, cfg);
  VggtWorkspace<float> ws;
  std::vector<float> images(3 * 28 * 30, 0.5f);
  CHECK_THROWS_WITH(vggt_forward<float>(images.data(), 1, 28, 30, cfg, weights, ws), Catch::Contains("28 x 30"));
  images.assign(3 * 28 * 28, 0.5f);
  images[100] = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH(vggt_forward<float>(images.data(), 1, 28, 28, cfg, weights, ws), Catch::Contains("image 0 has a non-finite value nan at channel 0, row 3, column 16"));
  CHECK_THROWS_WITH(vggt_forward<float>(images.data(), 0, 28, 28, cfg, weights, ws), Catch::Contains("at least one image"));
}

TEST_CASE("VGGT config from JSON builds consistent head configs and refuses inconsistent ones", "[geometry][config]") {
  const auto cfg = vggt_config_from_json(std::string(R"({"img_size": 98, "patch_size": 14, "embed_dim": 64, "depth": 3,
      "num_heads": 2, "dino_depth": 2, "dino_heads": 2, "trunk_depth": 2, "cam_heads": 2, "features": 32,
      "out_channels": [16, 32, 64, 64], "intermediate_layer_idx": [0, 1, 1, 2]})"));
  CHECK(cfg.camera.dim == 128);
  CHECK(cfg.depth.dim_in == 128);
  CHECK(cfg.depth.features == 32);
  CHECK_THROWS_WITH(vggt_config_from_json(std::string(R"({"embed_dim": 64, "num_heads": 2, "depth": 3, "dino_heads": 2,
      "cam_heads": 2, "intermediate_layer_idx": [0, 1, 2, 3]})")), Catch::Contains("reads aggregator output 3"));
  const VggtConfig vggt1b;
  CHECK_NOTHROW(vggt1b.validate());
  CHECK(vggt_parameter_specs(vggt1b).size() > 1000);
}
