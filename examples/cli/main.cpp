// flexsplat command-line program: one binary, subcommands registered by the files beside this one.
#include <cstdio>
#include <exception>

#include "registry.hpp"

int main(int argc, char** argv) {
  using namespace flexsplat::cli;
  auto usage = [] {
    std::fprintf(stderr, "usage: flexsplat <command> [args...]\ncommands:\n");
    for (auto& [name, cmd] : commands()) std::fprintf(stderr, "  %-16s %s\n", name.c_str(), cmd.summary.c_str());
  };
  if (argc < 2 || std::string(argv[1]) == "-h" || std::string(argv[1]) == "--help") {
    usage();
    return argc < 2 ? 2 : 0;
  }
  auto it = commands().find(argv[1]);
  if (it == commands().end()) {
    std::fprintf(stderr, "flexsplat: unknown command '%s'\n", argv[1]);
    usage();
    return 2;
  }
  Args args(argv + 2, argv + argc);
  if (!args.empty() && (args[0] == "-h" || args[0] == "--help")) {
    std::fprintf(stderr, "usage: flexsplat %s %s\n%s\n", argv[1], it->second.usage.c_str(), it->second.summary.c_str());
    return 0;
  }
  try {
    return it->second.run(args);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "flexsplat %s: error: %s\n", argv[1], e.what());
    return 1;
  }
}
