#pragma once
// Small per-element helpers called from hot loops: GCC's size heuristics otherwise leave 3x3 products as calls
// that pass every matrix through memory.
#if defined(__GNUC__)
#define FLEXSPLAT_ALWAYS_INLINE [[gnu::always_inline]] inline
#else
#define FLEXSPLAT_ALWAYS_INLINE inline
#endif
