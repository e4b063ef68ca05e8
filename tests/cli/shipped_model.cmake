# The shipped model (the default without --model) on the bundled spot: reconstruct writes a .glb with its 4 cameras,
# and eval scores it at least 3 dB above a white image with cameras within 15 degrees (docs/evaluation.md has the full table).
# -DFLEXSPLAT=exe -DOBJECT=dir -DWORK_DIR=dir
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})
execute_process(COMMAND ${FLEXSPLAT} reconstruct ${OBJECT}/images/008.png ${OBJECT}/images/010.png
                        ${OBJECT}/images/012.png ${OBJECT}/images/014.png -o ${WORK_DIR}/spot.glb
                RESULT_VARIABLE code ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT EXISTS ${WORK_DIR}/spot.glb)
  message(FATAL_ERROR "reconstruct with the shipped model failed (${code}):\n${err}")
endif()
execute_process(COMMAND ${FLEXSPLAT} info ${WORK_DIR}/spot.glb RESULT_VARIABLE code OUTPUT_VARIABLE out)
if(NOT code EQUAL 0 OR NOT out MATCHES "cameras: 4")
  message(FATAL_ERROR "the reconstructed .glb does not hold the 4 predicted cameras:\n${out}")
endif()
execute_process(COMMAND ${FLEXSPLAT} eval ${OBJECT} --baseline white --quiet --json ${WORK_DIR}/eval.json
                RESULT_VARIABLE code ERROR_VARIABLE err)
if(NOT code EQUAL 0)
  message(FATAL_ERROR "eval with the shipped model failed (${code}):\n${err}")
endif()
file(READ ${WORK_DIR}/eval.json j)
string(JSON psnr GET "${j}" mean psnr)
string(JSON rot GET "${j}" mean rotation_error_deg)
string(JSON white GET "${j}" baselines white mean psnr)
# Whole decibels: the model must lead the white image by at least 3 dB.
string(REGEX REPLACE "\\..*" "" psnr_int "${psnr}")
string(REGEX REPLACE "\\..*" "" white_int "${white}")
math(EXPR margin "${psnr_int} - ${white_int}")
if(margin LESS 3 OR rot GREATER 15)
  message(FATAL_ERROR "shipped model on spot: PSNR ${psnr} dB (white ${white} dB), rotation error ${rot} deg")
endif()
message(STATUS "shipped model on spot: PSNR ${psnr} dB, white ${white} dB, rotation error ${rot} deg")
