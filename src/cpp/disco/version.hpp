#pragma once

namespace disco {
// The C++ core's own version string (set from pyproject.toml by CMake).
const char* core_version();
}  // namespace disco
