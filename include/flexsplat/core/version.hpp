#pragma once
// Library version; the inline namespace v0 changes with the ABI.
namespace flexsplat {
inline namespace v0 {
inline constexpr int version_major = 0;
inline constexpr int version_minor = 1;
inline constexpr int version_patch = 0;
inline constexpr const char* version_string = "0.1.0";
}  // namespace v0
}  // namespace flexsplat
