#include <catch2/catch.hpp>

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>

#include "flexsplat/core/half.hpp"

using namespace flexsplat;

namespace {
float from_bits32(std::uint32_t u) { return std::bit_cast<float>(u); }
std::uint16_t f16_bits(float x) { return f16(x).bits; }
std::uint16_t bf16_bits(float x) { return bf16(x).bits; }
float f16_value(std::uint16_t b) { return static_cast<float>(f16::from_bits(b)); }
float bf16_value(std::uint16_t b) { return static_cast<float>(bf16::from_bits(b)); }
}  // namespace

TEST_CASE("f16 decodes known bit patterns exactly", "[half]") {
  CHECK(f16_value(0x3c00) == 1.0f);
  CHECK(f16_value(0xc000) == -2.0f);
  CHECK(f16_value(0x7bff) == 65504.0f);
  CHECK(f16_value(0x0400) == std::ldexp(1.0f, -14));        // smallest normal
  CHECK(f16_value(0x0001) == std::ldexp(1.0f, -24));        // smallest subnormal
  CHECK(f16_value(0x03ff) == std::ldexp(1023.0f, -24));     // largest subnormal
  CHECK(f16_value(0x8001) == -std::ldexp(1.0f, -24));
  CHECK(f16_value(0x3555) == std::ldexp(341.0f + 1024.0f, -12));
  CHECK(std::bit_cast<std::uint32_t>(f16_value(0x8000)) == 0x80000000u);  // negative zero keeps its sign
  CHECK(f16_value(0x7c00) == std::numeric_limits<float>::infinity());
  CHECK(f16_value(0xfc00) == -std::numeric_limits<float>::infinity());
  CHECK(std::isnan(f16_value(0x7e00)));
  CHECK(std::isnan(f16_value(0x7c01)));  // signalling NaN pattern is still NaN, never inf
}

TEST_CASE("f16 encodes with round-to-nearest-even, overflow to inf, subnormals and NaN", "[half]") {
  CHECK(f16_bits(1.0f) == 0x3c00);
  CHECK(f16_bits(-2.0f) == 0xc000);
  CHECK(f16_bits(65504.0f) == 0x7bff);
  CHECK(f16_bits(1.0f / 3.0f) == 0x3555);
  // Ties go to the even mantissa.
  CHECK(f16_bits(1.0f + std::ldexp(1.0f, -11)) == 0x3c00);
  CHECK(f16_bits(1.0f + 3.0f * std::ldexp(1.0f, -11)) == 0x3c02);
  CHECK(f16_bits(1.0f + std::ldexp(1.0f, -11) + std::ldexp(1.0f, -20)) == 0x3c01);
  // 65520 is the tie between 65504 and 2^16: rounds to the even side, which is inf.
  CHECK(f16_bits(65519.0f) == 0x7bff);
  CHECK(f16_bits(65520.0f) == 0x7c00);
  CHECK(f16_bits(1e10f) == 0x7c00);
  CHECK(f16_bits(-1e10f) == 0xfc00);
  CHECK(f16_bits(std::numeric_limits<float>::infinity()) == 0x7c00);
  // Subnormal results and their ties.
  CHECK(f16_bits(std::ldexp(1.0f, -24)) == 0x0001);
  CHECK(f16_bits(std::ldexp(1.0f, -25)) == 0x0000);
  CHECK(f16_bits(std::ldexp(3.0f, -25)) == 0x0002);
  CHECK(f16_bits(std::ldexp(1.0f, -25) + std::ldexp(1.0f, -40)) == 0x0001);
  CHECK(f16_bits(-std::ldexp(1023.0f, -24)) == 0x83ff);
  CHECK(f16_bits(std::ldexp(2047.0f, -25)) == 0x0400);  // tie just below the smallest normal rounds up into it
  CHECK(f16_bits(from_bits32(0x00000001u)) == 0x0000);  // float subnormal underflows to zero
  CHECK(f16_bits(-0.0f) == 0x8000);
  const std::uint16_t nan = f16_bits(std::numeric_limits<float>::quiet_NaN());
  CHECK((nan & 0x7c00) == 0x7c00);
  CHECK((nan & 0x03ff) != 0);
  const std::uint16_t payload_nan = f16_bits(from_bits32(0x7f800001u));  // payload only in the low bits
  CHECK((payload_nan & 0x03ff) != 0);
}

TEST_CASE("every f16 bit pattern survives a round trip through float", "[half]") {
  int mismatches = 0;
  for (std::uint32_t b = 0; b <= 0xffff; ++b) {
    const float x = f16_value(static_cast<std::uint16_t>(b));
    if (std::isnan(x)) {
      mismatches += !std::isnan(f16_value(f16_bits(x)));
      continue;
    }
    mismatches += f16_bits(x) != b;
  }
  CHECK(mismatches == 0);
}

TEST_CASE("bf16 encodes with round-to-nearest-even and keeps NaN a NaN", "[half]") {
  CHECK(bf16_bits(1.0f) == 0x3f80);
  CHECK(bf16_bits(-2.0f) == 0xc000);
  CHECK(bf16_bits(from_bits32(0x3f808000u)) == 0x3f80);  // tie, even below
  CHECK(bf16_bits(from_bits32(0x3f818000u)) == 0x3f82);  // tie, even above
  CHECK(bf16_bits(from_bits32(0x3f808001u)) == 0x3f81);  // just above the tie
  CHECK(bf16_bits(from_bits32(0x3f807fffu)) == 0x3f80);
  CHECK(bf16_bits(from_bits32(0x7f7fffffu)) == 0x7f80);  // float max rounds to inf
  CHECK(bf16_bits(std::numeric_limits<float>::infinity()) == 0x7f80);
  CHECK(bf16_bits(-std::numeric_limits<float>::infinity()) == 0xff80);
  CHECK(bf16_bits(from_bits32(0x00018000u)) == 0x0002);  // subnormal tie rounds to even
  CHECK(bf16_bits(from_bits32(0x00008000u)) == 0x0000);
  CHECK(bf16_bits(from_bits32(0x00008001u)) == 0x0001);
  CHECK(bf16_bits(-0.0f) == 0x8000);
  const std::uint16_t nan = bf16_bits(from_bits32(0x7f800001u));  // would round to inf without the NaN guard
  CHECK(std::isnan(bf16_value(nan)));
  CHECK(std::isnan(bf16_value(bf16_bits(-std::numeric_limits<float>::quiet_NaN()))));
}

TEST_CASE("bf16 decodes known bit patterns and every pattern round-trips", "[half]") {
  CHECK(bf16_value(0x3f80) == 1.0f);
  CHECK(bf16_value(0x4049) == 3.140625f);
  CHECK(bf16_value(0x0001) == from_bits32(0x00010000u));
  CHECK(bf16_value(0x7f80) == std::numeric_limits<float>::infinity());
  CHECK(std::isnan(bf16_value(0x7fc0)));
  int mismatches = 0;
  for (std::uint32_t b = 0; b <= 0xffff; ++b) {
    const float x = bf16_value(static_cast<std::uint16_t>(b));
    if (std::isnan(x)) continue;
    mismatches += bf16_bits(x) != b;
  }
  CHECK(mismatches == 0);
}
