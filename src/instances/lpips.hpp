#pragma once
#include "flexsplat/loss/lpips.hpp"
#include "instance.hpp"
#define FLEXSPLAT_INSTANCES_LPIPS(X)                                                                                   \
  X(flexsplat::loss::lpips_forward, float) X(flexsplat::loss::lpips_forward, double)                                   \
  X(flexsplat::loss::lpips_backward, float) X(flexsplat::loss::lpips_backward, double)
FLEXSPLAT_INSTANCES_LPIPS(FLEXSPLAT_EXTERN_INSTANCE)
