// check-reference: dispatches each bundle on its __metadata__.kind to the checker a module registered.
#include <cstdio>

#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int check_reference(Args args) {
  // --rows N: each bundle must compare exactly N tensors, so that a checker that silently skips some cannot pass.
  std::string rows_text;
  const long long rows = take_option(args, "--rows", rows_text) ? parse_integer(rows_text, "--rows", 1, 1000000) : 0;
  require(!args.empty(), "check-reference needs at least one .safetensors bundle");
  int failures = 0;
  for (const auto& path : args) {
    try {
      const auto file = safetensors::File::open(path);
      require(file.has_metadata("kind"), "bundle '", path, "' has no __metadata__.kind");
      const std::string kind = file.metadata("kind");
      auto it = checkers().find(kind);
      if (it == checkers().end()) {
        std::string known;
        for (auto& [k, c] : checkers()) known += (known.empty() ? "" : ", ") + k;
        fail("bundle '", path, "' has unknown kind '", kind, "' (known kinds: ", known, ")");
      }
      ReferenceReport report;
      report.file = path;
      report.kind = kind;
      it->second(file, report);
      report.print(stdout);
      const bool count_ok = rows == 0 || static_cast<long long>(report.rows.size()) == rows;
      if (!count_ok)
        std::printf("%s: compared %zu tensors, expected %lld (--rows)\n", path.c_str(), report.rows.size(), rows);
      const bool pass = report.all_pass() && count_ok;
      std::printf("%s: %s\n", path.c_str(), pass ? "PASS" : "FAIL");
      if (!pass) ++failures;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "check-reference: FAIL: %s\n", e.what());
      ++failures;
    }
  }
  return failures == 0 ? 0 : 1;
}

const RegisterCommand registered_cmd_check_reference("check-reference",
                                 {"compare the library against golden reference bundles (by __metadata__.kind)",
                                  "[--rows N] BUNDLE.safetensors...", check_reference});

}  // namespace
}  // namespace flexsplat::cli
