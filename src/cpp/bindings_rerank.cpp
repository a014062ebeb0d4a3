// Bindings of the re-ranking's correlations along sectors: the aligned correlations of
// query images with candidates and the plain yaw's phase-correlation curves (part of
// _core; bindings.cpp defines the module).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>

#include "disco/sector_correlation.hpp"

#include "bindings.hpp"

namespace py = pybind11;

namespace disco_bindings {

// --- src/cpp/disco/sector_correlation.* ---
void add_rerank(py::module_& m) {
    using F32 = py::array_t<float, py::array::c_style | py::array::forcecast>;
    m.def(
        "aligned_correlations",
        [](const F32& queries, const F32& candidates) {
            if (queries.ndim() != 3 || candidates.ndim() != 3 ||
                queries.shape(1) != candidates.shape(1) ||
                queries.shape(2) != candidates.shape(2) || queries.shape(1) < 1 ||
                queries.shape(2) < 1)
                throw py::value_error(
                    "aligned_correlations: queries [V, R, S] and candidates [K, R, S], "
                    "R, S >= 1");
            const std::int64_t views = queries.shape(0), count = candidates.shape(0);
            F32 out({static_cast<py::ssize_t>(views), static_cast<py::ssize_t>(count)});
            {
                py::gil_scoped_release release;
                disco::aligned_correlations(queries.data(), views, candidates.data(), count,
                                            queries.shape(1), queries.shape(2),
                                            out.mutable_data());
            }
            return out;
        },
        py::arg("queries"), py::arg("candidates"),
        "Peak centred circular cross-correlations [V, K] along sectors, / the norms");
    m.def(
        "yaw_curves",
        [](const F32& query, const F32& matches, const F32& weights) {
            if (query.ndim() != 2 || matches.ndim() != 3 || matches.shape(1) != query.shape(0) ||
                matches.shape(2) != query.shape(1) || query.shape(0) < 1 ||
                query.shape(1) < 1 || weights.ndim() != 1 || weights.shape(0) != query.shape(0))
                throw py::value_error(
                    "yaw_curves: query [R, S], matches [K, R, S] and weights [R], R, S >= 1");
            const std::int64_t count = matches.shape(0), sectors = query.shape(1);
            F32 out({static_cast<py::ssize_t>(count), static_cast<py::ssize_t>(sectors)});
            {
                py::gil_scoped_release release;
                disco::yaw_curves(query.data(), matches.data(), count, query.shape(0), sectors,
                                  weights.data(), out.mutable_data());
            }
            return out;
        },
        py::arg("query"), py::arg("matches"), py::arg("weights"),
        "Whitened phase-correlation curves [K, S] of query [R, S] against matches [K, R, S]");
}

}  // namespace disco_bindings
