# `flexsplat train --init VGGT_FILE`: a VGGT state dict (the reference bundle, names under "param.") initialises the
# geometry; at lr 0 the saved model holds the file's tensors byte for byte. A file without VGGT tensors is refused.
# -DFLEXSPLAT=exe -DCONFIG=json -DBUNDLE=vggt.safetensors -DNOT_VGGT=other.safetensors -DWORK_DIR=dir
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})
execute_process(COMMAND ${FLEXSPLAT} train --config ${CONFIG} --data procedural --out ${WORK_DIR}/run --init ${BUNDLE}
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0)
  message(FATAL_ERROR "train --init failed (${code}):\n${out}\n${err}")
endif()
if(NOT err MATCHES "geometry initialised from")
  message(FATAL_ERROR "train --init did not report the initialisation:\n${err}")
endif()

# Hex of tensor NAME's bytes in safetensors FILE (header: 8-byte little-endian length, then JSON).
function(tensor_hex file name result)
  file(READ ${file} len_hex LIMIT 8 HEX)
  set(len 0)
  foreach(i RANGE 7 0 -1)
    math(EXPR pos "${i} * 2")
    string(SUBSTRING "${len_hex}" ${pos} 2 byte)
    math(EXPR len "${len} * 256 + 0x${byte}")
  endforeach()
  file(READ ${file} header OFFSET 8 LIMIT ${len})
  string(JSON begin GET "${header}" "${name}" data_offsets 0)
  string(JSON end GET "${header}" "${name}" data_offsets 1)
  string(JSON dtype GET "${header}" "${name}" dtype)
  math(EXPR offset "8 + ${len} + ${begin}")
  math(EXPR size "${end} - ${begin}")
  file(READ ${file} bytes OFFSET ${offset} LIMIT ${size} HEX)
  set(${result} "${dtype}:${bytes}" PARENT_SCOPE)
endfunction()

foreach(name aggregator.camera_token aggregator.frame_blocks.0.attn.qkv.weight camera_head.pose_branch.fc2.bias
             depth_head.scratch.output_conv2.2.weight)
  tensor_hex(${WORK_DIR}/run/model.safetensors ${name} got)
  tensor_hex(${BUNDLE} param.${name} expected)
  if(NOT got STREQUAL expected)
    message(FATAL_ERROR "${name}: the trained model's tensor differs from the --init file's")
  endif()
endforeach()

execute_process(COMMAND ${FLEXSPLAT} train --config ${CONFIG} --data procedural --out ${WORK_DIR}/bad --init ${NOT_VGGT}
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(code EQUAL 0 OR NOT err MATCHES "not a VGGT state dict")
  message(FATAL_ERROR "train --init with a non-VGGT file: exit ${code}, expected a refusal naming it:\n${err}")
endif()
message(STATUS "train --init: geometry equals the VGGT file; a non-VGGT file is refused")
