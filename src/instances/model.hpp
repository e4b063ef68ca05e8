#pragma once
#include "flexsplat/train/step.hpp"
#include "instance.hpp"
#define FLEXSPLAT_INSTANCES_MODEL(X)                                                                                   \
  X(flexsplat::model::geometry_stage_forward, float) X(flexsplat::model::geometry_stage_forward, double)               \
  X(flexsplat::model::geometry_stage_backward, float) X(flexsplat::model::geometry_stage_backward, double)             \
  X(flexsplat::model::appearance_objective, float) X(flexsplat::model::appearance_objective, double)                   \
  X(flexsplat::model::make_train_example, float) X(flexsplat::model::make_train_example, double)                       \
  X(flexsplat::model::scene_loss, float) X(flexsplat::model::scene_loss, double)                                       \
  X(flexsplat::model::scene_gradient, float) X(flexsplat::model::scene_gradient, double)                               \
  X(flexsplat::model::train_step, float) X(flexsplat::model::load_flexsplat, float)
FLEXSPLAT_INSTANCES_MODEL(FLEXSPLAT_EXTERN_INSTANCE)
