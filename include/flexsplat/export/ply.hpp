#pragma once
// INRIA 3DGS PLY (x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*): logit opacity, log scale, w-first
// quaternions, f_rest channel-major. Reads binary little-endian and ASCII; writes binary little-endian.
#include <algorithm>
#include <bit>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <string_view>
#include <vector>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/export/gaussian_set.hpp"
#include "flexsplat/nn/activations.hpp"

namespace flexsplat {
inline namespace v0 {
namespace ply {

// log(0) and logit(0 or 1) are infinite: stored values are clamped to this magnitude (exp(-40) ~ 4e-18).
inline constexpr double kMaxLogMagnitude = 40.0;

struct WriteReport {
  gaussians::ExportRepairs repairs;
  std::size_t bytes = 0;
};


inline std::vector<std::string> property_names(int sh_degree) {
  std::vector<std::string> names = {"x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"};
  const int rest = 3 * (sh_coefficients(sh_degree) - 1);
  for (int i = 0; i < rest; ++i) names.push_back("f_rest_" + std::to_string(i));
  for (const char* s : {"opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"})
    names.push_back(s);
  return names;
}

template <class T>
std::vector<unsigned char> encode_ply(const GaussianSet<T>& input, WriteReport* report = nullptr) {
  static_assert(std::endian::native == std::endian::little, "PLY writer assumes a little-endian host");
  GaussianSet<double> set = convert_gaussian_set<double>(input);
  const gaussians::ExportRepairs repairs = gaussians::repair_for_export(set, "ply export");
  const int degree = set.sh_degree();
  const int rest = sh_coefficients(degree) - 1;
  const std::vector<std::string> names = property_names(degree);
  std::string header = "ply\nformat binary_little_endian 1.0\ncomment written by flexsplat\nelement vertex " +
                       std::to_string(set.size()) + "\n";
  for (const std::string& name : names) header += "property float " + name + "\n";
  header += "end_header\n";
  std::vector<unsigned char> out(header.begin(), header.end());
  const std::size_t row = names.size();
  std::vector<float> values(row);
  out.reserve(out.size() + static_cast<std::size_t>(set.size()) * row * 4);
  for (index_t i = 0; i < set.size(); ++i) {
    std::size_t k = 0;
    for (int c = 0; c < 3; ++c) values[k++] = static_cast<float>(set.means(i, c));
    for (int c = 0; c < 3; ++c) values[k++] = 0.0f;
    for (int c = 0; c < 3; ++c) values[k++] = static_cast<float>(set.sh(i, 0, c));
    for (int c = 0; c < 3; ++c)
      for (int j = 1; j <= rest; ++j) values[k++] = static_cast<float>(set.sh(i, j, c));
    values[k++] = static_cast<float>(nn::logit(static_cast<double>(set.opacities(i)), kMaxLogMagnitude));
    for (int c = 0; c < 3; ++c)
      values[k++] = static_cast<float>(std::max(std::log(set.scales(i, c)), -kMaxLogMagnitude));
    for (int c = 0; c < 4; ++c) values[k++] = static_cast<float>(set.quats(i, c));
    const auto* bytes = reinterpret_cast<const unsigned char*>(values.data());
    out.insert(out.end(), bytes, bytes + row * 4);
  }
  if (report) {
    report->repairs = repairs;
    report->bytes = out.size();
  }
  return out;
}

template <class T>
WriteReport write_ply(const GaussianSet<T>& set, const std::filesystem::path& path) {
  WriteReport report;
  const std::vector<unsigned char> bytes = encode_ply(set, &report);
  write_file_atomic(path, "ply writer", std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
  return report;
}

namespace detail {

enum class Scalar { I8, U8, I16, U16, I32, U32, F32, F64 };

inline bool parse_scalar(const std::string& name, Scalar& out) {
  static const std::pair<const char*, Scalar> table[] = {
      {"char", Scalar::I8},    {"int8", Scalar::I8},     {"uchar", Scalar::U8},   {"uint8", Scalar::U8},
      {"short", Scalar::I16},  {"int16", Scalar::I16},   {"ushort", Scalar::U16}, {"uint16", Scalar::U16},
      {"int", Scalar::I32},    {"int32", Scalar::I32},   {"uint", Scalar::U32},   {"uint32", Scalar::U32},
      {"float", Scalar::F32},  {"float32", Scalar::F32}, {"double", Scalar::F64}, {"float64", Scalar::F64}};
  for (auto& [n, s] : table)
    if (name == n) { out = s; return true; }
  return false;
}

inline std::size_t scalar_size(Scalar s) {
  switch (s) {
    case Scalar::I8: case Scalar::U8: return 1;
    case Scalar::I16: case Scalar::U16: return 2;
    case Scalar::I32: case Scalar::U32: case Scalar::F32: return 4;
    case Scalar::F64: return 8;
  }
  return 0;
}

inline double load_le(Scalar s, const unsigned char* p) {
  switch (s) {
    case Scalar::I8: { std::int8_t v; std::memcpy(&v, p, 1); return v; }
    case Scalar::U8: return *p;
    case Scalar::I16: { std::int16_t v; std::memcpy(&v, p, 2); return v; }
    case Scalar::U16: { std::uint16_t v; std::memcpy(&v, p, 2); return v; }
    case Scalar::I32: { std::int32_t v; std::memcpy(&v, p, 4); return v; }
    case Scalar::U32: { std::uint32_t v; std::memcpy(&v, p, 4); return v; }
    case Scalar::F32: { float v; std::memcpy(&v, p, 4); return v; }
    case Scalar::F64: { double v; std::memcpy(&v, p, 8); return v; }
  }
  return 0;
}

struct Property {
  std::string name;
  Scalar type = Scalar::F32;
  std::size_t offset = 0;
};

}  // namespace detail

// Parses a 3DGS PLY. Raw values are validated (NaN, count, size) before conversion; the result is validated as a set.
inline GaussianSet<float> decode_ply(const unsigned char* data, std::size_t size,
                                                const std::string& source) {
  using namespace detail;
  static_assert(std::endian::native == std::endian::little, "PLY reader assumes a little-endian host");
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  require(text.substr(0, 4) == "ply\n" || text.substr(0, 5) == "ply\r\n", source, ": not a PLY file (no 'ply' magic)");
  const std::size_t end_marker = text.find("end_header");
  require(end_marker != std::string_view::npos, source, ": PLY header has no 'end_header' (truncated?)");
  std::size_t body = text.find('\n', end_marker);
  require(body != std::string_view::npos, source, ": PLY header is not terminated by a newline");
  ++body;
  std::istringstream header{std::string(text.substr(0, end_marker))};
  std::string line, format;
  long long vertex_count = -1;
  bool in_vertex = false, seen_element = false;
  std::vector<Property> props;
  std::size_t row = 0;
  while (std::getline(header, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream words(line);
    std::string key;
    words >> key;
    if (key == "format") {
      std::string version;
      words >> format >> version;
      require(format == "binary_little_endian" || format == "ascii", source, ": PLY format '", format,
              "' is not supported (binary_little_endian or ascii)");
    } else if (key == "element") {
      std::string name;
      long long count = -1;
      words >> name >> count;
      require(!words.fail() && count >= 0, source, ": malformed PLY element line '", line, "'");
      require(seen_element || name == "vertex", source, ": PLY element '", name,
              "' precedes 'vertex' (vertex must come first)");
      in_vertex = name == "vertex" && !seen_element;
      seen_element = true;
      if (in_vertex) vertex_count = count;
    } else if (key == "property" && in_vertex) {
      std::string type, name;
      words >> type >> name;
      require(type != "list", source, ": list property in the vertex element is not supported");
      Property p;
      require(parse_scalar(type, p.type), source, ": PLY property '", name, "' has unknown type '", type, "'");
      p.name = name;
      p.offset = row;
      row += scalar_size(p.type);
      for (const Property& q : props) require(q.name != name, source, ": PLY property '", name, "' appears twice");
      props.push_back(p);
    }
  }
  require(!format.empty(), source, ": PLY header has no 'format' line");
  require(vertex_count >= 0, source, ": PLY header has no 'element vertex'");
  auto find = [&](const std::string& name) -> const Property& {
    for (const Property& p : props)
      if (p.name == name) return p;
    fail(source, ": PLY vertex element has no property '", name, "'");
  };
  int rest_count = 0;
  while (std::any_of(props.begin(), props.end(),
                     [&](const Property& p) { return p.name == "f_rest_" + std::to_string(rest_count); }))
    ++rest_count;
  require(rest_count % 3 == 0, source, ": ", rest_count, " f_rest_* properties is not a multiple of 3");
  const int degree = sh_degree_for(1 + rest_count / 3, source);
  const int rest = rest_count / 3;
  const std::vector<std::string> needed = property_names(degree);
  std::vector<const Property*> columns;
  for (const std::string& name : needed) {
    if (name == "nx" || name == "ny" || name == "nz") continue;  // normals are unused and optional
    columns.push_back(&find(name));
  }

  const std::size_t n = static_cast<std::size_t>(vertex_count);
  // The count is checked against the body before allocating for it: an ASCII value takes at least two characters.
  if (format == "binary_little_endian")
    require(row > 0 && n <= (size - body) / row, source, ": PLY declares ", n, " vertices of ", row,
            " bytes but the body holds ", size - body, " bytes (truncated or wrong count)");
  else
    require(n <= (size - body + 1) / (2 * props.size()), source, ": ASCII PLY declares ", n, " vertices of ",
            props.size(), " values but the body holds only ", size - body, " bytes (truncated or wrong count)");
  std::vector<double> raw(n * columns.size());
  if (format == "binary_little_endian") {
    for (std::size_t i = 0; i < n; ++i)
      for (std::size_t c = 0; c < columns.size(); ++c)
        raw[i * columns.size() + c] = load_le(columns[c]->type, data + body + i * row + columns[c]->offset);
  } else {
    std::vector<std::size_t> index_of(columns.size());
    for (std::size_t c = 0; c < columns.size(); ++c)
      index_of[c] = static_cast<std::size_t>(columns[c] - props.data());
    const char* p = reinterpret_cast<const char*>(data) + body;
    const char* end = reinterpret_cast<const char*>(data) + size;
    std::vector<double> values(props.size());
    for (std::size_t i = 0; i < n; ++i) {
      for (std::size_t k = 0; k < props.size(); ++k) {
        while (p < end && std::isspace(static_cast<unsigned char>(*p))) ++p;
        require(p < end, source, ": ASCII PLY ends at vertex ", i, " of ", n, " (truncated or wrong count)");
        double v = 0;
        const auto [next, ec] = std::from_chars(p, end, v);
        if (ec != std::errc()) {
          // from_chars rejects "nan"/"inf" spellings some writers use: name the vertex either way.
          fail(source, ": ASCII PLY has an unreadable value at vertex ", i, ", property '", props[k].name, "'");
        }
        values[k] = v;
        p = next;
      }
      for (std::size_t c = 0; c < columns.size(); ++c) raw[i * columns.size() + c] = values[index_of[c]];
    }
  }
  for (std::size_t i = 0; i < n; ++i)
    for (std::size_t c = 0; c < columns.size(); ++c)
      require(std::isfinite(raw[i * columns.size() + c]), source, ": PLY property '", columns[c]->name,
              "' of vertex ", i, " is not finite (", raw[i * columns.size() + c], ")");

  GaussianSet<float> set = make_gaussian_set<float>(static_cast<index_t>(n), degree);
  const std::size_t width = columns.size();
  for (std::size_t i = 0; i < n; ++i) {
    const double* r = raw.data() + i * width;
    std::size_t k = 0;
    for (int c = 0; c < 3; ++c) set.means(i, c) = static_cast<float>(r[k++]);
    for (int c = 0; c < 3; ++c) set.sh(i, 0, c) = static_cast<float>(r[k++]);
    for (int c = 0; c < 3; ++c)
      for (int j = 1; j <= rest; ++j) set.sh(i, j, c) = static_cast<float>(r[k++]);
    set.opacities(i) = static_cast<float>(nn::sigmoid(r[k++]));
    for (int c = 0; c < 3; ++c) set.scales(i, c) = static_cast<float>(std::exp(r[k++]));
    double norm = 0;
    for (int c = 0; c < 4; ++c) norm += r[k + c] * r[k + c];
    norm = std::sqrt(norm);
    // 3DGS training leaves quaternions unnormalised (the renderer normalises): normalise, but a zero one is an error.
    require(norm > 1e-12, source, ": rotation of vertex ", i, " is a zero quaternion");
    for (int c = 0; c < 4; ++c) set.quats(i, c) = static_cast<float>(r[k++] / norm);
  }
  gaussians::validate(set, source);
  return set;
}

inline GaussianSet<float> read_ply(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  require(in.good(), "cannot open '", path.string(), "'");
  const std::vector<unsigned char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return decode_ply(bytes.data(), bytes.size(), path.string());
}

}  // namespace ply
}  // namespace v0
}  // namespace flexsplat
