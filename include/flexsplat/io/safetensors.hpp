#pragma once
// safetensors: validating mmap reader (zero-copy where dtype and alignment allow) and atomic writer.
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

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
    for (auto e : shape) n *= e;
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

class File {
public:
  static File open(const std::filesystem::path& path) {
    File f;
    f.path_ = path.string();
    const int fd = ::open(f.path_.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) f.error("cannot open: ", std::strerror(errno));
    struct stat st {};
    if (::fstat(fd, &st) != 0) {
      ::close(fd);
      f.error("cannot stat: ", std::strerror(errno));
    }
    f.size_ = static_cast<std::size_t>(st.st_size);
    if (f.size_ > 0) {
      void* p = ::mmap(nullptr, f.size_, PROT_READ, MAP_PRIVATE, fd, 0);
      ::close(fd);
      if (p == MAP_FAILED) f.error("mmap failed: ", std::strerror(errno));
      f.map_ = std::shared_ptr<void>(p, [size = f.size_](void* q) { ::munmap(q, size); });
    } else {
      ::close(fd);
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
  const std::vector<TensorInfo>& tensors() const noexcept { return tensors_; }
  bool contains(const std::string& name) const { return index_.count(name) != 0; }
  const TensorInfo& info(const std::string& name) const {
    auto it = index_.find(name);
    if (it == index_.end()) error("no tensor '", name, "'");
    return tensors_[it->second];
  }
  const std::uint8_t* bytes(const TensorInfo& t) const { return data_begin() + t.begin; }

  // Converted copy with a checked rank: any float/int dtype to T.
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
    const std::uint8_t* p = bytes(t);
    if (reinterpret_cast<std::uintptr_t>(p) % alignof(T) != 0)
      error("tensor '", name, "' is not aligned for a zero-copy view");
    return TensorView<const T, Rank>(reinterpret_cast<const T*>(p), checked_shape<Rank>(t));
  }

  // Element conversion into a caller buffer of t.numel() elements.
  template <class T>
  void convert(const TensorInfo& t, T* out) const {
    const std::uint8_t* p = bytes(t);
    const index_t n = t.numel();
    auto load = [&](auto tag) {
      using S = decltype(tag);
      for (index_t i = 0; i < n; ++i) {
        S v;
        std::memcpy(&v, p + i * sizeof(S), sizeof(S));
        if constexpr (std::is_same_v<S, f16> || std::is_same_v<S, bf16>)
          out[i] = static_cast<T>(static_cast<float>(v));
        else
          out[i] = static_cast<T>(v);
      }
    };
    switch (t.dtype) {
      case Dtype::F64: load(double{}); break;
      case Dtype::F32: load(float{}); break;
      case Dtype::F16: load(f16{}); break;
      case Dtype::BF16: load(bf16{}); break;
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
    std::memcpy(&header_len, base(), 8);
    if (header_len > max_header_bytes) error("header length ", header_len, " exceeds the limit of ", max_header_bytes);
    if (header_len > size_ - 8)
      error("header length ", header_len, " runs past the end of the file (", size_, " bytes)");
    header_len_ = header_len;
    nlohmann::json header;
    try {
      header = nlohmann::json::parse(reinterpret_cast<const char*>(base() + 8),
                                     reinterpret_cast<const char*>(base() + 8 + header_len));
    } catch (const nlohmann::json::exception& e) {
      error("header is not valid JSON: ", e.what());
    }
    if (!header.is_object()) error("header is not a JSON object");
    const std::size_t data_size = size_ - 8 - header_len_;
    for (auto it = header.begin(); it != header.end(); ++it) {
      if (it.key() == "__metadata__") {
        if (!it->is_object()) error("__metadata__ is not an object");
        for (auto m = it->begin(); m != it->end(); ++m) {
          if (!m->is_string()) error("__metadata__ entry '", m.key(), "' is not a string");
          metadata_[m.key()] = m->get<std::string>();
        }
        continue;
      }
      tensors_.push_back(parse_entry(it.key(), *it, data_size));
    }
    std::vector<const TensorInfo*> by_offset;
    for (auto& t : tensors_) by_offset.push_back(&t);
    std::sort(by_offset.begin(), by_offset.end(), [](auto* a, auto* b) { return a->begin < b->begin; });
    std::size_t cursor = 0;
    for (auto* t : by_offset) {
      if (t->begin < cursor) error("tensor '", t->name, "' overlaps the previous tensor (starts at ", t->begin, ")");
      cursor = t->end;
    }
    for (std::size_t i = 0; i < tensors_.size(); ++i) index_[tensors_[i].name] = i;
  }

  TensorInfo parse_entry(const std::string& name, const nlohmann::json& e, std::size_t data_size) const {
    TensorInfo t;
    t.name = name;
    if (!e.is_object()) error("tensor '", name, "': entry is not an object");
    if (!e.contains("dtype") || !e["dtype"].is_string()) error("tensor '", name, "': missing dtype");
    if (!parse_dtype(e["dtype"].get<std::string>(), t.dtype))
      error("tensor '", name, "': unknown dtype '", e["dtype"].get<std::string>(), "'");
    if (!e.contains("shape") || !e["shape"].is_array()) error("tensor '", name, "': missing shape");
    std::uint64_t bytes = dtype_size(t.dtype);
    for (auto& d : e["shape"]) {
      if (!d.is_number_unsigned()) error("tensor '", name, "': shape entry ", d.dump(), " is not a non-negative integer");
      const std::uint64_t extent = d.get<std::uint64_t>();
      if (extent != 0 && bytes > data_size / extent && bytes != 0)
        error("tensor '", name, "': shape ", e["shape"].dump(), " needs more bytes than the file holds");
      bytes *= extent;
      t.shape.push_back(static_cast<index_t>(extent));
    }
    const auto& off = e.contains("data_offsets") ? e["data_offsets"] : nlohmann::json();
    if (!off.is_array() || off.size() != 2 || !off[0].is_number_unsigned() || !off[1].is_number_unsigned())
      error("tensor '", name, "': data_offsets must be two non-negative integers");
    const std::uint64_t b = off[0].get<std::uint64_t>(), en = off[1].get<std::uint64_t>();
    if (b > en) error("tensor '", name, "': data_offsets [", b, ", ", en, "] are reversed");
    if (en > data_size) error("tensor '", name, "': data_offsets end ", en, " is past the data section (", data_size, " bytes)");
    if (en - b != bytes)
      error("tensor '", name, "': byte length ", en - b, " does not match shape ", e["shape"].dump(), " x ",
            dtype_size(t.dtype), " bytes = ", bytes);
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

// Collects tensors, then writes them atomically (temp file + rename).
class Writer {
public:
  void set_metadata(const std::string& key, const std::string& value) { metadata_[key] = value; }

  void add_raw(const std::string& name, Dtype dtype, std::vector<index_t> shape, const void* data, std::size_t bytes) {
    for (auto& e : entries_) require(e.name != name, "safetensors writer: duplicate tensor '", name, "'");
    index_t n = 1;
    for (auto d : shape) {
      require(d >= 0, "safetensors writer: tensor '", name, "' has a negative extent");
      n *= d;
    }
    require(static_cast<std::size_t>(n) * dtype_size(dtype) == bytes, "safetensors writer: tensor '", name,
            "' byte count ", bytes, " does not match its shape");
    Entry e{name, dtype, std::move(shape), {}};
    e.bytes.resize(bytes);
    if (bytes) std::memcpy(e.bytes.data(), data, bytes);
    entries_.push_back(std::move(e));
  }

  template <class T, std::size_t Rank>
  void add(const std::string& name, TensorView<const T, Rank> t) {
    auto c = copy_of(t);
    add_raw(name, dtype_of<T>(), std::vector<index_t>(t.shape().begin(), t.shape().end()), c.data(),
            c.size() * sizeof(T));
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
    const std::filesystem::path tmp = path.string() + ".tmp" + std::to_string(::getpid());
    {
      std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
      require(static_cast<bool>(out), "safetensors writer: cannot create '", tmp.string(), "'");
      const std::uint64_t len = text.size();
      out.write(reinterpret_cast<const char*>(&len), 8);
      out.write(text.data(), static_cast<std::streamsize>(text.size()));
      for (auto& e : entries_) out.write(reinterpret_cast<const char*>(e.bytes.data()), static_cast<std::streamsize>(e.bytes.size()));
      out.flush();
      if (!out) {
        std::error_code ec;
        std::filesystem::remove(tmp, ec);
        fail("safetensors writer: writing '", tmp.string(), "' failed");
      }
    }
    std::error_code ec;
    std::filesystem::rename(tmp, path, ec);
    if (ec) {
      std::filesystem::remove(tmp, ec);
      fail("safetensors writer: cannot rename to '", path.string(), "'");
    }
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
