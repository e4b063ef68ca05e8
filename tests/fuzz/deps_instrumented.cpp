// stb_image and tinygltf implementations compiled with the fuzzers' instrumentation (Debian ships them as libstb.so
// and libtinygltf.so, which libFuzzer could neither guide through nor check with ASan/UBSan).
#define STB_IMAGE_IMPLEMENTATION
#define STB_IMAGE_WRITE_IMPLEMENTATION
#define TINYGLTF_IMPLEMENTATION
#include <stb/stb_image.h>
#include <stb/stb_image_write.h>
// tiny_gltf.h includes the stb headers again: their implementation parts must not be emitted twice.
#undef STB_IMAGE_IMPLEMENTATION
#undef STB_IMAGE_WRITE_IMPLEMENTATION
#include <tiny_gltf.h>
