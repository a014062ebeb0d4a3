#include "disco/version.hpp"

namespace disco {
const char* core_version() { return DISCO_VERSION; }
}  // namespace disco
