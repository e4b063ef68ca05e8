#pragma once
// PNG reading and writing through stb (implementation in Debian's libstb.so), JPEG reading through libjpeg-turbo.
// Images are HWC tensors: uint8 or uint16 as stored, or float in [0, 1]. Straight (non-premultiplied) alpha.
#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <csetjmp>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <type_traits>
#include <vector>

#include <unistd.h>

// jpeglib.h needs FILE and size_t declared first.
#include <jpeglib.h>
#include <stb/stb_image.h>
#include <stb/stb_image_write.h>

// Exported by Debian's libstb.so; stb_image_write.h declares it only in its implementation section.
extern "C" unsigned char* stbi_zlib_compress(unsigned char* data, int data_len, int* out_len, int quality);

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace image {

struct ImageInfo {
  int width = 0, height = 0;
  int channels = 0;   // as stored: 1 grey, 2 grey+alpha, 3 RGB, 4 RGBA
  int bit_depth = 8;  // 16 only for 16-bit PNG
};

// Images with more pixels than this are refused before decoding: a 100-byte file can declare 16384 x 16384.
inline constexpr std::int64_t max_image_pixels = std::int64_t(1) << 26;

namespace detail {

template <class... Parts>
[[noreturn]] void image_error(const std::filesystem::path& path, Parts&&... parts) {
  fail("image file '", path.string(), "': ", std::forward<Parts>(parts)...);
}

inline std::vector<unsigned char> read_file_bytes(const std::filesystem::path& path) {
  std::error_code ec;
  const auto status = std::filesystem::status(path, ec);
  if (ec || !std::filesystem::exists(status)) image_error(path, "cannot open: no such file");
  if (!std::filesystem::is_regular_file(status)) image_error(path, "cannot open: not a regular file");
  std::ifstream in(path, std::ios::binary);
  if (!in) image_error(path, "cannot open: ", std::strerror(errno));
  std::vector<unsigned char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) image_error(path, "read error");
  if (bytes.empty()) image_error(path, "file is empty");
  if (bytes.size() > static_cast<std::size_t>(std::numeric_limits<int>::max()))
    image_error(path, "file of ", bytes.size(), " bytes is too large to decode");
  return bytes;
}

// JPEG through libjpeg-turbo (Pillow's decoder, so JPEG input matches the VGGT preprocessing): stb 2.27's JPEG
// decoder asserts, shifts out of range and writes past its Huffman tables on corrupt files (docs/reliability.md).
// Progressive files may chain scans without end; no encoder writes more than a few dozen.
inline constexpr int max_jpeg_scans = 100;

// Everything libjpeg touches, in one block the caller owns: longjmp then skips only libjpeg's C frames.
struct JpegReader {
  jpeg_decompress_struct cinfo{};
  jpeg_error_mgr err{};
  jpeg_progress_mgr progress{};
  std::jmp_buf jump{};
  char message[JMSG_LENGTH_MAX + 64] = {};
};

inline JpegReader& jpeg_reader(j_common_ptr c) { return *reinterpret_cast<JpegReader*>(c->client_data); }

inline void jpeg_fail(j_common_ptr c) {
  c->err->format_message(c, jpeg_reader(c).message);
  std::longjmp(jpeg_reader(c).jump, 1);
}

// Level -1 is corrupt data, which libjpeg would decode on as grey blocks; trace messages (level >= 0) are dropped.
inline void jpeg_message(j_common_ptr c, int level) {
  if (level < 0) jpeg_fail(c);
}

inline void jpeg_scan_limit(j_common_ptr c) {
  auto& r = jpeg_reader(c);
  if (r.cinfo.input_scan_number <= max_jpeg_scans) return;
  std::snprintf(r.message, sizeof r.message, "more than %d progressive scans", max_jpeg_scans);
  std::longjmp(r.jump, 1);
}

// Reads the header (and, with `pixels`, the image as grey or RGB rows) of a JPEG; false with r.message on an error.
// No C++ object with a destructor lives in this frame, so longjmp back to it is well defined.
inline bool jpeg_run(JpegReader& r, const unsigned char* p, std::size_t n, std::vector<unsigned char>* pixels) {
  r.cinfo.err = jpeg_std_error(&r.err);
  r.err.error_exit = jpeg_fail;
  r.err.emit_message = jpeg_message;
  r.progress.progress_monitor = jpeg_scan_limit;
  r.cinfo.client_data = &r;  // kept by jpeg_create_decompress, which may already fail
  if (setjmp(r.jump)) {
    jpeg_destroy_decompress(&r.cinfo);
    return false;
  }
  jpeg_create_decompress(&r.cinfo);
  r.cinfo.progress = &r.progress;
  jpeg_mem_src(&r.cinfo, p, static_cast<unsigned long>(n));
  jpeg_read_header(&r.cinfo, TRUE);
  const auto space = r.cinfo.jpeg_color_space;
  if (space != JCS_GRAYSCALE && space != JCS_YCbCr && space != JCS_RGB) {
    std::snprintf(r.message, sizeof r.message, "%d-component CMYK/YCCK JPEG is not supported (save it as RGB)",
                  r.cinfo.num_components);
    jpeg_destroy_decompress(&r.cinfo);
    return false;
  }
  if (pixels) {
    r.cinfo.out_color_space = space == JCS_GRAYSCALE ? JCS_GRAYSCALE : JCS_RGB;
    jpeg_start_decompress(&r.cinfo);
    const std::size_t row = std::size_t(r.cinfo.output_width) * std::size_t(r.cinfo.output_components);
    pixels->resize(row * r.cinfo.output_height);
    while (r.cinfo.output_scanline < r.cinfo.output_height) {
      JSAMPROW out = pixels->data() + row * r.cinfo.output_scanline;
      jpeg_read_scanlines(&r.cinfo, &out, 1);
    }
    jpeg_finish_decompress(&r.cinfo);
  }
  jpeg_destroy_decompress(&r.cinfo);
  return true;
}

struct JpegHeader {
  int width = 0, height = 0, channels = 0;
};

inline JpegHeader jpeg_header(const std::filesystem::path& path, const unsigned char* p, std::size_t n) {
  JpegReader r;
  if (!jpeg_run(r, p, n, nullptr)) image_error(path, "cannot decode JPEG (", r.message, ")");
  return {static_cast<int>(r.cinfo.image_width), static_cast<int>(r.cinfo.image_height),
          r.cinfo.jpeg_color_space == JCS_GRAYSCALE ? 1 : 3};
}

// stb's conversions, so PNG and JPEG give the same result: grey = (77 r + 150 g + 29 b) >> 8, alpha opaque,
// 16-bit = 257 x 8-bit.
template <class S>
Tensor<S, 3> convert_channels(const std::vector<unsigned char>& in, int h, int w, int stored, int channels) {
  const int c = channels ? channels : stored;
  Tensor<S, 3> out(Shape<3>{h, w, c});
  const S scale = std::is_same_v<S, std::uint8_t> ? S(1) : S(257);
  const S opaque = std::numeric_limits<S>::max();
  const std::size_t count = std::size_t(h) * std::size_t(w);
  for (std::size_t i = 0; i < count; ++i) {
    const unsigned char* q = in.data() + i * stored;
    const unsigned r = q[0], g = stored == 3 ? q[1] : q[0], b = stored == 3 ? q[2] : q[0];
    const unsigned grey = stored == 3 ? (r * 77 + g * 150 + b * 29) >> 8 : r;
    S* o = out.data() + i * c;
    if (c <= 2) {
      o[0] = static_cast<S>(grey * scale);
      if (c == 2) o[1] = opaque;
    } else {
      o[0] = static_cast<S>(r * scale);
      o[1] = static_cast<S>(g * scale);
      o[2] = static_cast<S>(b * scale);
      if (c == 4) o[3] = opaque;
    }
  }
  return out;
}

inline bool is_jpeg(const std::vector<unsigned char>& bytes) {
  return bytes.size() >= 3 && bytes[0] == 0xFF && bytes[1] == 0xD8 && bytes[2] == 0xFF;
}

// Refused before decoding: anything but PNG and JPEG (stb would also decode GIF, PSD, BMP, TGA, HDR, PIC and PNM),
// PNG chunks longer than the rest of the file (stb grows its IDAT buffer to a chunk's declared length before
// reading it), and declared sizes beyond max_image_pixels.
inline void check_declared_size(const std::filesystem::path& path, const std::vector<unsigned char>& bytes) {
  const unsigned char* p = bytes.data();
  const std::size_t n = bytes.size();
  static const unsigned char png_magic[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  const bool jpeg = is_jpeg(bytes);
  if (n >= 8 && std::memcmp(p, png_magic, 8) == 0) {
    bool image_data = false;
    for (std::size_t pos = 8; pos + 8 <= n;) {
      const std::uint64_t len = (std::uint64_t(p[pos]) << 24) | (std::uint64_t(p[pos + 1]) << 16) |
                                (std::uint64_t(p[pos + 2]) << 8) | std::uint64_t(p[pos + 3]);
      if (len + 12 > n - pos)
        image_error(path, "PNG chunk at byte ", pos, " declares ", len, " bytes, past the end of the file (", n,
                    " bytes)");
      if (std::memcmp(p + pos + 4, "IEND", 4) == 0) break;
      // stb would memcpy into its still-null IDAT buffer (undefined behaviour even for 0 bytes).
      if (std::memcmp(p + pos + 4, "IDAT", 4) == 0) {
        if (len == 0 && !image_data) image_error(path, "PNG starts its image data with an empty IDAT chunk");
        image_data = true;
      }
      pos += 12 + len;
    }
  } else if (!jpeg) {
    image_error(path, "cannot decode: not a readable PNG/JPEG image (no PNG signature or JPEG SOI marker)");
  }
  int w = 0, h = 0, c = 0;
  if (jpeg) {
    const JpegHeader header = jpeg_header(path, p, n);
    w = header.width;
    h = header.height;
  } else if (!stbi_info_from_memory(p, static_cast<int>(n), &w, &h, &c)) {
    return;  // stb names the problem when decoding
  }
  const std::int64_t pixels = static_cast<std::int64_t>(w) * h;
  if (pixels > max_image_pixels)
    image_error(path, "declares ", w, " x ", h, " pixels, more than the limit of ", max_image_pixels);
  // Every 8x8 block of a JPEG costs at least one bit (its DC code): a file with under 1 byte per 1024 pixels is
  // mostly missing, and a decoder would spend seconds decoding the missing blocks from padding.
  if (jpeg && pixels > 1024 * static_cast<std::int64_t>(n))
    image_error(path, "JPEG declares ", w, " x ", h, " pixels but holds only ", n, " bytes (truncated?)");
}

inline ImageInfo probe_bytes(const std::filesystem::path& path, const std::vector<unsigned char>& bytes) {
  check_declared_size(path, bytes);
  ImageInfo info;
  if (is_jpeg(bytes)) {
    const JpegHeader header = jpeg_header(path, bytes.data(), bytes.size());
    return {header.width, header.height, header.channels, 8};
  }
  const int len = static_cast<int>(bytes.size());
  if (!stbi_info_from_memory(bytes.data(), len, &info.width, &info.height, &info.channels))
    image_error(path, "not a readable PNG/JPEG image (", stbi_failure_reason(), ")");
  info.bit_depth = stbi_is_16_bit_from_memory(bytes.data(), len) ? 16 : 8;
  return info;
}

inline void check_channels(const std::filesystem::path& path, int channels) {
  if (channels < 0 || channels > 4) image_error(path, "requested ", channels, " channels; use 0 (as stored) to 4");
}

// Decodes at the stored bit depth S (uint8 or uint16) with `channels` (0 = as stored) into an HWC tensor.
template <class S>
Tensor<S, 3> decode(const std::filesystem::path& path, const std::vector<unsigned char>& bytes, int channels) {
  check_channels(path, channels);
  check_declared_size(path, bytes);
  if (is_jpeg(bytes)) {
    JpegReader r;
    std::vector<unsigned char> rows;
    if (!jpeg_run(r, bytes.data(), bytes.size(), &rows)) image_error(path, "cannot decode JPEG (", r.message, ")");
    return convert_channels<S>(rows, static_cast<int>(r.cinfo.output_height), static_cast<int>(r.cinfo.output_width),
                               r.cinfo.output_components, channels);
  }
  int w = 0, h = 0, stored = 0;
  S* pixels = nullptr;
  if constexpr (std::is_same_v<S, std::uint8_t>)
    pixels = stbi_load_from_memory(bytes.data(), static_cast<int>(bytes.size()), &w, &h, &stored, channels);
  else
    pixels = stbi_load_16_from_memory(bytes.data(), static_cast<int>(bytes.size()), &w, &h, &stored, channels);
  if (!pixels) image_error(path, "cannot decode (", stbi_failure_reason(), ")");
  const int c = channels ? channels : stored;
  Tensor<S, 3> out(Shape<3>{h, w, c});
  std::copy(pixels, pixels + out.size(), out.data());
  stbi_image_free(pixels);
  return out;
}

// CRC-32 (ISO-HDLC, as PNG chunks use).
inline std::uint32_t crc32(const unsigned char* data, std::size_t n, std::uint32_t crc = 0) {
  static const auto table = [] {
    std::array<std::uint32_t, 256> t{};
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? 0xedb88320u ^ (c >> 1) : c >> 1;
      t[i] = c;
    }
    return t;
  }();
  crc = ~crc;
  for (std::size_t i = 0; i < n; ++i) crc = table[(crc ^ data[i]) & 0xff] ^ (crc >> 8);
  return ~crc;
}

}  // namespace detail

// Size, stored channels and bit depth without decoding the pixels.
inline ImageInfo probe(const std::filesystem::path& path) {
  return detail::probe_bytes(path, detail::read_file_bytes(path));
}

// 8-bit HWC (16-bit files are reduced to their high byte). channels 0 keeps the stored count; stb expands or drops
// channels otherwise (grey -> RGB replicates, a missing alpha becomes 255).
inline Tensor<std::uint8_t, 3> read_u8(const std::filesystem::path& path, int channels = 0) {
  return detail::decode<std::uint8_t>(path, detail::read_file_bytes(path), channels);
}

// 16-bit HWC: 16-bit PNG values as stored (e.g. depth maps); 8-bit files are scaled by 257 (255 -> 65535).
inline Tensor<std::uint16_t, 3> read_u16(const std::filesystem::path& path, int channels = 0) {
  return detail::decode<std::uint16_t>(path, detail::read_file_bytes(path), channels);
}

// Float HWC in [0, 1] at the file's own precision: 8-bit values / 255, 16-bit values / 65535.
template <class T = float>
Tensor<T, 3> read_float(const std::filesystem::path& path, int channels = 0) {
  static_assert(std::is_floating_point_v<T>, "read_float needs a floating type");
  const auto bytes = detail::read_file_bytes(path);
  const ImageInfo info = detail::probe_bytes(path, bytes);
  Tensor<T, 3> out;
  auto convert = [&](const auto& stored, T scale) {
    out = Tensor<T, 3>(stored.shape());
    const auto* src = stored.data();
    T* dst = out.data();
    for (index_t i = 0; i < out.size(); ++i) dst[i] = static_cast<T>(src[i]) / scale;
  };
  if (info.bit_depth == 16) convert(detail::decode<std::uint16_t>(path, bytes, channels), T(65535));
  else convert(detail::decode<std::uint8_t>(path, bytes, channels), T(255));
  return out;
}

// out = rgb * alpha + background * (1 - alpha) for an HWC RGBA (or grey+alpha, expanded) float image.
template <class T>
void composite_over(TensorView<const T, 3> rgba, const std::array<T, 3>& background, TensorView<T, 3> rgb) {
  require(rgba.shape(2) == 4, "composite_over needs 4 channels (RGBA), got shape ", shape_string(rgba.shape()));
  require(rgb.shape() == Shape<3>{rgba.shape(0), rgba.shape(1), 3}, "composite_over output has shape ",
          shape_string(rgb.shape()), ", expected [", rgba.shape(0), ", ", rgba.shape(1), ", 3]");
  for (index_t y = 0; y < rgba.shape(0); ++y)
    for (index_t x = 0; x < rgba.shape(1); ++x) {
      const T a = rgba(y, x, 3);
      for (index_t c = 0; c < 3; ++c) rgb(y, x, c) = rgba(y, x, c) * a + background[c] * (T(1) - a);
    }
}

// Reads any PNG/JPEG as float RGB in [0, 1]: alpha (if stored) is composited over background, grey is replicated.
template <class T = float>
Tensor<T, 3> read_rgb(const std::filesystem::path& path, const std::array<T, 3>& background = {T(1), T(1), T(1)}) {
  Tensor<T, 3> rgba = read_float<T>(path, 4);
  Tensor<T, 3> rgb(Shape<3>{rgba.shape(0), rgba.shape(1), 3});
  composite_over<T>(rgba.view(), background, rgb.view());
  return rgb;
}

// Depth map stored as 16-bit PNG: value * scale, 0 stays 0 (no surface). Returns HW.
template <class T = float>
Tensor<T, 2> read_depth_png(const std::filesystem::path& path, T scale) {
  const auto bytes = detail::read_file_bytes(path);
  const ImageInfo info = detail::probe_bytes(path, bytes);
  if (info.bit_depth != 16 || info.channels != 1)
    detail::image_error(path, "a depth map must be a 16-bit single-channel PNG, found ", info.bit_depth, "-bit with ",
                        info.channels, " channels");
  const auto raw = detail::decode<std::uint16_t>(path, bytes, 1);
  Tensor<T, 2> depth(Shape<2>{raw.shape(0), raw.shape(1)});
  for (index_t i = 0; i < depth.size(); ++i) depth.data()[i] = static_cast<T>(raw.data()[i]) * scale;
  return depth;
}

// 8-bit PNG from an HWC view with 1 to 4 channels, written atomically (temp file + rename).
inline void write_png(const std::filesystem::path& path, TensorView<const std::uint8_t, 3> image) {
  const index_t h = image.shape(0), w = image.shape(1), c = image.shape(2);
  require(c >= 1 && c <= 4, "write_png '", path.string(), "': ", c, " channels, expected 1 to 4");
  require(h >= 1 && w >= 1 && h <= (1 << 24) && w <= (1 << 24), "write_png '", path.string(), "': bad size ",
          shape_string(image.shape()));
  const auto contiguous = copy_of(image);
  std::vector<unsigned char> encoded;
  auto sink = [](void* context, void* data, int size) {
    auto* out = static_cast<std::vector<unsigned char>*>(context);
    out->insert(out->end(), static_cast<unsigned char*>(data), static_cast<unsigned char*>(data) + size);
  };
  if (!stbi_write_png_to_func(sink, &encoded, static_cast<int>(w), static_cast<int>(h), static_cast<int>(c),
                              contiguous.data(), static_cast<int>(w * c)))
    fail("write_png '", path.string(), "': encoding failed");
  write_file_atomic(path, "write_png", std::string_view(reinterpret_cast<const char*>(encoded.data()), encoded.size()));
}

// Float HWC in [0, 1]: clamped and rounded to the nearest 8-bit value; NaN is an error.
template <class T>
void write_png(const std::filesystem::path& path, TensorView<const T, 3> image) {
  static_assert(std::is_floating_point_v<T>, "write_png takes uint8 or floating images");
  Tensor<std::uint8_t, 3> bytes(image.shape());
  index_t n = 0;
  for (index_t y = 0; y < image.shape(0); ++y)
    for (index_t x = 0; x < image.shape(1); ++x)
      for (index_t c = 0; c < image.shape(2); ++c, ++n) {
        const T v = image(y, x, c);
        require(!std::isnan(v), "write_png '", path.string(), "': NaN at pixel (", x, ", ", y, ") channel ", c);
        bytes.data()[n] = static_cast<std::uint8_t>(std::lround(std::clamp(v, T(0), T(1)) * T(255)));
      }
  write_png(path, TensorView<const std::uint8_t, 3>(bytes.view()));
}

template <class T>
void write_png(const std::filesystem::path& path, const Tensor<T, 3>& image) {
  write_png(path, TensorView<const T, 3>(image.view()));
}

// 16-bit PNG (e.g. depth maps) from an HWC view with 1 to 4 channels, written atomically. stb writes only 8-bit
// PNGs, so the chunks are assembled here around stb's zlib compressor (rows unfiltered).
inline void write_png_u16(const std::filesystem::path& path, TensorView<const std::uint16_t, 3> image) {
  const index_t h = image.shape(0), w = image.shape(1), c = image.shape(2);
  require(c >= 1 && c <= 4, "write_png_u16 '", path.string(), "': ", c, " channels, expected 1 to 4");
  require(h >= 1 && w >= 1 && h * w * c * 2 + h < std::numeric_limits<int>::max(), "write_png_u16 '", path.string(),
          "': bad size ", shape_string(image.shape()));
  std::vector<unsigned char> raw;
  raw.reserve(static_cast<std::size_t>(h * (w * c * 2 + 1)));
  for (index_t y = 0; y < h; ++y) {
    raw.push_back(0);  // filter type None
    for (index_t x = 0; x < w; ++x)
      for (index_t k = 0; k < c; ++k) {
        const std::uint16_t v = image(y, x, k);
        raw.push_back(static_cast<unsigned char>(v >> 8));  // PNG samples are big-endian
        raw.push_back(static_cast<unsigned char>(v & 0xff));
      }
  }
  int zlen = 0;
  unsigned char* z = stbi_zlib_compress(raw.data(), static_cast<int>(raw.size()), &zlen, 8);
  if (!z) fail("write_png_u16 '", path.string(), "': compression failed");
  std::vector<unsigned char> png = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  auto put32 = [](std::vector<unsigned char>& out, std::uint32_t v) {
    for (int shift = 24; shift >= 0; shift -= 8) out.push_back(static_cast<unsigned char>(v >> shift));
  };
  auto chunk = [&](const char* type, const unsigned char* data, std::size_t n) {
    put32(png, static_cast<std::uint32_t>(n));
    const std::size_t start = png.size();
    png.insert(png.end(), type, type + 4);
    png.insert(png.end(), data, data + n);
    put32(png, detail::crc32(png.data() + start, n + 4));
  };
  constexpr unsigned char color_type[] = {0, 0, 4, 2, 6};  // grey, grey+alpha, RGB, RGBA
  std::vector<unsigned char> ihdr;
  put32(ihdr, static_cast<std::uint32_t>(w));
  put32(ihdr, static_cast<std::uint32_t>(h));
  ihdr.insert(ihdr.end(), {16, color_type[c], 0, 0, 0});
  chunk("IHDR", ihdr.data(), ihdr.size());
  chunk("IDAT", z, static_cast<std::size_t>(zlen));
  std::free(z);
  chunk("IEND", nullptr, 0);
  write_file_atomic(path, "write_png16", std::string_view(reinterpret_cast<const char*>(png.data()), png.size()));
}

}  // namespace image
}  // namespace v0
}  // namespace flexsplat
