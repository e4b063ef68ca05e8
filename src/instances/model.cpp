// The one definition of the float/double instances declared in model.hpp (see instance.hpp).
#include "decoder.hpp"
#include "geometry.hpp"
#include "lpips.hpp"
#include "raster.hpp"
#include "model.hpp"

FLEXSPLAT_INSTANCES_MODEL(FLEXSPLAT_INSTANCE)
