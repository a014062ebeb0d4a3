// Bindings of the yaw kernels: re-centred views, their phase-correlation curves and the
// real FFT along sectors (part of _core; bindings.cpp defines the module).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <complex>
#include <cstdint>
#include <vector>

#include "disco/polar_resample.hpp"
#include "disco/recentre_curves.hpp"
#include "disco/sector_fft.hpp"

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
    // --- the real FFT along sectors (src/cpp/disco/sector_fft.*) ---
    m.def(
        "sector_rfft",
        [](const F32& x) {
            if (x.ndim() < 1 || x.shape(x.ndim() - 1) < 1)
                throw py::value_error("sector_rfft: x must be float32 [..., n], n >= 1");
            const std::int64_t n = x.shape(x.ndim() - 1), rows = x.size() / n;
            std::vector<py::ssize_t> shape(x.shape(), x.shape() + x.ndim());
            shape.back() = n / 2 + 1;
            py::array_t<std::complex<float>> out(shape);
            {
                py::gil_scoped_release release;
                disco::rfft_rows(x.data(), rows, n,
                                 reinterpret_cast<float*>(out.mutable_data()));
            }
            return out;
        },
        py::arg("x"), "numpy.fft.rfft(x, axis=-1) of float32 rows, in float32 (complex64)");
    m.def(
        "sector_irfft",
        [](const py::array_t<std::complex<float>, py::array::c_style>& x, std::int64_t n) {
            if (x.ndim() < 1 || n < 1 || x.shape(x.ndim() - 1) != n / 2 + 1)
                throw py::value_error("sector_irfft: x must be complex64 [..., n // 2 + 1]");
            const std::int64_t rows = x.size() / (n / 2 + 1);
            std::vector<py::ssize_t> shape(x.shape(), x.shape() + x.ndim());
            shape.back() = static_cast<py::ssize_t>(n);
            F32 out(shape);
            {
                py::gil_scoped_release release;
                disco::irfft_rows(reinterpret_cast<const float*>(x.data()), rows, n,
                                  out.mutable_data());
            }
            return out;
        },
        py::arg("x"), py::arg("n"), "numpy.fft.irfft(x, n, axis=-1) of complex64 rows, in float32");

    // --- phase-correlation curves of re-centred views (src/cpp/disco/recentre_curves.*) ---
    m.def(
        "recentre_curves",
        [](const F32& padded, std::int64_t width, const std::vector<F32>& places,
           const F32& match, const F32& weights, std::int64_t rings_padded) {
            if (padded.ndim() != 1 || width < 2 || padded.size() < 2 * width)
                throw py::value_error("padded must be a flat float32 table of rows of width");
            if (match.ndim() != 2 || weights.ndim() != 1 || weights.shape(0) != match.shape(0))
                throw py::value_error("match must be float32 [R, S] and weights float32 [R]");
            const std::int64_t rings = match.shape(0), sectors = match.shape(1);
            if (rings < 1 || sectors < 1 || rings_padded < rings || rings_padded % 16 != 0)
                throw py::value_error("rings_padded must be a multiple of 16, at least R");
            std::vector<const float*> ptrs;
            ptrs.reserve(places.size());
            for (const auto& p : places) {
                if (p.ndim() != 2 || p.shape(0) != 2 || p.shape(1) != sectors * rings_padded)
                    throw py::value_error(
                        "each view's places must be float32 [2, sectors * rings_padded]");
                ptrs.push_back(p.data());
            }
            const disco::RecentreImage image{padded.data(), padded.size(), width,
                                             rings,         sectors,       rings_padded};
            F32 out({static_cast<py::ssize_t>(places.size()), static_cast<py::ssize_t>(sectors)});
            {
                py::gil_scoped_release release;
                disco::recentre_curves(image, ptrs, match.data(), weights.data(),
                                       out.mutable_data());
            }
            return out;
        },
        py::arg("padded"), py::arg("width"), py::arg("places"), py::arg("match"),
        py::arg("weights"), py::arg("rings_padded"),
        "Phase-correlation curves [views, S] of re-centred views against one match");
}

}  // namespace disco_bindings
