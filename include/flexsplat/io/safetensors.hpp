#pragma once
// safetensors: validating mmap reader (zero-copy where dtype and alignment allow) and atomic writer.
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <limits>
#include <memory>
#include <set>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/core/half.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace safetensors {

enum class Dtype { F64, F32, F16, BF16, I64, I32, U8 };

inline std::size_t dtype_size(Dtype d) {
  switch (d) {
    case Dtype::F64: case Dtype::I64: return 8;
    case Dtype::F32: case Dtype::I32: return 4;
    case Dtype::F16: case Dtype::BF16: return 2;
    case Dtype::U8: return 1;
  }
  return 0;
}

inline const char* dtype_name(Dtype d) {
  switch (d) {
    case Dtype::F64: return "F64";
    case Dtype::F32: return "F32";
    case Dtype::F16: return "F16";
    case Dtype::BF16: return "BF16";
    case Dtype::I64: return "I64";
    case Dtype::I32: return "I32";
    case Dtype::U8: return "U8";
  }
  return "?";
}

inline bool parse_dtype(const std::string& name, Dtype& out) {
  static const std::pair<const char*, Dtype> table[] = {{"F64", Dtype::F64}, {"F32", Dtype::F32},
                                                        {"F16", Dtype::F16}, {"BF16", Dtype::BF16},
                                                        {"I64", Dtype::I64}, {"I32", Dtype::I32},
                                                        {"U8", Dtype::U8}};
  for (auto& [n, d] : table)
    if (name == n) { out = d; return true; }
  return false;
}

template <class T>
constexpr Dtype dtype_of() {
  if constexpr (std::is_same_v<T, double>) return Dtype::F64;
  else if constexpr (std::is_same_v<T, float>) return Dtype::F32;
  else if constexpr (std::is_same_v<T, f16>) return Dtype::F16;
  else if constexpr (std::is_same_v<T, bf16>) return Dtype::BF16;
  else if constexpr (std::is_same_v<T, std::int64_t>) return Dtype::I64;
  else if constexpr (std::is_same_v<T, std::int32_t>) return Dtype::I32;
  else if constexpr (std::is_same_v<T, std::uint8_t>) return Dtype::U8;
  else static_assert(sizeof(T) == 0, "no safetensors dtype for this type");
}

struct TensorInfo {
  std::string name;
  Dtype dtype{};
  std::vector<index_t> shape;
  std::size_t begin = 0, end = 0;  // byte offsets into the data section
  index_t numel() const {
    index_t n = 1;
    for (auto e : shape) n *= e;  // validated at parse time: cannot overflow
    return n;
  }
};

inline std::string shape_string(const std::vector<index_t>& shape) {
  std::string s = "[";
  for (std::size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + "]";
}

// Header JSON larger than this is refused before allocating for it.
inline constexpr std::uint64_t max_header_bytes = std::uint64_t(100) << 20;

// A validated, memory-mapped file. Copies share the mapping; views stay valid while any copy lives.
class File {
public:
  static File open(const std::filesystem::path& path) {
    File f;
    f.path_ = path.string();
    const int fd = ::open(f.path_.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) f.error("cannot open: ", std::strerror(errno));
    struct stat st {};
    if (::fstat(fd, &st) != 0) {
      const int err = errno;
      ::close(fd);
      f.error("cannot stat: ", std::strerror(err));
    }
    if (!S_ISREG(st.st_mode)) {
      ::close(fd);
      f.error("not a regular file");
    }
    f.size_ = static_cast<std::size_t>(st.st_size);
    if (f.size_ > 0) {
      void* p = ::mmap(nullptr, f.size_, PROT_READ, MAP_PRIVATE, fd, 0);
      const int err = errno;
      ::close(fd);
      if (p == MAP_FAILED) f.error("mmap failed: ", std::strerror(err));
      f.map_ = std::shared_ptr<void>(p, [size = f.size_](void* q) { ::munmap(q, size); });
    } else {
      ::close(fd);
    }
    f.parse();
    return f;
  }

  // The same validation on an in-memory copy of a file's bytes; `source` names it in errors.
  static File from_bytes(const void* data, std::size_t size, const std::string& source) {
    File f;
    f.path_ = source;
    f.size_ = size;
    if (size > 0) {
      std::shared_ptr<std::uint8_t[]> copy(new std::uint8_t[size]);
      std::memcpy(copy.get(), data, size);
      f.map_ = std::shared_ptr<void>(copy, copy.get());
    }
    f.parse();
    return f;
  }

  const std::string& path() const noexcept { return path_; }
  const std::map<std::string, std::string>& metadata() const noexcept { return metadata_; }
  std::string metadata(const std::string& key) const {
    auto it = metadata_.find(key);
    if (it == metadata_.end()) error("no __metadata__ entry '", key, "'");
    return it->second;
  }
  bool has_metadata(const std::string& key) const { return metadata_.count(key) != 0; }
  // Sorted by name.
  const std::vector<TensorInfo>& tensors() const noexcept { return tensors_; }
  bool contains(const std::string& name) const { return index_.count(name) != 0; }
  const TensorInfo& info(const std::string& name) const {
    auto it = index_.find(name);
    if (it == index_.end()) error("no tensor '", name, "'");
    return tensors_[it->second];
  }
  const std::uint8_t* bytes(const TensorInfo& t) const { return data_begin() + t.begin; }

  // Converted copy with a checked rank: any dtype to a floating T, integer dtypes to an integer T (range-checked).
  template <class T, std::size_t Rank>
  Tensor<T, Rank> get(const std::string& name) const {
    const TensorInfo& t = info(name);
    Shape<Rank> shape = checked_shape<Rank>(t);
    Tensor<T, Rank> out(shape);
    convert(t, out.data());
    return out;
  }

  // Zero-copy view: dtype must equal T and the data must be aligned for T.
  template <class T, std::size_t Rank>
  TensorView<const T, Rank> view(const std::string& name) const {
    const TensorInfo& t = info(name);
    if (t.dtype != dtype_of<T>())
      error("tensor '", name, "' has dtype ", dtype_name(t.dtype), ", a zero-copy view needs ",
            dtype_name(dtype_of<T>()));
    const Shape<Rank> shape = checked_shape<Rank>(t);
    if (t.numel() == 0) return TensorView<const T, Rank>(nullptr, shape);
    const std::uint8_t* p = bytes(t);
    if (reinterpret_cast<std::uintptr_t>(p) % alignof(T) != 0)
      error("tensor '", name, "' is not aligned for a zero-copy view");
    return TensorView<const T, Rank>(reinterpret_cast<const T*>(p), shape);
  }

  // Element conversion into a caller buffer of t.numel() elements.
  template <class T>
  void convert(const TensorInfo& t, T* out) const {
    static_assert(std::is_floating_point_v<T> || std::is_integral_v<T>, "convert to a float or integer type");
    const std::uint8_t* p = bytes(t);
    const index_t n = t.numel();
    auto load = [&](auto tag) {
      using S = decltype(tag);
      for (index_t i = 0; i < n; ++i) {
        S v;
        std::memcpy(&v, p + i * sizeof(S), sizeof(S));
        if constexpr (std::is_same_v<S, f16> || std::is_same_v<S, bf16>) {
          out[i] = static_cast<T>(static_cast<float>(v));
        } else if constexpr (std::is_integral_v<T> && std::is_integral_v<S>) {
          if (!std::in_range<T>(v))
            error("tensor '", t.name, "' element ", i, " = ", +v, " does not fit the requested integer type");
          out[i] = static_cast<T>(v);
        } else {
          out[i] = static_cast<T>(v);
        }
      }
    };
    const bool float_source = t.dtype == Dtype::F64 || t.dtype == Dtype::F32 || t.dtype == Dtype::F16 ||
                              t.dtype == Dtype::BF16;
    if constexpr (std::is_integral_v<T>) {
      if (float_source)
        error("tensor '", t.name, "' has floating dtype ", dtype_name(t.dtype), "; read it as float or double");
    }
    switch (t.dtype) {
      case Dtype::F64: if constexpr (std::is_floating_point_v<T>) load(double{}); break;
      case Dtype::F32: if constexpr (std::is_floating_point_v<T>) load(float{}); break;
      case Dtype::F16: if constexpr (std::is_floating_point_v<T>) load(f16{}); break;
      case Dtype::BF16: if constexpr (std::is_floating_point_v<T>) load(bf16{}); break;
      case Dtype::I64: load(std::int64_t{}); break;
      case Dtype::I32: load(std::int32_t{}); break;
      case Dtype::U8: load(std::uint8_t{}); break;
    }
  }

  template <class... Parts>
  [[noreturn]] void error(Parts&&... parts) const {
    fail("safetensors file '", path_, "': ", std::forward<Parts>(parts)...);
  }

private:
  const std::uint8_t* base() const { return static_cast<const std::uint8_t*>(map_.get()); }
  const std::uint8_t* data_begin() const { return base() + 8 + header_len_; }

  template <std::size_t Rank>
  Shape<Rank> checked_shape(const TensorInfo& t) const {
    if (t.shape.size() != Rank)
      error("tensor '", t.name, "' has shape ", shape_string(t.shape), " (rank ", t.shape.size(), "), expected rank ",
            Rank);
    Shape<Rank> s{};
    for (std::size_t i = 0; i < Rank; ++i) s[i] = t.shape[i];
    return s;
  }

  void parse() {
    if (size_ < 8) error("file is ", size_, " bytes, shorter than the 8-byte header length");
    std::uint64_t header_len = 0;
    std::memcpy(&header_len, base(), 8);  // little-endian on every supported target
    if (header_len > max_header_bytes) error("header length ", header_len, " exceeds the limit of ", max_header_bytes);
    if (header_len > size_ - 8)
      error("header length ", header_len, " runs past the end of the file (", size_, " bytes)");
    header_len_ = header_len;
    nlohmann::json header;
    std::string duplicate;
    // nlohmann keeps only the last of repeated keys: catch repeats while parsing.
    std::set<std::string> seen;
    auto on_event = [&](int depth, nlohmann::json::parse_event_t event, nlohmann::json& parsed) {
      if (depth == 1 && event == nlohmann::json::parse_event_t::key && parsed.is_string() &&
          !seen.insert(parsed.get<std::string>()).second && duplicate.empty())
        duplicate = parsed.get<std::string>();
      return true;
    };
    try {
      header = nlohmann::json::parse(reinterpret_cast<const char*>(base() + 8),
                                     reinterpret_cast<const char*>(base() + 8 + header_len), on_event);
    } catch (const nlohmann::json::exception& e) {
      error("header is not valid JSON: ", e.what());
    }
    if (!header.is_object()) error("header is not a JSON object but ", header.type_name());
    if (!duplicate.empty()) error("tensor '", duplicate, "' appears more than once in the header");
    const std::size_t data_size = size_ - 8 - header_len_;
    for (auto it = header.begin(); it != header.end(); ++it) {
      if (it.key() == "__metadata__") {
        if (!it->is_object()) error("__metadata__ is not an object but ", it->type_name());
        for (auto m = it->begin(); m != it->end(); ++m) {
          if (!m->is_string()) error("__metadata__ entry '", m.key(), "' is not a string but ", m->type_name());
          metadata_[m.key()] = m->get<std::string>();
        }
        continue;
      }
      tensors_.push_back(parse_entry(it.key(), *it, data_size));
    }
    // The data section is exactly the tensors back to back: no overlaps, no holes, no trailing bytes.
    std::vector<const TensorInfo*> by_offset;
    for (auto& t : tensors_) by_offset.push_back(&t);
    std::stable_sort(by_offset.begin(), by_offset.end(), [](auto* a, auto* b) {
      return a->begin != b->begin ? a->begin < b->begin : a->end < b->end;
    });
    std::size_t cursor = 0;
    const TensorInfo* previous = nullptr;
    for (auto* t : by_offset) {
      if (t->begin < cursor)
        error("tensor '", t->name, "' (bytes [", t->begin, ", ", t->end, ")) overlaps tensor '", previous->name,
              "' (bytes [", previous->begin, ", ", previous->end, "))");
      if (t->begin > cursor)
        error("tensor '", t->name, "' starts at byte ", t->begin, " leaving a hole after byte ", cursor);
      cursor = t->end;
      previous = t;
    }
    if (cursor != data_size)
      error("data section has ", data_size, " bytes but the tensors cover only ", cursor,
            previous ? concat(" (last tensor '", previous->name, "')") : std::string(" (no tensors)"));
    for (std::size_t i = 0; i < tensors_.size(); ++i) index_[tensors_[i].name] = i;
  }

  TensorInfo parse_entry(const std::string& name, const nlohmann::json& e, std::size_t data_size) const {
    TensorInfo t;
    t.name = name;
    if (!e.is_object()) error("tensor '", name, "': entry is not an object but ", e.type_name());
    if (!e.contains("dtype") || !e["dtype"].is_string()) error("tensor '", name, "': missing dtype");
    if (!parse_dtype(e["dtype"].get<std::string>(), t.dtype))
      error("tensor '", name, "': unknown dtype '", e["dtype"].get<std::string>(), "'");
    if (!e.contains("shape") || !e["shape"].is_array()) error("tensor '", name, "': missing shape");
    // Element count with overflow checks; extents after a zero still must not overflow on their own.
    std::uint64_t numel = 1, nonzero_product = 1;
    constexpr std::uint64_t limit = static_cast<std::uint64_t>(std::numeric_limits<index_t>::max());
    for (auto& d : e["shape"]) {
      if (!d.is_number_unsigned())
        error("tensor '", name, "': shape entry ", d.dump(), " is not a non-negative integer");
      const std::uint64_t extent = d.get<std::uint64_t>();
      if (extent != 0 && (nonzero_product > limit / extent))
        error("tensor '", name, "': shape ", e["shape"].dump(), " overflows the element count");
      if (extent != 0) nonzero_product *= extent;
      numel *= extent;
      t.shape.push_back(static_cast<index_t>(extent));
    }
    const std::size_t element_bytes = dtype_size(t.dtype);
    if (numel > data_size / element_bytes)
      error("tensor '", name, "': shape ", e["shape"].dump(), " of ", dtype_name(t.dtype), " needs ", numel,
            " elements, more than the ", data_size, "-byte data section holds");
    const std::uint64_t bytes = numel * element_bytes;
    const auto& off = e.contains("data_offsets") ? e["data_offsets"] : nlohmann::json();
    if (!off.is_array() || off.size() != 2 || !off[0].is_number_unsigned() || !off[1].is_number_unsigned())
      error("tensor '", name, "': data_offsets must be two non-negative integers, got ", off.dump());
    const std::uint64_t b = off[0].get<std::uint64_t>(), en = off[1].get<std::uint64_t>();
    if (b > en) error("tensor '", name, "': data_offsets [", b, ", ", en, "] are reversed");
    if (en > data_size)
      error("tensor '", name, "': data_offsets end ", en, " is past the data section (", data_size, " bytes)");
    if (en - b != bytes)
      error("tensor '", name, "': byte length ", en - b, " does not match shape ", e["shape"].dump(), " x ",
            element_bytes, " bytes = ", bytes);
    t.begin = b;
    t.end = en;
    return t;
  }

  std::string path_;
  std::shared_ptr<void> map_;
  std::size_t size_ = 0;
  std::size_t header_len_ = 0;
  std::map<std::string, std::string> metadata_;
  std::vector<TensorInfo> tensors_;
  std::map<std::string, std::size_t> index_;
};

// Collects tensors, then writes them atomically (temp file in the same folder, fsync, rename).
class Writer {
public:
  void set_metadata(const std::string& key, const std::string& value) { metadata_[key] = value; }

  void add_raw(const std::string& name, Dtype dtype, std::vector<index_t> shape, const void* data, std::size_t bytes) {
    require(name != "__metadata__", "safetensors writer: '__metadata__' is reserved and cannot name a tensor");
    for (auto& e : entries_) require(e.name != name, "safetensors writer: duplicate tensor '", name, "'");
    index_t n = 1;
    for (auto d : shape) {
      require(d >= 0, "safetensors writer: tensor '", name, "' has a negative extent in ", shape_string(shape));
      require(d == 0 || n <= std::numeric_limits<index_t>::max() / d, "safetensors writer: tensor '", name,
              "' shape ", shape_string(shape), " overflows the element count");
      n *= d;
    }
    require(static_cast<std::size_t>(n) <= std::numeric_limits<std::size_t>::max() / dtype_size(dtype) &&
                static_cast<std::size_t>(n) * dtype_size(dtype) == bytes,
            "safetensors writer: tensor '", name, "' byte count ", bytes, " does not match shape ",
            shape_string(shape), " of ", dtype_name(dtype));
    Entry e{name, dtype, std::move(shape), {}};
    e.bytes.resize(bytes);
    if (bytes) std::memcpy(e.bytes.data(), data, bytes);
    entries_.push_back(std::move(e));
  }

  template <class T, std::size_t Rank>
  void add(const std::string& name, TensorView<T, Rank> t) {
    using V = std::remove_const_t<T>;
    auto c = copy_of(t);
    add_raw(name, dtype_of<V>(), std::vector<index_t>(t.shape().begin(), t.shape().end()), c.data(),
            static_cast<std::size_t>(c.size()) * sizeof(V));
  }
  template <class T, std::size_t Rank>
  void add(const std::string& name, const Tensor<T, Rank>& t) { add(name, t.view()); }

  void write(const std::filesystem::path& path) const {
    nlohmann::json header = nlohmann::json::object();
    if (!metadata_.empty()) header["__metadata__"] = metadata_;
    std::size_t offset = 0;
    for (auto& e : entries_) {
      header[e.name] = {{"dtype", dtype_name(e.dtype)}, {"shape", e.shape}, {"data_offsets", {offset, offset + e.bytes.size()}}};
      offset += e.bytes.size();
    }
    std::string text = header.dump();
    while ((8 + text.size()) % 8 != 0) text.push_back(' ');  // keeps the data section 8-byte aligned
    write_file_atomic(path, "safetensors writer", [&](std::ostream& out) {
      const std::uint64_t len = text.size();
      out.write(reinterpret_cast<const char*>(&len), 8);
      out.write(text.data(), static_cast<std::streamsize>(text.size()));
      for (auto& e : entries_) out.write(reinterpret_cast<const char*>(e.bytes.data()), static_cast<std::streamsize>(e.bytes.size()));
    });
  }

private:
  struct Entry {
    std::string name;
    Dtype dtype;
    std::vector<index_t> shape;
    std::vector<std::uint8_t> bytes;
  };
  std::map<std::string, std::string> metadata_;
  std::vector<Entry> entries_;
};

}  // namespace safetensors
}  // namespace v0
}  // namespace flexsplat
