#pragma once
#include "flexsplat/geometry/vggt.hpp"
#include "instance.hpp"
#define FLEXSPLAT_INSTANCES_GEOMETRY_T(X, T)                                                                           \
  X(flexsplat::io::check_parameters, T) X(flexsplat::geometry::load_vggt_weights, T)                             \
  X(flexsplat::geometry::load_aggregator_trunk_weights, T) X(flexsplat::geometry::load_camera_head_weights, T)         \
  X(flexsplat::geometry::dino_forward, T) X(flexsplat::geometry::dino_backward, T)                                     \
  X(flexsplat::geometry::aggregator_trunk_forward, T) X(flexsplat::geometry::aggregator_trunk_forward_train, T)        \
  X(flexsplat::geometry::aggregator_trunk_backward, T)                                                                 \
  X(flexsplat::geometry::camera_head_forward, T) X(flexsplat::geometry::camera_head_forward_train, T)                  \
  X(flexsplat::geometry::camera_head_backward, T)                                                                      \
  X(flexsplat::geometry::dpt_head_forward, T) X(flexsplat::geometry::dpt_head_forward_train, T)                        \
  X(flexsplat::geometry::dpt_head_backward, T)                                                                         \
  X(flexsplat::geometry::vggt_forward, T) X(flexsplat::geometry::vggt_forward_train, T)                                \
  X(flexsplat::geometry::vggt_backward, T)
#define FLEXSPLAT_INSTANCES_GEOMETRY(X) FLEXSPLAT_INSTANCES_GEOMETRY_T(X, float) FLEXSPLAT_INSTANCES_GEOMETRY_T(X, double)
FLEXSPLAT_INSTANCES_GEOMETRY(FLEXSPLAT_EXTERN_INSTANCE)
