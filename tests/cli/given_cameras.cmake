# reconstruct --cameras with the bundled spot's cameras written by `flexsplat cameras` as a COLMAP text model, a
# COLMAP binary model and a transforms.json: each writes a .glb holding the 4 given cameras; a photo the cameras do
# not name is refused with its name. (tests/model/test_given_cameras.cpp checks the splats are the same and in place.)
# -DFLEXSPLAT=exe -DOBJECT=dir -DWORK_DIR=dir
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})
set(images ${OBJECT}/images/009.png ${OBJECT}/images/015.png ${OBJECT}/images/026.png ${OBJECT}/images/004.png)
foreach(format colmap-text colmap-binary transforms)
  set(out ${WORK_DIR}/${format})
  if(format STREQUAL "transforms")
    set(out ${WORK_DIR}/transforms.json)
  endif()
  execute_process(COMMAND ${FLEXSPLAT} cameras ${OBJECT}/cameras.json -o ${out} --format ${format}
                  RESULT_VARIABLE code OUTPUT_VARIABLE stdout ERROR_VARIABLE err)
  if(NOT code EQUAL 0 OR NOT stdout MATCHES "cameras.json, 32 camera")
    message(FATAL_ERROR "cameras -> ${format} failed (${code}):\n${stdout}\n${err}")
  endif()
  execute_process(COMMAND ${FLEXSPLAT} reconstruct ${images} --cameras ${out} -o ${WORK_DIR}/${format}.glb
                  RESULT_VARIABLE code ERROR_VARIABLE err)
  if(NOT code EQUAL 0 OR NOT err MATCHES "4 camera\\(s\\) from the" OR NOT err MATCHES "the views' consistency")
    message(FATAL_ERROR "reconstruct --cameras ${out} failed (${code}):\n${err}")
  endif()
  execute_process(COMMAND ${FLEXSPLAT} info ${WORK_DIR}/${format}.glb RESULT_VARIABLE code OUTPUT_VARIABLE out)
  if(NOT code EQUAL 0 OR NOT out MATCHES "cameras: 4" OR NOT out MATCHES "009.png 256x256 fx=309.019")
    message(FATAL_ERROR "the .glb from ${format} does not hold the 4 given cameras at the photos' size:\n${out}")
  endif()
endforeach()
execute_process(COMMAND ${FLEXSPLAT} reconstruct ${OBJECT}/images/009.png ${CMAKE_CURRENT_LIST_DIR}/data/rgb_64x48.png
                        --cameras ${WORK_DIR}/colmap-text -o ${WORK_DIR}/bad.glb
                RESULT_VARIABLE code ERROR_VARIABLE err)
if(code EQUAL 0 OR NOT err MATCHES "has no camera for image '.*rgb_64x48.png'")
  message(FATAL_ERROR "a photo without a camera was not refused by name (${code}):\n${err}")
endif()
