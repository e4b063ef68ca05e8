#pragma once
// Umbrella header: everything flexsplat offers.
#include "flexsplat/core/version.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/half.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/core/parallel.hpp"
#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/core/simd.hpp"
#include "flexsplat/core/gemm.hpp"
#include "flexsplat/image/resample.hpp"
#include "flexsplat/geometry/preprocess.hpp"
#include "flexsplat/geometry/preprocess_reference.hpp"
