#pragma once
// VGGT's image preprocessing, vggt/utils/load_fn.py `load_and_preprocess_images(image_path_list, mode)` at
// facebookresearch/vggt 44b3afb, reproduced exactly:
//  1. an "RGBA" image is alpha-composited onto an opaque white RGBA background (Pillow's integer
//     Image.alpha_composite) and every image is converted to "RGB" (other modes: Pillow's convert("RGB"), which
//     drops an "LA" alpha without compositing and clips 16-bit greyscale at 255);
//  2. target sizes: crop mode sets the width to 518 and the height to round(h * (518 / w) / 14) * 14; pad mode does
//     the same for the longer side (width when w >= h). `round` is Python's: ties to even;
//  3. Pillow BICUBIC resize (flexsplat/image/resample.hpp), then ToTensor (uint8 / 255 in float32);
//  4. crop mode: centre crop of the height to 518 when it is taller; pad mode: centred white (1.0) padding to
//     518 x 518 (top/left get the smaller half);
//  5. when the images end up with different shapes, each is padded with white, centred, to the largest height and
//     the largest width of the batch.
// Output: float [S, 3, H, W] in [0, 1], contiguous.
//
// Input buffers are interleaved 8-bit (see resample.hpp): channels 1 = Pillow "L", 2 = "LA", 3 = "RGB",
// 4 = "RGBA" (straight alpha). The file overload decodes PNG so that the buffer holds what Pillow 9.4's PNG plugin
// would give (mode chosen from the IHDR colour type and bit depth); other formats go through stb_image, whose JPEG
// decoder is not libjpeg's (values may differ by a few units).
#include <stb/stb_image.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <iterator>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/image/resample.hpp"

namespace flexsplat {
inline namespace v0 {

inline constexpr index_t vggt_target_size = 518;
inline constexpr index_t vggt_patch_size = 14;
inline constexpr float vggt_pad_value = 1.0f;

enum class VggtPreprocessMode { crop, pad };

inline VggtPreprocessMode parse_vggt_preprocess_mode(std::string_view name) {
  if (name == "crop") return VggtPreprocessMode::crop;
  if (name == "pad") return VggtPreprocessMode::pad;
  fail("Mode must be either 'crop' or 'pad' (got '", name, "')");
}

inline const char* vggt_preprocess_mode_name(VggtPreprocessMode mode) {
  return mode == VggtPreprocessMode::crop ? "crop" : "pad";
}

// Non-owning interleaved 8-bit image: pixel (x, y) channel c at pixels[(y * width + x) * channels + c].
struct InterleavedImageView {
  const std::uint8_t* pixels = nullptr;
  index_t width = 0, height = 0;
  int channels = 0;
};

// Owning interleaved 8-bit image (what the decoder returns).
struct InterleavedImage {
  index_t width = 0, height = 0;
  int channels = 0;
  std::vector<std::uint8_t> pixels;
  InterleavedImageView view() const { return {pixels.data(), width, height, channels}; }
};

// Python 3 round() of a double to an integer: nearest, ties to even.
inline double python_round(double x) {
  const double lower = std::floor(x);
  const double diff = x - lower;
  if (diff < 0.5) return lower;
  if (diff > 0.5) return lower + 1.0;
  return std::fmod(lower, 2.0) == 0.0 ? lower : lower + 1.0;
}

struct VggtResizeTarget {
  index_t width = 0, height = 0;
};

// The (new_width, new_height) load_and_preprocess_images hands to Image.resize, with its float arithmetic.
inline VggtResizeTarget vggt_resize_target(index_t width, index_t height, VggtPreprocessMode mode) {
  require(width >= 1 && height >= 1, "VGGT preprocessing: image of size ", width, "x", height, " is empty");
  const auto rounded = [](index_t side, index_t target, index_t other) {
    const double scaled = static_cast<double>(side) * (static_cast<double>(target) / static_cast<double>(other));
    return static_cast<index_t>(python_round(scaled / static_cast<double>(vggt_patch_size))) * vggt_patch_size;
  };
  VggtResizeTarget t;
  if (mode == VggtPreprocessMode::pad && width < height) {
    t.height = vggt_target_size;
    t.width = rounded(width, vggt_target_size, height);
  } else {
    t.width = vggt_target_size;
    t.height = rounded(height, vggt_target_size, width);
  }
  require(t.width >= 1 && t.height >= 1, "VGGT preprocessing: a ", width, "x", height, " image resizes to ",
          t.width, "x", t.height, " (", vggt_preprocess_mode_name(mode),
          " mode); Pillow rejects it: height and width must be > 0");
  return t;
}

// Pillow ImagingAlphaComposite of `src` over an opaque white destination, then convert("RGB") (drop alpha).
inline void pillow_composite_on_white(const std::uint8_t rgba[4], std::uint8_t rgb_out[3]) {
  constexpr std::uint32_t dst_c = 255, dst_a = 255, precision_bits = 7;
  const std::uint32_t sa = rgba[3];
  if (sa == 0) {
    rgb_out[0] = rgb_out[1] = rgb_out[2] = static_cast<std::uint8_t>(dst_c);
    return;
  }
  const std::uint32_t blend = dst_a * (255 - sa);
  const std::uint32_t outa255 = sa * 255 + blend;
  const std::uint32_t coef1 = sa * 255 * 255 * (1u << precision_bits) / outa255;
  const std::uint32_t coef2 = 255 * (1u << precision_bits) - coef1;
  for (int c = 0; c < 3; ++c) {
    const std::uint32_t tmp = rgba[c] * coef1 + dst_c * coef2 + (0x80u << precision_bits);
    rgb_out[c] = static_cast<std::uint8_t>(((((tmp >> 8) + tmp) >> 8)) >> precision_bits);
  }
}

// Step 1: the image as Pillow holds it after the compositing / convert("RGB") lines (interleaved RGB).
inline void vggt_convert_to_rgb(const InterleavedImageView& image, std::vector<std::uint8_t>& rgb) {
  require(image.channels >= 1 && image.channels <= 4, "VGGT preprocessing: image with ", image.channels,
          " channels (expected 1 L, 2 LA, 3 RGB or 4 RGBA)");
  require(image.width >= 1 && image.height >= 1, "VGGT preprocessing: empty image ", image.width, "x",
          image.height);
  require(image.pixels != nullptr, "VGGT preprocessing: null pixel buffer");
  const std::size_t n = static_cast<std::size_t>(image.width) * static_cast<std::size_t>(image.height);
  rgb.resize(n * 3);
  const std::uint8_t* in = image.pixels;
  std::uint8_t* out = rgb.data();
  switch (image.channels) {
    case 1:  // "L" -> "RGB"
    case 2:  // "LA" -> "RGB": Pillow's la2rgb keeps the grey level and drops alpha (only "RGBA" is composited)
      for (std::size_t p = 0; p < n; ++p) out[3 * p] = out[3 * p + 1] = out[3 * p + 2] = in[p * image.channels];
      break;
    case 3: std::copy(in, in + n * 3, out); break;
    case 4:
      for (std::size_t p = 0; p < n; ++p) pillow_composite_on_white(in + 4 * p, out + 3 * p);
      break;
  }
}

namespace detail {

// Writes one resized RGB image into dst [3, out_h, out_w] (already filled with the pad value) at (top, left),
// taking source rows [row0, row0 + rows) of the resized image.
inline void vggt_place_image(const std::uint8_t* rgb, index_t width, index_t row0, index_t rows, float* dst,
                             index_t out_h, index_t out_w, index_t top, index_t left) {
  for (int c = 0; c < 3; ++c)
    for (index_t y = 0; y < rows; ++y) {
      const std::uint8_t* src_row = rgb + (static_cast<std::size_t>(row0 + y) * width) * 3 + c;
      float* out_row = dst + (static_cast<index_t>(c) * out_h + top + y) * out_w + left;
      for (index_t x = 0; x < width; ++x) out_row[x] = static_cast<float>(src_row[x * 3]) / 255.0f;
    }
}

}  // namespace detail

// load_and_preprocess_images on already-decoded images. Returns [S, 3, H, W] float in [0, 1].
inline Tensor<float, 4> vggt_preprocess_images(std::span<const InterleavedImageView> images,
                                               VggtPreprocessMode mode) {
  require(!images.empty(), "At least 1 image is required");
  struct Processed {
    std::vector<std::uint8_t> rgb;  // resized, interleaved
    index_t width = 0, height = 0;  // of rgb
    index_t row0 = 0, rows = 0;     // rows kept (crop)
    index_t out_h = 0, out_w = 0;   // per-image tensor size (after crop / pad)
  };
  std::vector<Processed> processed(images.size());
  std::vector<std::uint8_t> rgb_full;
  PillowResampleWorkspace ws;
  for (std::size_t i = 0; i < images.size(); ++i) {
    const InterleavedImageView& im = images[i];
    try {
      vggt_convert_to_rgb(im, rgb_full);
      const VggtResizeTarget t = vggt_resize_target(im.width, im.height, mode);
      Processed& p = processed[i];
      p.width = t.width;
      p.height = t.height;
      p.rgb.resize(static_cast<std::size_t>(t.width * t.height * 3));
      resize_pillow_bicubic(rgb_full.data(), static_cast<int>(im.width), static_cast<int>(im.height), 3,
                            p.rgb.data(), static_cast<int>(t.width), static_cast<int>(t.height), ws);
      p.row0 = 0;
      p.rows = t.height;
      if (mode == VggtPreprocessMode::crop && t.height > vggt_target_size) {
        p.row0 = (t.height - vggt_target_size) / 2;
        p.rows = vggt_target_size;
      }
      p.out_h = p.rows;
      p.out_w = p.width;
      if (mode == VggtPreprocessMode::pad) {
        p.out_h = std::max(p.out_h, vggt_target_size);
        p.out_w = std::max(p.out_w, vggt_target_size);
      }
    } catch (const Error& e) {
      fail("image ", i, " of ", images.size(), ": ", e.what());
    }
  }
  index_t max_h = 0, max_w = 0;
  for (const auto& p : processed) {
    max_h = std::max(max_h, p.out_h);
    max_w = std::max(max_w, p.out_w);
  }
  Tensor<float, 4> out(Shape<4>{static_cast<index_t>(images.size()), 3, max_h, max_w}, vggt_pad_value);
  for (std::size_t i = 0; i < processed.size(); ++i) {
    const Processed& p = processed[i];
    // Per-image pad (pad mode) then batch pad: both centre with the smaller half before, so offsets add up.
    const index_t pad_top = (p.out_h - p.rows) / 2, pad_left = (p.out_w - p.width) / 2;
    const index_t batch_top = (max_h - p.out_h) / 2, batch_left = (max_w - p.out_w) / 2;
    float* dst = out.data() + static_cast<index_t>(i) * 3 * max_h * max_w;
    detail::vggt_place_image(p.rgb.data(), p.width, p.row0, p.rows, dst, max_h, max_w, batch_top + pad_top,
                             batch_left + pad_left);
  }
  return out;
}

inline Tensor<float, 4> vggt_preprocess_images(const std::vector<InterleavedImage>& images, VggtPreprocessMode mode) {
  std::vector<InterleavedImageView> views;
  views.reserve(images.size());
  for (const auto& im : images) views.push_back(im.view());
  return vggt_preprocess_images(std::span<const InterleavedImageView>(views), mode);
}

// ---------------------------------------------------------------------------------------------------------------
// Decoding with Pillow 9.4's mode semantics
// ---------------------------------------------------------------------------------------------------------------

// Mode Pillow's PNG plugin gives a PNG, from IHDR bit depth and colour type.
struct PngHeader {
  std::uint32_t width = 0, height = 0;
  int bit_depth = 0, color_type = 0;
};

inline bool parse_png_header(std::span<const std::uint8_t> bytes, PngHeader& h) {
  static constexpr std::uint8_t signature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (bytes.size() < 33 || std::memcmp(bytes.data(), signature, 8) != 0) return false;
  if (std::memcmp(bytes.data() + 12, "IHDR", 4) != 0) return false;
  const auto be32 = [&](std::size_t o) {
    return (std::uint32_t(bytes[o]) << 24) | (std::uint32_t(bytes[o + 1]) << 16) | (std::uint32_t(bytes[o + 2]) << 8) |
           std::uint32_t(bytes[o + 3]);
  };
  h.width = be32(16);
  h.height = be32(20);
  h.bit_depth = bytes[24];
  h.color_type = bytes[25];
  return true;
}

// Channels of the interleaved buffer that stands for the Pillow image of a PNG: 16-bit grey is mode "I" (handled
// separately), grey+alpha is "LA" at 8 bits but "RGBA" at 16 bits, palette and tRNS transparency are dropped by
// convert("RGB") so they decode as RGB.
inline int pillow_png_channels(const PngHeader& h) {
  switch (h.color_type) {
    case 0: return 1;
    case 2: return 3;
    case 3: return 3;
    case 4: return h.bit_depth == 16 ? 4 : 2;
    case 6: return 4;
  }
  return 0;
}

inline InterleavedImage decode_image_bytes_like_pillow(std::span<const std::uint8_t> bytes, const std::string& name) {
  require(!bytes.empty(), "image '", name, "': file is empty");
  require(bytes.size() <= static_cast<std::size_t>(INT32_MAX), "image '", name, "': file too large for stb_image");
  const int len = static_cast<int>(bytes.size());
  int w = 0, h = 0, comp = 0;
  if (!stbi_info_from_memory(bytes.data(), len, &w, &h, &comp))
    fail("image '", name, "': cannot decode (", stbi_failure_reason(), ")");
  PngHeader png;
  int channels = comp;
  const bool is_png = parse_png_header(bytes, png);
  if (is_png) {
    channels = pillow_png_channels(png);
    require(channels != 0, "image '", name, "': PNG colour type ", png.color_type, " is not valid");
  }
  InterleavedImage out;
  if (is_png && png.color_type == 0 && png.bit_depth == 16) {
    // Pillow opens 16-bit grey as mode "I"; convert("RGB") clips each value to [0, 255].
    std::unique_ptr<stbi_us, void (*)(void*)> data(stbi_load_16_from_memory(bytes.data(), len, &w, &h, &comp, 1),
                                                   stbi_image_free);
    if (!data) fail("image '", name, "': cannot decode (", stbi_failure_reason(), ")");
    out.width = w;
    out.height = h;
    out.channels = 1;
    out.pixels.resize(static_cast<std::size_t>(w) * static_cast<std::size_t>(h));
    for (std::size_t i = 0; i < out.pixels.size(); ++i)
      out.pixels[i] = static_cast<std::uint8_t>(std::min<stbi_us>(data.get()[i], 255));
    return out;
  }
  require(channels >= 1 && channels <= 4, "image '", name, "': unsupported channel count ", channels);
  std::unique_ptr<stbi_uc, void (*)(void*)> data(stbi_load_from_memory(bytes.data(), len, &w, &h, &comp, channels),
                                                 stbi_image_free);
  if (!data) fail("image '", name, "': cannot decode (", stbi_failure_reason(), ")");
  out.width = w;
  out.height = h;
  out.channels = channels;
  const std::size_t n = static_cast<std::size_t>(w) * static_cast<std::size_t>(h) * static_cast<std::size_t>(channels);
  out.pixels.assign(data.get(), data.get() + n);
  return out;
}

inline InterleavedImage decode_image_like_pillow(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  require(static_cast<bool>(in), "image '", path, "': cannot open");
  const std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return decode_image_bytes_like_pillow(bytes, path);
}

// load_and_preprocess_images(image_path_list, mode) on files.
inline Tensor<float, 4> vggt_load_and_preprocess_images(const std::vector<std::string>& paths,
                                                        VggtPreprocessMode mode) {
  require(!paths.empty(), "At least 1 image is required");
  std::vector<InterleavedImage> images;
  images.reserve(paths.size());
  for (const auto& p : paths) images.push_back(decode_image_like_pillow(p));
  return vggt_preprocess_images(images, mode);
}

}  // namespace v0
}  // namespace flexsplat
