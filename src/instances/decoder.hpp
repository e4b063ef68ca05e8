#pragma once
#include "flexsplat/decoder/model.hpp"
#include "instance.hpp"
#define FLEXSPLAT_INSTANCES_DECODER(X)                                                                                 \
  X(flexsplat::decoder::decoder_forward, float) X(flexsplat::decoder::decoder_forward, double)                         \
  X(flexsplat::decoder::decoder_backward, float) X(flexsplat::decoder::decoder_backward, double)                       \
  X(flexsplat::decoder::model_init, float) X(flexsplat::decoder::model_init, double)                                   \
  X(flexsplat::decoder::model_forward, float) X(flexsplat::decoder::model_forward, double)                             \
  X(flexsplat::decoder::model_backward, float) X(flexsplat::decoder::model_backward, double)
FLEXSPLAT_INSTANCES_DECODER(FLEXSPLAT_EXTERN_INSTANCE)
