// The one definition of the float/double instances declared in decoder.hpp (see instance.hpp).
#include "decoder.hpp"

FLEXSPLAT_INSTANCES_DECODER(FLEXSPLAT_INSTANCE)
