#pragma once
// VGGT weights: the name/shape table derived from a VggtConfig (names exactly as VGGT's state_dict), one check that
// lists every missing, mis-shaped or unexpected tensor at once, and binding to the per-module weight structs.
// Tensors of the track head, and of the point head unless the config enables it, are ignored.
#include <filesystem>
#include <string>
#include <vector>

#include "flexsplat/geometry/aggregator.hpp"
#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/geometry/config.hpp"
#include "flexsplat/geometry/dino.hpp"
#include "flexsplat/geometry/dpt_head.hpp"
#include "flexsplat/io/param_check.hpp"
#include "flexsplat/io/param_source.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

inline constexpr const char* vggt_dino_prefix = "aggregator.patch_embed.";
inline constexpr const char* vggt_depth_prefix = "depth_head.";
inline constexpr const char* vggt_point_prefix = "point_head.";
inline constexpr const char* vggt_match_prefix = "match_head.";

// Every tensor the configured model reads, in state_dict order (aggregator, camera head, depth head).
inline std::vector<io::TensorSpec> vggt_parameter_specs(const VggtConfig& c) {
  std::vector<io::TensorSpec> specs;
  const std::size_t before_dino = 2;
  append_aggregator_trunk_specs(specs, c.aggregator);
  std::vector<io::TensorSpec> dino;
  append_dino_specs(dino, vggt_dino_prefix, c.aggregator.dino);
  specs.insert(specs.begin() + before_dino, dino.begin(), dino.end());
  append_camera_head_specs(specs, c.camera, "camera_head.");
  append_dpt_head_specs(specs, c.depth, vggt_depth_prefix);
  if (c.point_head) append_dpt_head_specs(specs, c.point(), vggt_point_prefix);
  if (c.match_dim > 0) append_dpt_head_specs(specs, c.match(), vggt_match_prefix);
  return specs;
}

// Throws one flexsplat::Error listing every missing, mis-shaped and unexpected tensor of the configured modules.
template <class T>
void check_vggt_parameters(const io::ParamSource<T>& src, const VggtConfig& c) {
  std::vector<std::string> modules{"aggregator.", "camera_head.", "depth_head."};
  if (c.point_head) modules.push_back(vggt_point_prefix);
  if (c.match_dim > 0) modules.push_back(vggt_match_prefix);
  io::check_parameters(src, vggt_parameter_specs(c), modules, "VGGT");
}

template <class T>
struct VggtWeights {
  DinoWeights<T> dino;
  AggregatorWeights<T> aggregator;
  CameraHeadWeights<T> camera;
  DptHeadWeights<T> depth;
  DptHeadWeights<T> point;  // all null unless VggtConfig::point_head
  DptHeadWeights<T> match;  // all null unless VggtConfig::match_dim > 0
};

template <class T>
VggtWeights<T> load_vggt_weights(io::ParamSource<T>& src, const VggtConfig& c) {
  c.validate();
  check_vggt_parameters(src, c);
  VggtWeights<T> w;
  w.dino = load_dino_weights(src, vggt_dino_prefix, c.aggregator.dino);
  w.aggregator = load_aggregator_trunk_weights(src, c.aggregator);
  w.camera = load_camera_head_weights(src, c.camera, "camera_head.");
  w.depth = load_dpt_head_weights(src, c.depth, vggt_depth_prefix);
  if (c.point_head) w.point = load_dpt_head_weights(src, c.point(), vggt_point_prefix);
  if (c.match_dim > 0) w.match = load_dpt_head_weights(src, c.match(), vggt_match_prefix);
  return w;
}

// A checkpoint on disk (VGGT's model.safetensors, or a reference bundle with prefix "param."), mmapped: F32 tensors
// are used in place, F16/BF16 converted once. Keeps the mapping alive as long as the weights.
template <class T>
struct VggtCheckpoint {
  io::ParamSource<T> source;
  VggtWeights<T> weights;

  static std::unique_ptr<VggtCheckpoint> open(const std::filesystem::path& path, const VggtConfig& c,
                                              const std::string& prefix = {}) {
    auto ck = std::make_unique<VggtCheckpoint>();
    ck->source = io::ParamSource<T>(safetensors::File::open(path), prefix);
    ck->weights = load_vggt_weights(ck->source, c);
    return ck;
  }
};

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
