#pragma once
#include "flexsplat/raster/render.hpp"
#include "instance.hpp"
#define FLEXSPLAT_INSTANCES_RASTER(X)                                                                                  \
  X(flexsplat::raster::render_forward, float) X(flexsplat::raster::render_forward, double)                             \
  X(flexsplat::raster::render_backward, float) X(flexsplat::raster::render_backward, double)
FLEXSPLAT_INSTANCES_RASTER(FLEXSPLAT_EXTERN_INSTANCE)
