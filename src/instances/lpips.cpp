// The one definition of the float/double instances declared in lpips.hpp (see instance.hpp).
#include "lpips.hpp"

FLEXSPLAT_INSTANCES_LPIPS(FLEXSPLAT_INSTANCE)
