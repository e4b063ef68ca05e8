#include <catch2/catch.hpp>

#include <vector>

#include "flexsplat/geometry/flops.hpp"

using namespace flexsplat;
using namespace flexsplat::geometry;

// Every 2-D weight of the camera head is a linear layer applied once per frame and iteration, so its FLOPs follow from
// the parameter specs alone; the trunk's attention adds QK^T and PV over the frames.
TEST_CASE("flops: the camera head count equals its linear layers' shapes plus trunk attention", "[geometry][flops]") {
  for (index_t frames : {1, 4}) {
    CameraHeadConfig c;  // VGGT-1B
    c.trunk_depth = 2;
    c.iterations = 3;
    std::vector<io::TensorSpec> specs;
    append_camera_head_specs(specs, c);
    double linear = 0;
    for (const auto& s : specs)
      if (s.shape.size() == 2) linear += 2.0 * double(frames) * double(s.shape[0]) * double(s.shape[1]);
    const double attention = double(c.trunk_depth) * 4.0 * double(frames * frames) * double(c.dim);
    INFO("frames " << frames);
    CHECK(camera_head_flops(c, frames) == Approx(double(c.iterations) * (linear + attention)).epsilon(1e-12));
  }
}

TEST_CASE("flops: the DPT count grows with the patch grid and sums into the VGGT total", "[geometry][flops]") {
  const VggtConfig cfg;
  const auto small = vggt_forward_flops(cfg, 2, 14 * 8, 14 * 8), large = vggt_forward_flops(cfg, 2, 14 * 16, 14 * 16);
  CHECK(large.depth_head > 3.5 * small.depth_head);  // four times the pixels, convolutions linear in them
  CHECK(small.depth_head == Approx(2 * dpt_flops(cfg.depth, 8, 8)).epsilon(1e-12));
  CHECK(small.total() == Approx(small.dino + small.aggregator + small.camera_head + small.depth_head));
}
