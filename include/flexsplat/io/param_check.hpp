#pragma once
// One error that lists every problem of a parameter set at once: missing tensors, tensors of the wrong shape, and
// tensors in the file under a module's prefix that no expected parameter names.
#include <set>
#include <string>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/io/param_source.hpp"

namespace flexsplat {
inline namespace v0 {
namespace io {

// The problems found in a parameter set, raised as one error that lists them all (one line per tensor).
struct ParamProblems {
  std::vector<std::string> general, missing, misshaped, unexpected;

  // Returns when there is nothing to list; else fails with `header`, then the general problems and each list.
  void raise(const std::string& header, const char* misshaped_title = "with the wrong shape") const {
    if (general.empty() && missing.empty() && misshaped.empty() && unexpected.empty()) return;
    std::string message = header;
    for (const auto& p : general) message += "\n  " + p;
    auto list = [&](const char* title, const std::vector<std::string>& items) {
      if (items.empty()) return;
      message += concat("\n  ", items.size(), " ", title, ":");
      for (const auto& item : items) message += "\n    " + item;
    };
    list("missing", missing);
    list(misshaped_title, misshaped);
    list("unexpected", unexpected);
    fail(message);
  }
};

// owned_prefixes: name prefixes (before the source's file prefix, e.g. "camera_head.") whose every file tensor must
// be among `specs`; empty to skip the unexpected-tensor check.
template <class T>
void check_parameters(const ParamSource<T>& src, const std::vector<TensorSpec>& specs,
                      const std::vector<std::string>& owned_prefixes, const std::string& what) {
  ParamProblems found;
  auto &missing = found.missing, &misshaped = found.misshaped, &unexpected = found.unexpected;
  std::set<std::string> expected;
  for (const auto& s : specs) {
    expected.insert(s.name);
    if (!src.contains(s.name)) {
      missing.push_back(src.prefix() + s.name + " " + safetensors::shape_string(s.shape));
      continue;
    }
    const auto have = src.shape(s.name);
    if (have != s.shape)
      misshaped.push_back(src.prefix() + s.name + " is " + safetensors::shape_string(have) + ", expected " +
                          safetensors::shape_string(s.shape));
  }
  if (src.has_file() && !owned_prefixes.empty()) {
    const std::string& fp = src.prefix();
    for (const auto& t : src.file().tensors()) {
      if (t.name.compare(0, fp.size(), fp) != 0) continue;
      const std::string name = t.name.substr(fp.size());
      for (const auto& owned : owned_prefixes)
        if (name.compare(0, owned.size(), owned) == 0 && !expected.count(name)) {
          unexpected.push_back(t.name + " " + safetensors::shape_string(t.shape));
          break;
        }
    }
  }
  found.raise(what + " parameters from " + src.describe() + " do not match the configuration:");
}

}  // namespace io
}  // namespace v0
}  // namespace flexsplat
