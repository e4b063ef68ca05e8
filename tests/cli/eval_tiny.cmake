# flexsplat eval and reconstruct end to end with a one-step tiny model (flexsplat train): eval on one shared object
# with the white baseline (the JSON must have the issue's keys and finite numbers in range); eval with --refine-steps,
# --rotation-noise and the posed-fit baseline (their keys, the same noise twice, refusals); reconstruct writes a .glb
# with the predicted cameras and a turntable, refines with --refine, and refuses an unreadable image and too many views.
# The one-step model's cameras are 130-150 degrees off, so after alignment its Gaussians fall outside the targets: it
# scores the white image's PSNR and SSIM (to the last digit here). Its scores are held to the white image's plus 2 dB /
# minus 1 dB (a few stray Gaussians in view move the PSNR by well under 1 dB; a black image scores about 1 dB on these
# mostly white targets, a [0, 255] scale 48 dB more), the white image's to its measured value within 0.05 dB (the
# scorer's rounding is far below that; another target, crop or compositing moves it by more).
# -DFLEXSPLAT=exe -DCONFIG=json -DOBJECT=dir -DWORK_DIR=dir
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})
function(run)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(NOT code EQUAL 0)
    message(FATAL_ERROR "command failed (${code}): ${ARGN}\n${out}\n${err}")
  endif()
  message(STATUS "${out}")
endfunction()
run(${FLEXSPLAT} train --quiet --config ${CONFIG} --data procedural --out ${WORK_DIR}/run)
run(${FLEXSPLAT} eval ${OBJECT} --model ${WORK_DIR}/run/model.safetensors --max-targets 4 --baseline white --quiet
    --json ${WORK_DIR}/eval.json --grid ${WORK_DIR}/grid.png)
if(NOT EXISTS ${WORK_DIR}/grid.png)
  message(FATAL_ERROR "eval --grid wrote no ${WORK_DIR}/grid.png")
endif()
file(READ ${WORK_DIR}/eval.json doc)
string(JSON model GET "${doc}" model)
string(JSON n LENGTH "${doc}" objects)
if(NOT n EQUAL 1)
  message(FATAL_ERROR "eval.json has ${n} objects, expected 1")
endif()
# value(json_path... ) -> var; checks lo <= value <= hi (a number, so finite).
function(check_range label lo hi)
  string(JSON v GET "${doc}" ${ARGN})
  if(NOT v MATCHES "^-?[0-9.]+([eE][-+]?[0-9]+)?$" OR v LESS lo OR v GREATER hi)
    message(FATAL_ERROR "${label} = '${v}' is not a number in [${lo}, ${hi}]")
  endif()
endfunction()
foreach(where "objects;0" "mean")
  string(REPLACE ";" " " label "${where}")
  check_range("${label} psnr" 7.27 10.27 ${where} psnr)  # white: 8.269 (4 targets)
  check_range("${label} ssim" 0.70 0.76 ${where} ssim)  # white: 0.7306
  check_range("${label} rotation_error_deg" 0 180 ${where} rotation_error_deg)
  check_range("${label} center_error_rel" 0 100 ${where} center_error_rel)
  check_range("${label} seconds" 0 60 ${where} seconds)
  string(JSON lp TYPE "${doc}" ${where} lpips)
  if(NOT lp STREQUAL "NULL")
    message(FATAL_ERROR "${label} lpips is ${lp} without --lpips, expected null")
  endif()
endforeach()
string(JSON name GET "${doc}" objects 0 name)
check_range("white psnr" 8.22 8.32 baselines white objects 0 psnr)  # measured 8.269
check_range("white ssim" 0.725 0.735 baselines white objects 0 ssim)  # measured 0.7306
string(JSON rt TYPE "${doc}" baselines white objects 0 rotation_error_deg)
if(NOT rt STREQUAL "NULL")
  message(FATAL_ERROR "the white baseline has a rotation error (${rt}); it has no cameras")
endif()
message(STATUS "eval.json: model ${model}, object ${name}")
# Scored at the folder's own size by default (the shared renders are 256 x 256), at the model's with --resolution model.
string(JSON res GET "${doc}" resolution)
string(JSON rh GET "${doc}" objects 0 resolution 0)
string(JSON rw GET "${doc}" objects 0 resolution 1)
if(NOT res STREQUAL "native" OR NOT rh EQUAL 256 OR NOT rw EQUAL 256)
  message(FATAL_ERROR "eval.json: resolution '${res}' [${rh}, ${rw}], expected native [256, 256]")
endif()
run(${FLEXSPLAT} eval ${OBJECT} --model ${WORK_DIR}/run/model.safetensors --max-targets 2 --quiet --resolution model
    --json ${WORK_DIR}/eval_model_size.json)
file(READ ${WORK_DIR}/eval_model_size.json doc_m)
string(JSON res GET "${doc_m}" resolution)
string(JSON rh GET "${doc_m}" objects 0 resolution 0)
if(NOT res MATCHES "^model$" OR NOT rh EQUAL 28)  # MATCHES: "model" also names a variable here
  message(FATAL_ERROR "eval --resolution model: resolution '${res}', height ${rh}, expected model, 28 (the tiny model)")
endif()

# --refine-steps, --rotation-noise and --baseline posed-fit: keys and ranges; the same seed gives the same noise.
# --refine-steps 20 (no time budget): the held-out trial runs 20 steps whatever the machine's speed, scored every 10.
foreach(run a b)
  run(${FLEXSPLAT} eval ${OBJECT} --model ${WORK_DIR}/run/model.safetensors --max-targets 2 --quiet --refine-steps 20
      --refine-size 64 --refine-validate on --rotation-noise 10 --seed 4 --baseline white,posed-fit
      --json ${WORK_DIR}/eval_${run}.json)
endforeach()
file(READ ${WORK_DIR}/eval_a.json doc)
file(READ ${WORK_DIR}/eval_b.json doc_b)
check_range("refine_seconds" 0 0 refine_seconds)
check_range("refine_steps" 20 20 refine_steps)
check_range("rotation_noise_deg" 10 10 rotation_noise_deg)
# The white image scores 9.575 on these 2 targets; the model (feed-forward and refined) scores it too (see the top).
check_range("white psnr" 9.525 9.625 baselines white objects 0 psnr)
check_range("refined psnr" 8.575 11.575 objects 0 psnr)
check_range("feed-forward psnr" 8.575 11.575 objects 0 feed_forward psnr)
check_range("feed-forward rotation error" 0 180 objects 0 feed_forward rotation_error_deg)
check_range("refine trial steps" 20 20 objects 0 refine trial_steps)
# The trial's outcome depends on the one-step model's cameras, which the GEMM backend's rounding moves (stage 1 of CI
# keeps 10 steps; the sanitizer stage's Eigen GEMMs keep carving and growth with 0 steps at 64 x 64 and nothing at
# 256 x 256; tests/eval/test_refine.cpp checks the decisions on fixed scenes): the JSON must be consistent with any.
# The kept step count is a scoring point (0, 10 or 20). A start the held-out view liked better (its loss fell) means
# the default 4096 Gaussians grown, a few of the 48 predicted ones, seen on the background, carved (39 here) and the
# input views' loss lower; otherwise the input set unchanged: nothing grown or carved, no step, the loss as it started.
string(JSON steps GET "${doc}" objects 0 refine steps)
if(NOT (steps EQUAL 0 OR steps EQUAL 10 OR steps EQUAL 20))
  message(FATAL_ERROR "refine steps = ${steps}: expected 0, 10 or 20, the trial's scoring points")
endif()
function(check_below label a b)
  string(JSON va GET "${doc}" ${a})
  string(JSON vb GET "${doc}" ${b})
  if(NOT va LESS vb)
    message(FATAL_ERROR "${label}: ${va} is not below ${vb}")
  endif()
endfunction()
string(JSON held_best GET "${doc}" objects 0 refine holdout_loss_best)
string(JSON held_initial GET "${doc}" objects 0 refine holdout_loss_initial)
if(held_best LESS held_initial)
  check_range("refine grown" 4096 4096 objects 0 refine grown)
  check_range("refine carved" 1 47 objects 0 refine carved)
  check_below("input views' loss" "objects;0;refine;loss_final" "objects;0;refine;loss_initial")
elseif(held_best EQUAL held_initial)
  check_range("refine steps (input kept)" 0 0 objects 0 refine steps)
  check_range("refine grown (input kept)" 0 0 objects 0 refine grown)
  check_range("refine carved (input kept)" 0 0 objects 0 refine carved)
  string(JSON lf GET "${doc}" objects 0 refine loss_final)
  string(JSON li GET "${doc}" objects 0 refine loss_initial)
  if(NOT lf EQUAL li)
    message(FATAL_ERROR "the input set was kept, yet the input views' loss moved from ${li} to ${lf}")
  endif()
else()
  message(FATAL_ERROR "the held-out view's best loss ${held_best} is above its start ${held_initial}")
endif()
check_range("refine size" 64 64 objects 0 refine size 0)  # --refine-size 64: the longer side
check_range("refine held-out loss" 0 1 objects 0 refine holdout_loss_best)
check_range("refine loss" 0 1 objects 0 refine loss_final)
# The refined Gaussians still fall outside the targets (the cameras are as far off): no change beyond 1 dB.
check_range("psnr change" -1 1 objects 0 refine psnr_change)
check_range("mean psnr change" -1 1 mean psnr_change)
# The posed fit gets the model's seconds (wall clock by design: the baseline is "as long as the model took"), so only
# its range is checked.
check_range("posed-fit psnr" 1 60 baselines posed-fit objects 0 psnr)
check_range("posed-fit ssim" -1 1 baselines posed-fit mean ssim)
check_range("posed-fit seconds" 0 60 baselines posed-fit objects 0 seconds)
string(JSON rt TYPE "${doc}" baselines posed-fit objects 0 rotation_error_deg)
if(NOT rt STREQUAL "NULL")
  message(FATAL_ERROR "the posed-fit baseline has a rotation error (${rt}); it is given the cameras")
endif()
string(JSON noisy_a GET "${doc}" objects 0 feed_forward rotation_error_deg)
string(JSON noisy_b GET "${doc_b}" objects 0 feed_forward rotation_error_deg)
string(JSON clean GET "${doc}" objects 0 rotation_error_deg)
if(NOT noisy_a STREQUAL noisy_b)
  message(FATAL_ERROR "--rotation-noise 10 --seed 4 gave rotation errors ${noisy_a} and ${noisy_b} in two runs")
endif()
# Without the held-out trial the growth always happens: the default count in the JSON, and the steps asked for.
run(${FLEXSPLAT} eval ${OBJECT} --model ${WORK_DIR}/run/model.safetensors --max-targets 1 --quiet --refine-steps 2
    --json ${WORK_DIR}/eval_grow.json)
file(READ ${WORK_DIR}/eval_grow.json doc)
check_range("refine grown without the trial" 4096 4096 objects 0 refine grown)
check_range("refine steps without the trial" 2 2 objects 0 refine steps)
check_range("refine size by default" 256 256 objects 0 refine size 0)  # the photos' own resolution
function(expect_eval_refusal pattern)
  execute_process(COMMAND ${FLEXSPLAT} eval ${OBJECT} --model ${WORK_DIR}/run/model.safetensors --quiet ${ARGN}
                  RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(code EQUAL 0 OR NOT err MATCHES "${pattern}")
    message(FATAL_ERROR "eval ${ARGN} gave exit code ${code} and '${err}', expected an error matching '${pattern}'")
  endif()
endfunction()
expect_eval_refusal("--refine '-1' must be a positive number" --refine -1)
expect_eval_refusal("--rotation-noise 200 must be at most 180" --rotation-noise 200)
expect_eval_refusal("--baseline 'posed' is not known" --baseline white,posed)
expect_eval_refusal("--resolution 'full' is neither 'native'" --resolution full)
expect_eval_refusal("--refine-validate 'yes': expected on or off" --refine 1 --refine-validate yes)
expect_eval_refusal("--refine-size '0': expected an integer in \\[1, 16384\\]" --refine 1 --refine-size 0)
expect_eval_refusal("--refine-grow need --refine SECONDS or --refine-steps N" --refine-carve off)
expect_eval_refusal("--refine-steps '0': expected an integer in \\[1, 100000000\\]" --refine-steps 0)
expect_eval_refusal("--refine-grow need --refine SECONDS" --refine-grow 10)
expect_eval_refusal("--refine-grow '-1': expected an integer in \\[0, 16777216\\]" --refine 1 --refine-grow -1)
expect_eval_refusal("--budget 'half': expected full, auto or auto:CELLS" --budget half)

# --budget auto: the JSON names it and counts the queries that ran, at most the budget's 48 and at least one (spot
# covers a quarter of each view); the same set of views with the whole budget runs all 48.
run(${FLEXSPLAT} eval ${OBJECT} --model ${WORK_DIR}/run/model.safetensors --max-targets 1 --quiet --budget auto
    --json ${WORK_DIR}/eval_auto.json)
file(READ ${WORK_DIR}/eval_auto.json doc)
string(JSON b GET "${doc}" budget)
if(NOT b STREQUAL "auto")
  message(FATAL_ERROR "eval --budget auto: JSON budget '${b}'")
endif()
check_range("auto budget" 48 48 objects 0 budget)
check_range("auto budget's Gaussians" 1 47 objects 0 gaussians)
file(READ ${WORK_DIR}/eval_grow.json doc)
check_range("whole budget's Gaussians" 48 48 objects 0 gaussians)

set(images ${OBJECT}/images/000.png ${OBJECT}/images/001.png)
execute_process(COMMAND ${FLEXSPLAT} reconstruct ${images} --model ${WORK_DIR}/run/model.safetensors -o ${WORK_DIR}/out.glb
                        --turntable ${WORK_DIR}/turntable.png --verbose --compact off
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT out MATCHES "out.glb: 48 Gaussians, 2 camera\\(s\\)" OR NOT out MATCHES "decoder"
   OR NOT EXISTS ${WORK_DIR}/turntable.png)
  message(FATAL_ERROR "reconstruct failed (${code}):\n${out}\n${err}")
endif()
# The turntable is at the photos' 256 x 256: 8 frames and 7 gaps of 2 pixels (the PNG header's width and height).
file(READ ${WORK_DIR}/turntable.png ihdr OFFSET 16 LIMIT 8 HEX)
if(NOT ihdr STREQUAL "0000080e00000100")
  message(FATAL_ERROR "turntable.png is not 2062 x 256 (IHDR width, height: ${ihdr})")
endif()
function(expect_refusal pattern)
  execute_process(COMMAND ${FLEXSPLAT} reconstruct ${ARGN} --model ${WORK_DIR}/run/model.safetensors -o ${WORK_DIR}/bad.glb
                  RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(code EQUAL 0 OR NOT err MATCHES "${pattern}")
    message(FATAL_ERROR "reconstruct ${ARGN} gave exit code ${code} and '${err}', expected an error matching '${pattern}'")
  endif()
endfunction()
execute_process(COMMAND ${FLEXSPLAT} reconstruct ${images} --model ${WORK_DIR}/run/model.safetensors -o ${WORK_DIR}/refined.ply
                        --refine 0.2 --refine-size 64 --refine-validate on
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT err MATCHES "refining for 0.2 s on the input views at 64 x 64"
   OR NOT err MATCHES "held-out trial of [0-9]+ steps" OR NOT err MATCHES "[0-9]+ refinement steps, loss on the inputs"
   OR NOT EXISTS ${WORK_DIR}/refined.ply)
  message(FATAL_ERROR "reconstruct --refine failed (${code}):\n${out}\n${err}")
endif()
# Without the trial the growth always happens: the count asked for (the trial above may keep the input unchanged).
execute_process(COMMAND ${FLEXSPLAT} reconstruct ${images} --model ${WORK_DIR}/run/model.safetensors -o ${WORK_DIR}/grown.ply
                        --refine 0.2 --refine-size 64 --refine-grow 500
                RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT err MATCHES " 500 grown in the silhouettes" OR NOT EXISTS ${WORK_DIR}/grown.ply)
  message(FATAL_ERROR "reconstruct --refine-grow 500 failed (${code}):\n${out}\n${err}")
endif()
execute_process(COMMAND ${FLEXSPLAT} reconstruct ${images} --model ${WORK_DIR}/run/model.safetensors -o ${WORK_DIR}/auto.glb
                        --budget auto --compact off RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT code EQUAL 0 OR NOT err MATCHES "--budget auto: the decoder ran ([0-9]+) of the budget's 48 queries")
  message(FATAL_ERROR "reconstruct --budget auto failed (${code}):\n${out}\n${err}")
endif()
set(ran ${CMAKE_MATCH_1})
if(ran LESS 1 OR ran GREATER 47 OR NOT out MATCHES "auto.glb: ${ran} Gaussians")
  message(FATAL_ERROR "reconstruct --budget auto ran ${ran} of 48 queries and wrote:\n${out}")
endif()
expect_refusal("--budget 'some': expected full or auto" ${images} --budget some)
expect_refusal("cannot decode" ${CONFIG})
expect_refusal("5 images; the model takes 1 to 4" ${images} ${images} ${OBJECT}/images/002.png)
