// The _core module's bindings, split by area so that each area's kernels register from
// a file of its own (bindings.cpp defines the module and calls these).
#pragma once

#include <pybind11/pybind11.h>

namespace disco_bindings {

void add_search(pybind11::module_& m);  // bindings_search.cpp: signature search
void add_yaw(pybind11::module_& m);     // bindings_yaw.cpp: yaw and re-centred views
void add_rerank(pybind11::module_& m);  // bindings_rerank.cpp: re-ranking correlations

}  // namespace disco_bindings
