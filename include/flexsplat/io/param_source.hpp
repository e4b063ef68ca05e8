#pragma once
// Named parameter tensors for the geometry model: zero-copy views of an mmapped safetensors file where dtype and
// alignment allow, otherwise one converted copy per tensor (F16/BF16/F64 -> T), plus in-memory tensors (random
// weights for benchmarks and tests).
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat {
inline namespace v0 {
namespace io {

// One expected parameter: its name (without file prefix) and shape.
struct TensorSpec {
  std::string name;
  std::vector<index_t> shape;
};

inline index_t spec_numel(const TensorSpec& s) {
  index_t n = 1;
  for (index_t e : s.shape) n *= e;
  return n;
}

// Elements of one flat block holding every spec in order.
inline index_t flat_size(const std::vector<TensorSpec>& specs) {
  index_t n = 0;
  for (const auto& s : specs) n += spec_numel(s);
  return n;
}

// The gradient slot of parameter p when parameters live in one flat block and gradients in another at the same
// offsets; null stays null.
template <class T>
T* rebase_pointer(const T* p, const T* params_base, T* grads_base) {
  return p ? grads_base + (p - params_base) : nullptr;
}

template <class T>
class ParamSource {
public:
  ParamSource() = default;
  // prefix is prepended to every name looked up in the file ("param." in reference bundles).
  explicit ParamSource(safetensors::File file, std::string prefix = {})
      : file_(std::move(file)), prefix_(std::move(prefix)) {}

  // In-memory tensor; takes precedence over the file.
  void add(const std::string& name, std::vector<index_t> shape, std::vector<T> values) {
    index_t n = 1;
    for (index_t e : shape) n *= e;
    require(static_cast<index_t>(values.size()) == n, "parameter '", name, "': ", values.size(),
            " values for shape ", safetensors::shape_string(shape));
    auto buffer = std::make_unique<Buffer>(values.begin(), values.end());
    memory_[name] = MemoryTensor{std::move(shape), buffer->data()};
    owned_.push_back(std::move(buffer));
  }

  // External tensor, not copied (a training store's params block): `data` must outlive this source and every
  // weight struct bound from it. Takes precedence over the file, like add().
  void add_view(const std::string& name, std::vector<index_t> shape, const T* data) {
    require(data != nullptr, "parameter '", name, "': null view");
    memory_[name] = MemoryTensor{std::move(shape), data};
  }

  bool has_file() const noexcept { return file_.has_value(); }
  const safetensors::File& file() const {
    require(file_.has_value(), "parameter source has no file");
    return *file_;
  }
  const std::string& prefix() const noexcept { return prefix_; }
  std::string describe() const { return file_ ? "file '" + file_->path() + "'" : std::string("in-memory parameters"); }

  bool contains(const std::string& name) const {
    return memory_.count(name) || (file_ && file_->contains(prefix_ + name));
  }

  std::vector<index_t> shape(const std::string& name) const {
    if (auto it = memory_.find(name); it != memory_.end()) return it->second.shape;
    require(file_ && file_->contains(prefix_ + name), describe(), ": no parameter '", prefix_ + name, "'");
    return file_->info(prefix_ + name).shape;
  }

  // Pointer to the tensor's elements; its shape must equal `expected`.
  const T* get(const std::string& name, const std::vector<index_t>& expected) {
    if (auto it = memory_.find(name); it != memory_.end()) {
      check_shape(name, it->second.shape, expected);
      return it->second.data;
    }
    require(file_.has_value() && file_->contains(prefix_ + name), describe(), ": missing parameter '", prefix_ + name,
            "' (expected shape ", safetensors::shape_string(expected), ")");
    const auto& info = file_->info(prefix_ + name);
    check_shape(name, info.shape, expected);
    if (auto it = converted_.find(name); it != converted_.end()) return it->second;
    const std::uint8_t* bytes = file_->bytes(info);
    if (info.dtype == safetensors::dtype_of<T>() && reinterpret_cast<std::uintptr_t>(bytes) % alignof(T) == 0)
      return reinterpret_cast<const T*>(bytes);
    require(info.dtype == safetensors::Dtype::F32 || info.dtype == safetensors::Dtype::F16 ||
                info.dtype == safetensors::Dtype::BF16 || info.dtype == safetensors::Dtype::F64,
            describe(), ": parameter '", prefix_ + name, "' has dtype ", safetensors::dtype_name(info.dtype),
            ", expected a floating-point type");
    auto buffer = std::make_unique<Buffer>(static_cast<std::size_t>(info.numel()));
    file_->convert(info, buffer->data());
    converted_bytes_ += buffer->size() * sizeof(T);
    const T* p = buffer->data();
    converted_[name] = p;
    owned_.push_back(std::move(buffer));
    return p;
  }

  // Bytes held in converted copies (zero for an aligned F32 file read as float).
  std::size_t converted_bytes() const noexcept { return converted_bytes_; }

private:
  using Buffer = std::vector<T, AlignedAllocator<T>>;
  struct MemoryTensor {
    std::vector<index_t> shape;
    const T* data = nullptr;
  };
  void check_shape(const std::string& name, const std::vector<index_t>& have, const std::vector<index_t>& want) const {
    require(have == want, describe(), ": parameter '", prefix_ + name, "' has shape ", safetensors::shape_string(have),
            ", expected ", safetensors::shape_string(want));
  }

  std::optional<safetensors::File> file_;
  std::string prefix_;
  std::map<std::string, MemoryTensor> memory_;
  std::map<std::string, const T*> converted_;
  std::vector<std::unique_ptr<Buffer>> owned_;
  std::size_t converted_bytes_ = 0;
};

// Binds every spec as a view into `base` (a flat block of flat_size(specs) elements), in order.
template <class T>
void add_flat_views(ParamSource<T>& src, const std::vector<TensorSpec>& specs, const T* base) {
  index_t at = 0;
  for (const auto& s : specs) {
    src.add_view(s.name, s.shape, base + at);
    at += spec_numel(s);
  }
}

}  // namespace io
}  // namespace v0
}  // namespace flexsplat
