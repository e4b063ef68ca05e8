#pragma once
// Exceptions that name the offending file, tensor, shape or value. require() evaluates its message parts eagerly:
// in hot paths write `if (!cond) fail(...)` so nothing is formatted when the check passes.
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>

namespace flexsplat {
inline namespace v0 {

class Error : public std::runtime_error {
public:
  using std::runtime_error::runtime_error;
};

template <class... Parts>
std::string concat(Parts&&... parts) {
  std::ostringstream out;
  (out << ... << std::forward<Parts>(parts));
  return out.str();
}

template <class... Parts>
[[noreturn]] void fail(Parts&&... parts) {
  throw Error(concat(std::forward<Parts>(parts)...));
}

// An error about one file or named source: "'source': parts".
template <class... Parts>
[[noreturn]] void fail_in(const std::string& source, Parts&&... parts) {
  fail("'", source, "': ", std::forward<Parts>(parts)...);
}

template <class... Parts>
void require(bool condition, Parts&&... parts) {
  if (!condition) fail(std::forward<Parts>(parts)...);
}

}  // namespace v0
}  // namespace flexsplat
