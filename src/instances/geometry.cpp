// The one definition of the float/double instances declared in geometry.hpp (see instance.hpp).
#include "geometry.hpp"

FLEXSPLAT_INSTANCES_GEOMETRY(FLEXSPLAT_INSTANCE)
