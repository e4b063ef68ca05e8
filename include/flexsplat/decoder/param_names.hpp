#pragma once
// Names and shapes of every tensor of the decoder side (appearance UNet, fusion, Gaussian decoder), listed in exactly
// the order and at exactly the offsets of ModelParamLayout and its sub-layouts: registered as one segment of a
// train::ParamStore, they make the model's flat parameter block one contiguous range of the store. Shapes follow
// PyTorch: conv [out, in, kh, kw], transposed conv [in, out, kh, kw], linear [out, in].
#include <string>
#include <vector>

#include "flexsplat/decoder/model.hpp"
#include "flexsplat/io/param_source.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// prefix is prepended to every name (e.g. "model." ); the names below it are "unet.*", "fusion.*", "decoder.*".
inline void append_model_specs(std::vector<io::TensorSpec>& out, const ModelConfig& c,
                               const std::string& prefix = {}) {
  validate_model_config(c);
  auto add = [&](const std::string& name, std::vector<index_t> shape) { out.push_back({prefix + name, std::move(shape)}); };

  // UNet, in unet_convs order: stem, per level (stride-2 conv, conv), then per level from the deepest (up, conv).
  const auto convs = unet_convs(c.unet);
  std::vector<std::string> names{"unet.stem"};
  for (index_t l = 0; l < c.unet.levels; ++l) {
    names.push_back("unet.encoder." + std::to_string(l) + ".down");
    names.push_back("unet.encoder." + std::to_string(l) + ".conv");
  }
  for (index_t l = c.unet.levels; l-- > 0;) {
    names.push_back("unet.decoder." + std::to_string(l) + ".up");
    names.push_back("unet.decoder." + std::to_string(l) + ".conv");
  }
  require(names.size() == convs.size(), "model specs: ", convs.size(), " UNet convolutions but ", names.size(), " names");
  for (std::size_t i = 0; i < convs.size(); ++i) {
    const auto& v = convs[i];
    if (v.transposed) add(names[i] + ".weight", {v.in_c, v.out_c, v.kernel, v.kernel});
    else add(names[i] + ".weight", {v.out_c, v.in_c, v.kernel, v.kernel});
    add(names[i] + ".bias", {v.out_c});
  }

  // Fusion, in FusionParamLayout order.
  const auto& f = c.fusion;
  add("fusion.depth_proj.weight", {f.unet_channels, f.depth_channels, 1, 1});
  add("fusion.depth_proj.bias", {f.unet_channels});
  add("fusion.refine.weight", {f.unet_channels, f.unet_channels, 3, 3});
  add("fusion.refine.bias", {f.unet_channels});
  add("fusion.reduce.weight", {f.out_channels, f.unet_channels, 1, 1});
  add("fusion.reduce.bias", {f.out_channels});
  add("fusion.rgb_head.weight", {3, f.out_channels, 1, 1});
  add("fusion.rgb_head.bias", {3});

  // Decoder, in DecoderParamLayout / take_layer_offsets order.
  const auto& d = c.decoder;
  const auto deform = d.deform();
  const index_t slots = deform.slot_count() * deform.heads * deform.points;
  add("decoder.query_embeddings", {d.max_queries, d.dim});
  add("decoder.init_head.weight", {splat_values, d.dim});
  add("decoder.init_head.bias", {splat_values});
  for (index_t l = 0; l < d.layers; ++l) {
    const std::string p = "decoder.layers." + std::to_string(l) + ".";
    add(p + "deform_attn.value_proj.weight", {d.dim, d.value_dim});
    add(p + "deform_attn.value_proj.bias", {d.dim});
    add(p + "deform_attn.sampling_offsets.weight", {2 * slots, d.dim});
    add(p + "deform_attn.sampling_offsets.bias", {2 * slots});
    add(p + "deform_attn.attention_weights.weight", {slots, d.dim});
    add(p + "deform_attn.attention_weights.bias", {slots});
    add(p + "deform_attn.output_proj.weight", {d.dim, d.dim});
    add(p + "deform_attn.output_proj.bias", {d.dim});
    add(p + "norm1.weight", {d.dim});
    add(p + "norm1.bias", {d.dim});
    add(p + "self_attn.qkv.weight", {3 * d.dim, d.dim});
    add(p + "self_attn.qkv.bias", {3 * d.dim});
    add(p + "self_attn.proj.weight", {d.dim, d.dim});
    add(p + "self_attn.proj.bias", {d.dim});
    add(p + "norm2.weight", {d.dim});
    add(p + "norm2.bias", {d.dim});
    add(p + "ffn.fc1.weight", {d.ffn, d.dim});
    add(p + "ffn.fc1.bias", {d.ffn});
    add(p + "ffn.fc2.weight", {d.dim, d.ffn});
    add(p + "ffn.fc2.bias", {d.dim});
    add(p + "norm3.weight", {d.dim});
    add(p + "norm3.bias", {d.dim});
    add(p + "head.weight", {splat_values, d.dim});
    add(p + "head.bias", {splat_values});
  }
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
