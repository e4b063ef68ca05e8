# The umbrella header include/flexsplat/flexsplat.hpp includes every public header of include/flexsplat directly
# (the test helpers of flexsplat/testing/ excepted: they are included on their own), and nothing else.
# -DSOURCE_DIR=repository root
set(root ${SOURCE_DIR}/include/flexsplat)
file(GLOB_RECURSE public RELATIVE ${root} ${root}/*.hpp)
list(FILTER public EXCLUDE REGEX "^(testing/.*|flexsplat\\.hpp)$")
list(LENGTH public count)
if(count LESS 100)
  message(FATAL_ERROR "only ${count} public headers found in include/flexsplat: the scan is broken")
endif()
file(STRINGS ${root}/flexsplat.hpp lines REGEX "^[ \t]*#[ \t]*include[ \t]*\"flexsplat/")
list(TRANSFORM lines REPLACE "^[^\"]*\"flexsplat/([^\"]+)\".*" "\\1" OUTPUT_VARIABLE included)
set(missing ${public})
list(REMOVE_ITEM missing ${included})
set(unknown ${included})
list(REMOVE_ITEM unknown ${public})
if(missing OR unknown)
  list(JOIN missing ", " missing_text)
  list(JOIN unknown ", " unknown_text)
  message(FATAL_ERROR "include/flexsplat/flexsplat.hpp does not include public headers [${missing_text}] and includes "
                      "what is no public header [${unknown_text}] (test helpers are included on their own)")
endif()
message(STATUS "flexsplat.hpp includes all ${count} public headers")
