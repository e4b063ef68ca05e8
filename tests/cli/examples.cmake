# The single-file examples on the bundled spot: examples/reconstruct (shipped model, 4 input photos) writes a .glb that
# `flexsplat info` reads with its 4 cameras, and examples/turntable renders that .glb into a PNG strip whose size is
# the grid's (8 views of 48x48: 8 x (48 + 6) + 6 = 438 by 48 + 16 + 12 = 76) and whose views the object covers.
# -DFLEXSPLAT=exe -DRECONSTRUCT=exe -DTURNTABLE=exe -DOBJECT=dir -DWORK_DIR=dir
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})
execute_process(COMMAND ${RECONSTRUCT} -o ${WORK_DIR}/spot.glb ${OBJECT}/images/008.png ${OBJECT}/images/010.png
                        ${OBJECT}/images/012.png ${OBJECT}/images/014.png
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT out MATCHES "spot.glb: [0-9]+ Gaussians from 4 photos")
  message(FATAL_ERROR "examples/reconstruct failed (${code}):\n${out}\n${err}")
endif()
execute_process(COMMAND ${FLEXSPLAT} info ${WORK_DIR}/spot.glb RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT out MATCHES "cameras: 4")
  message(FATAL_ERROR "examples/reconstruct's .glb does not load with its 4 cameras (${code}):\n${out}\n${err}")
endif()

execute_process(COMMAND ${TURNTABLE} ${WORK_DIR}/spot.glb -o ${WORK_DIR}/turntable.png --views 8 --size 48
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT EXISTS ${WORK_DIR}/turntable.png)
  message(FATAL_ERROR "examples/turntable failed (${code}):\n${out}\n${err}")
endif()
# PNG: 8-byte signature, IHDR length and type, then width and height as big-endian 32-bit integers.
file(READ ${WORK_DIR}/turntable.png header LIMIT 24 HEX)
string(SUBSTRING "${header}" 32 8 width_hex)
string(SUBSTRING "${header}" 40 8 height_hex)
math(EXPR width "0x${width_hex}")
math(EXPR height "0x${height_hex}")
if(NOT header MATCHES "^89504e470d0a1a0a" OR NOT width EQUAL 438 OR NOT height EQUAL 76)
  message(FATAL_ERROR "turntable.png is ${width} x ${height} (header ${header}), expected a 438 x 76 PNG")
endif()
# Not blank: the object must darken at least 2% of the white views' pixels (and cannot fill them all).
if(NOT out MATCHES "object covers ([0-9.]+)% of the views")
  message(FATAL_ERROR "examples/turntable did not report its coverage:\n${out}")
endif()
set(covered ${CMAKE_MATCH_1})
if(covered LESS 2 OR covered GREATER 99)
  message(FATAL_ERROR "turntable of the reconstruction: the object covers ${covered}% of the views")
endif()
# A .ply without cameras turns about world z.
execute_process(COMMAND ${FLEXSPLAT} convert ${WORK_DIR}/spot.glb ${WORK_DIR}/spot.ply RESULT_VARIABLE code ERROR_VARIABLE err)
execute_process(COMMAND ${TURNTABLE} ${WORK_DIR}/spot.ply -o ${WORK_DIR}/ply.png --views 4 --size 32
                RESULT_VARIABLE code2 OUTPUT_VARIABLE out ERROR_VARIABLE err2)
if(NOT code EQUAL 0 OR NOT code2 EQUAL 0 OR NOT out MATCHES "4 views of 32x32")
  message(FATAL_ERROR "turntable of a .ply failed (${code}, ${code2}):\n${err}\n${out}\n${err2}")
endif()
message(STATUS "examples: spot.glb with 4 cameras; turntable ${width} x ${height}, object covers ${covered}% of the views")
