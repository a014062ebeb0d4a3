// Bindings of the yaw kernels: re-centred views (part of _core; bindings.cpp defines the module).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdint>
#include <vector>

#include "disco/polar_resample.hpp"

#include "bindings.hpp"

namespace py = pybind11;

namespace disco_bindings {

// --- re-centred views of a polar image (src/cpp/disco/polar_resample.*) ---
void add_yaw(py::module_& m) {
    using F32 = py::array_t<float, py::array::c_style>;
    m.def(
        "resample_views",
        [](const F32& padded, std::int64_t width, const std::vector<F32>& places,
           std::int64_t cells) {
            if (padded.ndim() != 1 || width < 1 || cells < 0)
                throw py::value_error("padded must be a flat float32 image, width >= 1");
            std::vector<disco::ResamplePlaces> ptrs;
            ptrs.reserve(places.size());
            for (const auto& p : places) {
                if (p.ndim() != 2 || p.shape(0) != 2 || p.shape(1) != cells)
                    throw py::value_error("each view's places must be float32 [2, cells]");
                ptrs.push_back(p.data());
            }
            py::array_t<float> out({static_cast<py::ssize_t>(places.size()),
                                    static_cast<py::ssize_t>(cells)});
            {
                py::gil_scoped_release release;
                disco::resample_views(padded.data(), padded.size(), width, ptrs, cells,
                                      out.mutable_data());
            }
            return out;
        },
        py::arg("padded"), py::arg("width"), py::arg("places"), py::arg("cells"),
        "Bilinear reads [views, cells] of a padded polar image at precomputed places");
}

}  // namespace disco_bindings
