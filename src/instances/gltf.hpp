#pragma once
#include "flexsplat/export/gltf.hpp"
#include "instance.hpp"
#define FLEXSPLAT_INSTANCES_GLTF(X) X(flexsplat::gltf::encode_glb, float) X(flexsplat::gltf::write_glb, float)
FLEXSPLAT_INSTANCES_GLTF(FLEXSPLAT_EXTERN_INSTANCE)
