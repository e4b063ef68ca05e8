# ctest -j starts the tests of highest COST first; without it (a clean build has no cost history) it starts them in
# definition order, and the longest, defined last, run alone at the end. Seconds under ASan + UBSan (.ci/run's stage 2,
# docs/building.md#ci-and-compile-time; the consumer and MPI tests and the whole-model gradient checks run in stage 1
# only: estimates). A renamed test only loses its place in the queue. tests/CMakeLists.txt
# includes this file twice: at configure time for the tests it defines itself, and through TEST_INCLUDE_FILES at ctest
# time, after the Catch2 tests are discovered, for those.
set(flexsplat_test_costs
    "train:the whole model passes the float64 gradient check from the losses to every module's parameters|200"
    "train:with the point head, the match head and every camera loss on, the whole model passes the float64 gradient check, tensor by tensor|60"
    "check-reference: lpips_2024|77"
    "consumer_find_package|60"
    "consumer_add_subdirectory|60"
    "geometry:aggregator backward matches central differences (frame/global alternation, camera/register tokens, RoPE)|38"
    "nn:attention over several key blocks, fused q|k|v rows: scalar and SIMD paths match the dense definition|28"
    "geometry:VGGT end to end: images -> cameras, depth, confidence, world points, depth features, backward matches central differences for every parameter and the images (also through the depth head's image convolutions)|56"
    "train:appearance objective passes the float64 gradient check into parameters and geometry outputs|28"
    "cli: reconstruct and eval refuse bad inputs with a message|25"
    "nn:attention over several key blocks: float64 gradient check, 1 and 2 threads bit-identical on every path|22"
    "cli: eval and reconstruct with a one-step tiny model|21"
    "geometry:preprocess reference checker fails when it should|17"
    "cli: the shipped model reconstructs and beats a white image on spot|16"
    "geometry:DINO backward matches central differences (patch conv, tokens, resized position embedding, blocks, norm)|15"
    "geometry:block backward over more rows than one MLP chunk|15"
    "cli: train survives SIGKILL and resumes exactly|15"
    "loss:lpips matches the reference package on the shared lpips bundle (float64 all, float32 values)|14"
    "geometry:DPT head backward matches finite differences with exp depth and 1 + exp confidence|14"
    "geometry:block backward matches central differences (qk-norm, RoPE, LayerScale)|13"
    "cli: train write fault (full) keeps the checkpoint|12"
    "cli: train on 2 MPI ranks equals 1 process|11"
    "cli: train resumes exactly|11"
    "cli: train on 2 threads equals 1 thread|8"
    "nn:attention backward passes the float64 gradient check and is thread-count independent|11")
foreach(entry ${flexsplat_test_costs})
  string(FIND "${entry}" "|" bar REVERSE)
  string(SUBSTRING "${entry}" 0 ${bar} name)
  math(EXPR bar "${bar} + 1")
  string(SUBSTRING "${entry}" ${bar} -1 cost)
  if(NOT FLEXSPLAT_TEST_COSTS_AT_CONFIGURE)
    set_tests_properties("${name}" PROPERTIES COST ${cost})
  elseif(TEST "${name}")
    set_tests_properties("${name}" PROPERTIES COST ${cost})
  endif()
endforeach()
