#pragma once
// Explicit instantiation of the library's heavy float/double entry points for the project's own executables:
// CMake force-includes src/instances/<name>.hpp (extern declarations) into every test, example, benchmark and the
// command-line program whose sources reach the library headers it names, and links the flexsplat_instances static
// library (src/instances/<name>.cpp, the definitions), so each template body is compiled once per build instead of
// once per executable. Not installed: consumers of flexsplat::flexsplat still instantiate everything header-only.
// decltype(f<T>) spells the specialization's type, so no signature is repeated here.
#define FLEXSPLAT_EXTERN_INSTANCE(f, T) extern template decltype(f<T>) f<T>;
#define FLEXSPLAT_INSTANCE(f, T) template decltype(f<T>) f<T>;
