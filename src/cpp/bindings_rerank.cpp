// Bindings of the re-ranking's correlations along sectors: the aligned correlations of
// query images with candidates and the plain yaw's phase-correlation curves, yaws and
// confidences (part of _core; bindings.cpp defines the module).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <utility>
#include <vector>

#include "disco/sector_correlation.hpp"

#include "bindings.hpp"

namespace py = pybind11;

namespace disco_bindings {

namespace {

using F32 = py::array_t<float, py::array::c_style | py::array::forcecast>;
using F32Any = py::array_t<float, py::array::forcecast>;

// Images [K, R, S] whose rows are whole and contiguous, each image's rows one after
// another (one channel of [K, C, R, S] features is): kept as they are, with the floats
// from one image to the next; anything else copied into a C-contiguous array.
struct Images {
    F32Any array;
    std::int64_t stride;
};

Images images_of(const F32Any& a, const char* what) {
    if (a.ndim() != 3) throw py::value_error(std::string(what) + " must be [K, R, S]");
    const py::ssize_t f = static_cast<py::ssize_t>(sizeof(float));
    if (a.strides(2) == f && a.strides(1) == a.shape(2) * f && a.strides(0) >= 0 &&
        a.strides(0) % f == 0)
        return {a, a.strides(0) / f};
    F32 copy = F32::ensure(a);
    return {copy, a.shape(1) * a.shape(2)};
}

}  // namespace

// --- src/cpp/disco/sector_correlation.* ---
void add_rerank(py::module_& m) {
    m.def(
        "aligned_correlations",
        [](const F32& queries, const F32Any& candidates_in) {
            const Images c = images_of(candidates_in, "aligned_correlations: candidates");
            if (queries.ndim() != 3 || queries.shape(1) != c.array.shape(1) ||
                queries.shape(2) != c.array.shape(2) || queries.shape(1) < 1 ||
                queries.shape(2) < 1)
                throw py::value_error(
                    "aligned_correlations: queries [V, R, S] and candidates [K, R, S], "
                    "R, S >= 1");
            const std::int64_t views = queries.shape(0), count = c.array.shape(0);
            F32 out({static_cast<py::ssize_t>(views), static_cast<py::ssize_t>(count)});
            {
                py::gil_scoped_release release;
                disco::aligned_correlations(queries.data(), views, c.array.data(), count,
                                            c.stride, queries.shape(1), queries.shape(2),
                                            out.mutable_data());
            }
            return out;
        },
        py::arg("queries"), py::arg("candidates"),
        "Peak centred circular cross-correlations [V, K] along sectors, / the norms");

    m.def(
        "aligned_correlations_at",
        [](const F32& queries, const py::sequence& candidates) {
            if (queries.ndim() != 3 || queries.shape(1) < 1 || queries.shape(2) < 1)
                throw py::value_error("aligned_correlations_at: queries [V, R, S], R, S >= 1");
            const auto rings = queries.shape(1), sectors = queries.shape(2);
            // Each candidate read where it lies when its rows are contiguous (a channel of
            // a cached row's features is), else from a contiguous copy kept here.
            std::vector<F32Any> held;
            std::vector<const float*> table;
            held.reserve(candidates.size());
            table.reserve(candidates.size());
            for (const auto& item : candidates) {
                F32Any image = F32Any::ensure(item);
                if (!image || image.ndim() != 2 || image.shape(0) != rings ||
                    image.shape(1) != sectors)
                    throw py::value_error(
                        "aligned_correlations_at: every candidate must be [R, S] like the "
                        "queries");
                if (image.strides(1) != sizeof(float) ||
                    image.strides(0) != sectors * static_cast<py::ssize_t>(sizeof(float)))
                    image = F32::ensure(image);
                table.push_back(image.data());
                held.push_back(std::move(image));
            }
            const auto views = queries.shape(0);
            const auto count = static_cast<py::ssize_t>(table.size());
            F32 out({views, count});
            {
                py::gil_scoped_release release;
                disco::aligned_correlations_at(queries.data(), views, table.data(), count, rings,
                                               sectors, out.mutable_data());
            }
            return out;
        },
        py::arg("queries"), py::arg("candidates"),
        "aligned_correlations of candidates given one by one ([R, S] images), read in place");

    // The yaw kernels' arguments checked: query [R, S], matches [K, R, S], weights [R].
    auto checked = [](const F32& query, const F32Any& matches_in, const F32& weights) {
        const Images m = images_of(matches_in, "yaw: matches");
        if (query.ndim() != 2 || m.array.shape(1) != query.shape(0) ||
            m.array.shape(2) != query.shape(1) || query.shape(0) < 1 || query.shape(1) < 1 ||
            weights.ndim() != 1 || weights.shape(0) != query.shape(0))
            throw py::value_error(
                "yaw: query [R, S], matches [K, R, S] and weights [R], R, S >= 1");
        return m;
    };
    m.def(
        "yaw_curves",
        [checked](const F32& query, const F32Any& matches, const F32& weights) {
            const Images mi = checked(query, matches, weights);
            const std::int64_t count = mi.array.shape(0), sectors = query.shape(1);
            F32 out({static_cast<py::ssize_t>(count), static_cast<py::ssize_t>(sectors)});
            {
                py::gil_scoped_release release;
                disco::yaw_curves(query.data(), mi.array.data(), count, mi.stride,
                                  query.shape(0), sectors, weights.data(), out.mutable_data());
            }
            return out;
        },
        py::arg("query"), py::arg("matches"), py::arg("weights"),
        "Whitened phase-correlation curves [K, S] of query [R, S] against matches [K, R, S]");
    m.def(
        "yaw_conf",
        [checked](const F32& query, const F32Any& matches, const F32& weights,
                  std::int64_t separation) {
            const Images mi = checked(query, matches, weights);
            if (separation < 0) throw py::value_error("yaw_conf: separation must be >= 0");
            const std::int64_t count = mi.array.shape(0);
            F32 yaws(static_cast<py::ssize_t>(count)), confs(static_cast<py::ssize_t>(count));
            {
                py::gil_scoped_release release;
                disco::yaw_conf(query.data(), mi.array.data(), count, mi.stride, query.shape(0),
                                query.shape(1), weights.data(), separation,
                                yaws.mutable_data(), confs.mutable_data());
            }
            return py::make_tuple(yaws, confs);
        },
        py::arg("query"), py::arg("matches"), py::arg("weights"), py::arg("separation"),
        "(yaw [K] in degrees, confidence [K]) of yaw_curves' curves (yaw.estimate_yaw_conf)");
}

}  // namespace disco_bindings
