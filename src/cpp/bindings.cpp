// The one pybind11 file: turns the plain C++ library in src/cpp/disco/ into the
// private module disco_cli._core. Users never import _core; the Python wrappers
// (disco_cli.bev, ...) check shapes and dtypes and call it.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "disco/version.hpp"

namespace py = pybind11;

PYBIND11_MODULE(_core, m) {
    m.doc() = "disco's compiled core (private; use the disco_cli package)";
    m.attr("__version__") = disco::core_version();

    // --- polar BEV voxelizer (src/cpp/disco/polar_bev.*) ---

    // --- simulator ray casting (src/cpp/disco/raycast.*) ---

    // --- relative pose: ICP (src/cpp/disco/icp.*) ---
}
