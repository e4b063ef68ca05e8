#pragma once
// Subcommands and reference-bundle checkers register themselves from their own .cpp files.
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat::cli {

using Args = std::vector<std::string>;

struct Command {
  std::string summary;
  std::string usage;
  std::function<int(const Args&)> run;
};

inline std::map<std::string, Command>& commands() {
  static std::map<std::string, Command> table;
  return table;
}

struct RegisterCommand {
  RegisterCommand(const std::string& name, Command command) { commands()[name] = std::move(command); }
};

// A checker runs the library on a bundle's inputs and fills one comparison row per output tensor.
using Checker = std::function<void(const safetensors::File&, ReferenceReport&)>;

inline std::map<std::string, Checker>& checkers() {
  static std::map<std::string, Checker> table;
  return table;
}

struct RegisterChecker {
  RegisterChecker(const std::string& kind, Checker checker) { checkers()[kind] = std::move(checker); }
};

// Small argument helpers shared by subcommands.
inline bool take_flag(Args& args, const std::string& flag) {
  for (auto it = args.begin(); it != args.end(); ++it)
    if (*it == flag) {
      args.erase(it);
      return true;
    }
  return false;
}

inline bool take_option(Args& args, const std::string& flag, std::string& value) {
  for (auto it = args.begin(); it != args.end(); ++it)
    if (*it == flag) {
      require(std::next(it) != args.end(), "option ", flag, " needs a value");
      value = *std::next(it);
      args.erase(it, it + 2);
      return true;
    }
  return false;
}

// Numeric option values: the whole text must parse, and a bad one names the option and the text.
inline long long parse_integer(const std::string& text, const std::string& flag, long long lo, long long hi) {
  std::size_t used = 0;
  long long v = 0;
  try {
    v = std::stoll(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  require(used == text.size() && !text.empty() && v >= lo && v <= hi, flag, " '", text, "': expected an integer in [",
          lo, ", ", hi, "]");
  return v;
}

inline std::uint64_t parse_seed(const std::string& text, const std::string& flag) {
  std::size_t used = 0;
  unsigned long long v = 0;
  try {
    v = std::stoull(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  // stoull accepts "-1" as 2^64 - 1.
  require(used == text.size() && !text.empty() && text[0] != '-', flag, " '", text,
          "': expected an integer in [0, 2^64)");
  return v;
}

// A positive (or, with allow_zero, non-negative) finite number.
inline double parse_number(const std::string& text, const std::string& flag, bool allow_zero) {
  std::size_t used = 0;
  double v = NAN;
  try {
    v = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  require(used == text.size() && std::isfinite(v) && (v > 0 || (allow_zero && v == 0)), flag, " '", text,
          "' must be a ", allow_zero ? "non-negative" : "positive", " number");
  return v;
}

// A picture size given as its longer side: "native" or empty is 0 (the photos' own resolution), else 1 to 16384.
inline long long parse_longer_side(const std::string& text, const std::string& flag) {
  return text.empty() || text == "native" ? 0 : parse_integer(text, flag, 1, 16384);
}

// A Gaussian count: `fallback` when empty, else 0 to 2^24.
inline long long parse_gaussian_count(const std::string& text, const std::string& flag, long long fallback) {
  return text.empty() ? fallback : parse_integer(text, flag, 0, 1 << 24);
}

inline bool parse_on_off(const std::string& text, const std::string& flag) {
  require(text == "on" || text == "off", flag, " '", text, "': expected on or off");
  return text == "on";
}

// --model when given, else the shipped model (FLEXSPLAT_DEFAULT_MODEL, set by examples/CMakeLists.txt), which must exist.
// With `posed` (the photos' cameras given) the default is the model trained on given cameras, else the rig's.
inline std::string model_or_default(const std::string& given, bool posed = false) {
  if (!given.empty()) return given;
#if defined(FLEXSPLAT_DEFAULT_MODEL) && defined(FLEXSPLAT_DEFAULT_POSED_MODEL)
  const std::string path = posed ? FLEXSPLAT_DEFAULT_POSED_MODEL : FLEXSPLAT_DEFAULT_MODEL;
#else
  const std::string path = posed ? "models/flexsplat-posed.safetensors" : "models/flexsplat-small.safetensors";
#endif
  require(std::filesystem::exists(path), "no shipped model yet at '", path, "'; pass --model");
  return path;
}

}  // namespace flexsplat::cli
