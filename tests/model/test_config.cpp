#include <catch2/catch.hpp>

#include <map>

#include "flexsplat/model/cameras.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/raster/render.hpp"

using namespace flexsplat;

TEST_CASE("FlexSplat configs survive a JSON round trip", "[model][config]") {
  for (const auto& c : {model::flexsplat_tiny_config(), model::flexsplat_paper_config()}) {
    const auto text = model::to_json(c).dump();
    const auto back = model::flexsplat_config_from_json(text);
    CHECK(model::to_json(back).dump() == text);
    CHECK(geometry::vggt_parameter_specs(back.geometry).size() == geometry::vggt_parameter_specs(c.geometry).size());
    CHECK(decoder::ModelParamLayout(back.appearance).size == decoder::ModelParamLayout(c.appearance).size);
  }
}

TEST_CASE("the point head is a config switch: its tensors appear under VGGT's names and the JSON keeps it",
          "[model][config][points]") {
  auto c = model::flexsplat_tiny_config();
  const auto plain = geometry::vggt_parameter_specs(c.geometry);
  CHECK(model::to_json(c).at("geometry").contains("point_head") == false);  // old files compare equal
  c.geometry.point_head = true;
  const auto with = geometry::vggt_parameter_specs(c.geometry);
  std::size_t point = 0;
  for (const auto& s : with) point += s.name.rfind("point_head.", 0) == 0;
  CHECK(point == with.size() - plain.size());
  CHECK(point > 0);
  bool conv_out = false;
  for (const auto& s : with)
    if (s.name == "point_head.scratch.output_conv2.2.weight") conv_out = s.shape[0] == 4;  // x, y, z, confidence
  CHECK(conv_out);
  const auto back = model::flexsplat_config_from_json(model::to_json(c).dump());
  CHECK(back.geometry.point_head);
  auto j = model::to_json(c);
  j["geometry"]["point_head"] = 1;
  CHECK_THROWS_WITH(model::flexsplat_config_from_json(j.dump()), Catch::Contains("'point_head' = 1"));
  // The match head likewise: match_dim descriptor channels and the object probability, under match_head.*.
  c.geometry.match_dim = 5;
  const auto matched = geometry::vggt_parameter_specs(c.geometry);
  bool match_out = false;
  for (const auto& s : matched)
    if (s.name == "match_head.scratch.output_conv2.2.weight") match_out = s.shape[0] == 6;
  CHECK(match_out);
  CHECK(model::flexsplat_config_from_json(model::to_json(c).dump()).geometry.match_dim == 5);
  j = model::to_json(c);
  j["geometry"]["match_dim"] = 300;
  CHECK_THROWS_WITH(model::flexsplat_config_from_json(j.dump()), Catch::Contains("'match_dim' = 300"));
  // Its image convolutions: two of 8 channels, then 8 + features/2 channels into output_conv2.0; kept by the JSON.
  c.geometry.match_image = true;
  c.geometry.match_image_convs = 2;
  c.geometry.match_image_width = 8;
  std::map<std::string, std::vector<index_t>> shapes;
  for (const auto& s : geometry::vggt_parameter_specs(c.geometry)) shapes[s.name] = s.shape;
  CHECK(shapes["match_head.scratch.image_conv.0.weight"] == std::vector<index_t>{8, 3, 3, 3});
  CHECK(shapes["match_head.scratch.image_conv.1.weight"] == std::vector<index_t>{8, 8, 3, 3});
  CHECK(shapes.count("match_head.scratch.image_conv.2.weight") == 0);
  CHECK(shapes["match_head.scratch.output_conv2.0.weight"][1] == 8 + c.geometry.depth.head_features());
  const auto convs = model::flexsplat_config_from_json(model::to_json(c).dump()).geometry;
  CHECK(convs.match_image_convs == 2);
  CHECK(convs.match_image_width == 8);
  j = model::to_json(c);
  j["geometry"]["match_image_convs"] = 5;
  CHECK_THROWS_WITH(model::flexsplat_config_from_json(j.dump()), Catch::Contains("'match_image_convs' = 5"));
  j = model::to_json(c);
  j["geometry"]["match_image"] = false;
  CHECK_THROWS_WITH(model::flexsplat_config_from_json(j.dump()),
                    Catch::Contains("match_image_convs 2 needs match_image"));
  // The depth head's image convolutions: its own tensors under depth_head.*, none for the point head; kept by the JSON.
  c.geometry.set_depth_image(3, 8);
  shapes.clear();
  for (const auto& s : geometry::vggt_parameter_specs(c.geometry)) shapes[s.name] = s.shape;
  CHECK(shapes["depth_head.scratch.image_conv.0.weight"] == std::vector<index_t>{8, 3, 3, 3});
  CHECK(shapes["depth_head.scratch.image_conv.2.weight"] == std::vector<index_t>{8, 8, 3, 3});
  CHECK(shapes.count("depth_head.scratch.image_conv.3.weight") == 0);
  CHECK(shapes["depth_head.scratch.output_conv2.0.weight"][1] == 8 + c.geometry.depth.head_features());
  CHECK(shapes.count("point_head.scratch.image_conv.0.weight") == 0);
  CHECK(shapes["point_head.scratch.output_conv2.0.weight"][1] == c.geometry.depth.head_features());
  CHECK(shapes["match_head.scratch.image_conv.1.weight"] == std::vector<index_t>{8, 8, 3, 3});
  const auto depth_convs = model::flexsplat_config_from_json(model::to_json(c).dump()).geometry;
  CHECK(depth_convs.depth.image_convs == 3);
  CHECK(depth_convs.depth.image_width == 8);
  j = model::to_json(c);
  j["geometry"]["depth_image_convs"] = 5;
  CHECK_THROWS_WITH(model::flexsplat_config_from_json(j.dump()), Catch::Contains("'depth_image_convs' = 5"));
  c.geometry.depth.image_convs = 0;  // the pixels without convolutions: not a head the JSON can name
  CHECK_THROWS_WITH(c.validate(), Catch::Contains("set_depth_image"));
}

TEST_CASE("FlexSplat config errors name the offending setting", "[model][config]") {
  auto c = model::flexsplat_tiny_config();
  c.image_h = 30;
  CHECK_THROWS_WITH(c.validate(), Catch::Contains("multiple of the patch size 7"));
  c = model::flexsplat_tiny_config();
  c.appearance.fusion.depth_channels = 5;
  CHECK_THROWS_WITH(c.validate(), Catch::Contains("depth-feature channels"));
  c = model::flexsplat_tiny_config();
  c.gaussians = 1000;
  CHECK_THROWS_WITH(c.validate(), Catch::Contains("max_queries"));
  CHECK_THROWS_WITH(model::flexsplat_config_from_json("[1, 2]"), Catch::Contains("not a JSON object"));
  CHECK_THROWS_WITH(model::flexsplat_config_from_json("{\"image_h\": \"big\"}"), Catch::Contains("FlexSplat config JSON"));
}

TEST_CASE("VGGT intrinsics move by half a pixel and the camera adjoints add", "[model][cameras]") {
  const double Kv[9] = {100, 0, 64, 0, 90, 48, 0, 0, 1};
  double K[9];
  model::intrinsics_from_vggt(K, Kv, 1);
  CHECK(K[2] == 64.5);
  CHECK(K[5] == 48.5);
  CHECK(K[0] == 100);
  double back[9];  // intrinsics_to_vggt undoes it exactly
  model::intrinsics_to_vggt(back, K, 1);
  for (int i = 0; i < 9; ++i) CHECK(back[i] == Kv[i]);
  const double E[12] = {1, 0, 0, 0.5, 0, 1, 0, -1, 0, 0, 1, 3};
  const auto cam = raster::view_from_arrays(K, E, 128, 96);
  CHECK(cam.fx == 100);
  CHECK(cam.cy == 48.5);
  CHECK(cam.world_to_camera[11] == 3);
  CHECK(cam.world_to_camera[15] == 1);
  raster::ViewGrad<double> g;
  for (int i = 0; i < 12; ++i) g.world_to_camera[static_cast<std::size_t>(i)] = i + 1;
  g.fx = 0.5, g.fy = 0.25, g.cx = 2, g.cy = 3;
  double dK[9], dE[12];
  for (double& v : dK) v = 7;
  for (double& v : dE) v = -1;
  raster::view_from_arrays_backward(dK, dE, g);
  CHECK(dK[0] == 7.5);
  CHECK(dK[2] == 9);
  CHECK(dK[1] == 7);
  CHECK(dE[11] == 11);
  double dKv[9];
  for (double& v : dKv) v = 1;
  model::intrinsics_from_vggt_backward(dKv, dK, 1);
  CHECK(dKv[5] == 11);
}
