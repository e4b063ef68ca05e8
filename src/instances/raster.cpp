// The one definition of the float/double instances declared in raster.hpp (see instance.hpp).
#include "raster.hpp"

FLEXSPLAT_INSTANCES_RASTER(FLEXSPLAT_INSTANCE)
