#pragma once
// bf16 and IEEE f16 as storage types: converted to float for arithmetic.
#include <bit>
#include <cstdint>
#include <cmath>

namespace flexsplat {
inline namespace v0 {

struct bf16 {
  std::uint16_t bits = 0;
  bf16() = default;
  explicit bf16(float value) noexcept {
    std::uint32_t u = std::bit_cast<std::uint32_t>(value);
    if ((u & 0x7fffffffu) > 0x7f800000u) {  // NaN stays a quiet NaN
      bits = static_cast<std::uint16_t>((u >> 16) | 0x40u);
      return;
    }
    u += 0x7fffu + ((u >> 16) & 1u);  // round to nearest even
    bits = static_cast<std::uint16_t>(u >> 16);
  }
  explicit operator float() const noexcept { return std::bit_cast<float>(std::uint32_t(bits) << 16); }
  static bf16 from_bits(std::uint16_t b) noexcept { bf16 h; h.bits = b; return h; }
};

struct f16 {
  std::uint16_t bits = 0;
  f16() = default;
  explicit f16(float value) noexcept {
    const std::uint32_t u = std::bit_cast<std::uint32_t>(value);
    const std::uint32_t sign = (u >> 16) & 0x8000u;
    const std::uint32_t abs = u & 0x7fffffffu;
    if (abs > 0x7f800000u) { bits = static_cast<std::uint16_t>(sign | 0x7e00u); return; }
    if (abs >= 0x47800000u) { bits = static_cast<std::uint16_t>(sign | 0x7c00u); return; }  // overflow to inf
    if (abs < 0x38800000u) {  // subnormal or zero in f16
      const float magnitude = std::bit_cast<float>(abs);
      const std::uint32_t sub = static_cast<std::uint32_t>(std::nearbyint(magnitude * 16777216.0f));
      bits = static_cast<std::uint16_t>(sign | sub);
      return;
    }
    std::uint32_t rounded = abs + 0xfffu + ((abs >> 13) & 1u) - (112u << 23);
    bits = static_cast<std::uint16_t>(sign | (rounded >> 13));
  }
  explicit operator float() const noexcept {
    const std::uint32_t sign = std::uint32_t(bits & 0x8000u) << 16;
    const std::uint32_t exponent = (bits >> 10) & 0x1fu;
    const std::uint32_t mantissa = bits & 0x3ffu;
    if (exponent == 0) {
      const float magnitude = static_cast<float>(mantissa) * (1.0f / 16777216.0f);
      return sign ? -magnitude : magnitude;
    }
    if (exponent == 31) return std::bit_cast<float>(sign | 0x7f800000u | (mantissa << 13));
    return std::bit_cast<float>(sign | ((exponent + 112u) << 23) | (mantissa << 13));
  }
  static f16 from_bits(std::uint16_t b) noexcept { f16 h; h.bits = b; return h; }
};

}  // namespace v0
}  // namespace flexsplat
