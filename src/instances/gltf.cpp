// The one definition of the float/double instances declared in gltf.hpp (see instance.hpp).
#include "gltf.hpp"

FLEXSPLAT_INSTANCES_GLTF(FLEXSPLAT_INSTANCE)
