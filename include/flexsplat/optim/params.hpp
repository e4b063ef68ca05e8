#pragma once
// One parameter store for the whole model, in llm.c's spirit: params, grads and Adam's m and v are four flat
// 64-byte-aligned blocks with the same layout; every tensor is registered by a stable name and shape and reached by
// name (offset, span, shape) or in registration order. Geometry weights bind into the params block without copies
// (bind_views); the decoder's flat block is one contiguous segment (decoder::append_model_specs).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/io/param_source.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat {
inline namespace v0 {
namespace train {

using io::TensorSpec;

// Weight-decay rule: only matrices and convolution kernels decay. Off for every tensor of rank < 2 (biases,
// LayerNorm weights, LayerScale gammas, per-channel vectors) and for learned tokens and embedding tables, named by
// their last dot-separated component: it contains "token" (camera_token, register_tokens, cls_token, mask_token,
// empty_pose_tokens) or ends in "embed" / "embeddings" (pos_embed, query_embeddings). "patch_embed.proj.weight" ends
// in "weight", so it decays.
inline bool default_weight_decay(const std::string& name, const std::vector<index_t>& shape) {
  if (shape.size() < 2) return false;
  const std::size_t dot = name.rfind('.');
  const std::string last = dot == std::string::npos ? name : name.substr(dot + 1);
  auto ends_with = [&](const char* tail) {
    const std::string t(tail);
    return last.size() >= t.size() && last.compare(last.size() - t.size(), t.size(), t) == 0;
  };
  return last.find("token") == std::string::npos && !ends_with("embed") && !ends_with("embeddings");
}

struct ParamInfo {
  std::string name;
  std::vector<index_t> shape;
  index_t offset = 0;  // elements from the start of every block
  index_t numel = 0;
  bool decay = false;     // AdamW weight decay applies
  double lr_scale = 1.0;  // this tensor's learning rate is lr_scale x the schedule's (a PyTorch param group's lr)
};

// A registered group of tensors stored back to back (no padding inside); its start is 64-byte aligned.
struct Segment {
  std::string name;
  index_t offset = 0, size = 0;
  std::size_t first = 0, count = 0;  // indices into tensors()
};

template <class T>
class ParamStore {
public:
  using Block = std::vector<T, AlignedAllocator<T>>;
  static constexpr index_t alignment_elements = static_cast<index_t>(64 / sizeof(T));

  // Registers `specs` contiguously as segment `segment`, starting at the next 64-byte boundary; returns its offset.
  // Only before allocate(). Names must be unique across the store.
  index_t add_segment(const std::string& segment, const std::vector<io::TensorSpec>& specs) {
    require(!allocated(), "parameter store: segment '", segment, "' registered after allocate()");
    for (const auto& s : segments_) require(s.name != segment, "parameter store: duplicate segment '", segment, "'");
    index_t at = (size_ + alignment_elements - 1) / alignment_elements * alignment_elements;
    Segment seg{segment, at, 0, tensors_.size(), specs.size()};
    for (const auto& spec : specs) {
      require(!index_.count(spec.name), "parameter store: tensor '", spec.name, "' registered twice (segment '",
              segment, "')");
      index_t n = 1;
      for (index_t e : spec.shape) {
        require(e >= 0, "parameter store: tensor '", spec.name, "' has shape ", safetensors::shape_string(spec.shape));
        n *= e;
      }
      index_.emplace(spec.name, tensors_.size());
      tensors_.push_back({spec.name, spec.shape, at, n, default_weight_decay(spec.name, spec.shape)});
      at += n;
    }
    seg.size = at - seg.offset;
    segments_.push_back(seg);
    size_ = at;
    return seg.offset;
  }

  // Allocates the blocks, zero-filled: params only (inference) or params, grads, m and v (training).
  void allocate(bool training = true) {
    require(!allocated(), "parameter store: allocate() called twice");
    const index_t n = std::max<index_t>(size_, 1);
    params_.assign(static_cast<std::size_t>(n), T(0));
    if (training) {
      grads_.assign(static_cast<std::size_t>(n), T(0));
      m_.assign(static_cast<std::size_t>(n), T(0));
      v_.assign(static_cast<std::size_t>(n), T(0));
    }
  }
  bool allocated() const noexcept { return !params_.empty(); }
  bool training() const noexcept { return !grads_.empty(); }

  // Elements per block, including alignment padding between segments (always zero in every block).
  index_t size() const noexcept { return size_; }
  // Elements in tensors (without padding).
  index_t tensor_elements() const {
    index_t n = 0;
    for (const auto& t : tensors_) n += t.numel;
    return n;
  }
  const std::vector<ParamInfo>& tensors() const noexcept { return tensors_; }
  const std::vector<Segment>& segments() const noexcept { return segments_; }
  const Segment& segment(const std::string& name) const {
    for (const auto& s : segments_)
      if (s.name == name) return s;
    fail("parameter store: no segment '", name, "'");
  }
  bool contains(const std::string& name) const { return index_.count(name) != 0; }
  const ParamInfo& info(const std::string& name) const {
    auto it = index_.find(name);
    if (it == index_.end()) fail("parameter store: no tensor '", name, "'");
    return tensors_[it->second];
  }
  // Per-tensor learning-rate multiplier (default 1).
  void set_lr_scale(const std::string& name, double scale) {
    require(std::isfinite(scale) && scale >= 0, "parameter store: learning-rate scale ", scale, " for '", name,
            "' must be finite and >= 0");
    info(name);
    tensors_[index_.at(name)].lr_scale = scale;
  }
  // Overrides the weight-decay rule for one tensor.
  void set_decay(const std::string& name, bool decay) {
    info(name);
    tensors_[index_.at(name)].decay = decay;
  }

  T* params() { return checked(params_, "params"); }
  const T* params() const { return checked(params_, "params"); }
  T* grads() { return checked(grads_, "grads"); }
  const T* grads() const { return checked(grads_, "grads"); }
  T* adam_m() { return checked(m_, "Adam m"); }
  const T* adam_m() const { return checked(m_, "Adam m"); }
  T* adam_v() { return checked(v_, "Adam v"); }
  const T* adam_v() const { return checked(v_, "Adam v"); }

  std::span<T> param(const ParamInfo& t) { return {params() + t.offset, static_cast<std::size_t>(t.numel)}; }
  std::span<const T> param(const ParamInfo& t) const { return {params() + t.offset, static_cast<std::size_t>(t.numel)}; }
  std::span<T> grad(const ParamInfo& t) { return {grads() + t.offset, static_cast<std::size_t>(t.numel)}; }
  std::span<const T> grad(const ParamInfo& t) const { return {grads() + t.offset, static_cast<std::size_t>(t.numel)}; }
  std::span<T> param(const std::string& name) { return param(info(name)); }
  std::span<const T> param(const std::string& name) const { return param(info(name)); }
  std::span<T> grad(const std::string& name) { return grad(info(name)); }
  std::span<const T> grad(const std::string& name) const { return grad(info(name)); }
  // The params of a whole segment (the decoder's flat block).
  T* segment_params(const std::string& name) { return params() + segment(name).offset; }
  T* segment_grads(const std::string& name) { return grads() + segment(name).offset; }

  void zero_grads() { std::fill(grads_.begin(), grads_.end(), T(0)); }

  // Registers every tensor of segment `segment` (all segments if empty) as an external view in `src`, so
  // geometry::load_*_weights bind pointers straight into the params block. The store must not be reallocated while
  // the weights are used.
  void bind_views(io::ParamSource<T>& src, const std::string& segment_name = {}) const {
    for (const auto& s : segments_) {
      if (!segment_name.empty() && s.name != segment_name) continue;
      for (std::size_t i = s.first; i < s.first + s.count; ++i)
        src.add_view(tensors_[i].name, tensors_[i].shape, params() + tensors_[i].offset);
    }
  }

private:
  template <class B>
  static auto checked(B& b, const char* what) -> decltype(b.data()) {
    if (b.empty()) fail("parameter store: the ", what, " block is not allocated (call allocate(true) first)");
    return b.data();
  }

  std::vector<ParamInfo> tensors_;
  std::vector<Segment> segments_;
  std::map<std::string, std::size_t> index_;
  index_t size_ = 0;
  Block params_, grads_, m_, v_;
};

}  // namespace train
}  // namespace v0
}  // namespace flexsplat
