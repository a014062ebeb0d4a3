// Bindings of the yaw kernels: re-centred views, their phase-correlation curves and the
// real FFT along sectors (part of _core; bindings.cpp defines the module).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <complex>
#include <cstdint>
#include <limits>
#include <vector>

#include "disco/polar_resample.hpp"
#include "disco/recentre_curves.hpp"
#include "disco/recentre_places.hpp"
#include "disco/sector_fft.hpp"

#include "bindings.hpp"

namespace py = pybind11;

namespace disco_bindings {

namespace {

// Room in `room` for recentre_match's spectrum of the match, from a 64-byte boundary:
// its vectors are read once per ring block and frequency of every view, and a vector
// split across two cache lines costs about 5 % of a search's time.
float* spectrum_room(std::vector<float>& room, std::int64_t sectors, std::int64_t rings_padded) {
    room.resize(static_cast<std::size_t>(2 * (sectors / 2 + 1) * rings_padded + 16));
    const auto skip = (16 - reinterpret_cast<std::uintptr_t>(room.data()) / 4 % 16) % 16;
    return room.data() + skip;
}

}  // namespace

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
        "recentre_table",
        [](const F32& padded, std::int64_t width) {
            if (padded.ndim() != 1 || width < 2 || padded.size() % width != 0 ||
                padded.size() < 2 * width)
                throw py::value_error("padded must be a flat float32 table of rows of width");
            const std::int64_t rows = padded.size() / width;
            F32 out(static_cast<py::ssize_t>((rows - 1) * (width - 1) * 4));
            {
                py::gil_scoped_release release;
                disco::recentre_table(padded.data(), rows, width, out.mutable_data());
            }
            return out;
        },
        py::arg("padded"), py::arg("width"),
        "Each corner's four reads of a padded polar table, for recentre_curves");
    // The arguments recentre_curves and recentre_search share: the corner table, the
    // match's image and ring weights, the rings padded to whole vectors.
    auto check_curve_args = [](const F32& table, std::int64_t width, const F32& match,
                               const F32& weights, std::int64_t rings_padded) {
        if (table.ndim() != 1 || width < 2 || table.size() % (4 * (width - 1)) != 0 ||
            table.size() == 0)
            throw py::value_error("table must be recentre_table's of rows of width");
        if (match.ndim() != 2 || weights.ndim() != 1 || weights.shape(0) != match.shape(0))
            throw py::value_error("match must be float32 [R, S] and weights float32 [R]");
        const std::int64_t rings = match.shape(0), sectors = match.shape(1);
        if (rings < 1 || sectors < 1 || rings_padded < rings || rings_padded % 16 != 0)
            throw py::value_error("rings_padded must be a multiple of 16, at least R");
    };
    m.def(
        "recentre_curves",
        [check_curve_args](const F32& table, std::int64_t width, const std::vector<F32>& places,
           const F32& match, const F32& weights, std::int64_t rings_padded) {
            check_curve_args(table, width, match, weights, rings_padded);
            const std::int64_t rings = match.shape(0), sectors = match.shape(1);
            std::vector<const float*> ptrs;
            ptrs.reserve(places.size());
            for (const auto& p : places) {
                if (p.ndim() != 2 || p.shape(0) != 2 || p.shape(1) != sectors * rings)
                    throw py::value_error(
                        "each view's places must be float32 [2, sectors * rings]");
                ptrs.push_back(p.data());
            }
            const std::int64_t rows = table.size() / (4 * (width - 1)) + 1;
            const disco::RecentreImage image{table.data(), rows,    width,
                                             rings,        sectors, rings_padded};
            F32 out({static_cast<py::ssize_t>(places.size()), static_cast<py::ssize_t>(sectors)});
            {
                py::gil_scoped_release release;
                std::vector<float> room;
                float* spectrum = spectrum_room(room, sectors, rings_padded);
                disco::recentre_match(image, match.data(), spectrum);
                disco::recentre_curves(image, ptrs, spectrum, weights.data(), out.mutable_data());
            }
            return out;
        },
        py::arg("table"), py::arg("width"), py::arg("places"), py::arg("match"),
        py::arg("weights"), py::arg("rings_padded"),
        "Phase-correlation curves [views, S] of re-centred views against one match");
    m.def(
        "recentre_nccs",
        [](const F32& table, std::int64_t width, const std::vector<F32>& places,
           const F32& match, const std::vector<std::int64_t>& shifts) {
            if (table.ndim() != 1 || width < 2 || table.size() % (4 * (width - 1)) != 0 ||
                table.size() == 0)
                throw py::value_error("table must be recentre_table's of rows of width");
            if (match.ndim() != 2 || places.size() != shifts.size())
                throw py::value_error("match must be float32 [R, S], one shift per view");
            const std::int64_t rings = match.shape(0), sectors = match.shape(1);
            for (const auto& p : places)
                if (p.ndim() != 2 || p.shape(0) != 2 || p.shape(1) != sectors * rings)
                    throw py::value_error("each view's places must be float32 [2, sectors * rings]");
            const std::int64_t rows = table.size() / (4 * (width - 1)) + 1;
            const disco::RecentreImage image{table.data(), rows,    width,
                                             rings,        sectors, (rings + 15) / 16 * 16};
            std::vector<double> out(places.size());
            {
                py::gil_scoped_release release;
                std::vector<float> sectors_first(static_cast<std::size_t>(rings * sectors));
                for (std::int64_t r = 0; r < rings; ++r)
                    for (std::int64_t s = 0; s < sectors; ++s)
                        sectors_first[s * rings + r] = match.data()[r * sectors + s];
                for (std::size_t i = 0; i < places.size(); ++i)
                    out[i] = disco::recentre_ncc(image, places[i].data(), sectors_first.data(),
                                                 shifts[i]);
            }
            return out;
        },
        py::arg("table"), py::arg("width"), py::arg("places"), py::arg("match"), py::arg("shifts"),
        "Normalized correlations of views turned by -shift with the match (float64)");

    // --- the re-centring searches (yaw_refine._Views.core_searches): each round's
    // candidates, the new ones' curves (recentre_curves, GIL released) and each search's
    // best, for all of a call's searches side by side. The places come from the kept
    // places dict, else `more_places` (keys flat + key_offset); where some are in
    // neither, nothing of that round is computed and their flat indices come back, to be
    // added and asked again (the rounds before are done by then, their curves in
    // `kept`). ---
    m.def(
        "recentre_search",
        [check_curve_args](const F32& table, std::int64_t width, const py::dict& kept_places,
           const py::dict& more_places, std::int64_t key_offset, const F32& match, const F32& weights,
           std::int64_t rings_padded, py::array_t<float, py::array::c_style>& kept,
           py::array_t<std::uint8_t, py::array::c_style>& done,
           const std::vector<std::vector<std::int64_t>>& coarse,
           const std::vector<py::object>& windows, const std::vector<std::int64_t>& steps,
           const std::vector<std::int64_t>& offsets) {
            check_curve_args(table, width, match, weights, rings_padded);
            const std::int64_t rings = match.shape(0), sectors = match.shape(1);
            const std::int64_t cells = kept.ndim() == 2 ? kept.shape(0) : -1;
            if (cells < 1 || kept.shape(1) != sectors || done.ndim() != 1 ||
                done.shape(0) != cells || coarse.size() != windows.size())
                throw py::value_error("kept [L, S], done [L] and one window per search");
            const std::size_t n = coarse.size();
            std::vector<std::vector<std::int64_t>> window(n);
            for (std::size_t i = 0; i < n; ++i) {
                if (coarse[i].empty()) throw py::value_error("a search without a first grid");
                if (!windows[i].is_none())
                    window[i] = windows[i].cast<std::vector<std::int64_t>>();
                for (std::int64_t w : window[i])
                    if (w < 0 || w >= sectors) throw py::value_error("a window past the sectors");
            }
            const std::int64_t rows = table.size() / (4 * (width - 1)) + 1;
            const disco::RecentreImage image{table.data(), rows,    width,
                                             rings,        sectors, rings_padded};
            std::vector<float> room;
            float* spectrum = spectrum_room(room, sectors, rings_padded);
            disco::recentre_match(image, match.data(), spectrum);
            float* kept_rows = kept.mutable_data();
            std::uint8_t* is_done = done.mutable_data();
            std::vector<std::int64_t> best(n);
            std::vector<double> value(n, -std::numeric_limits<double>::infinity());
            for (std::size_t i = 0; i < n; ++i) best[i] = coarse[i][0];
            for (std::size_t round = 0; round <= steps.size(); ++round) {
                std::vector<std::vector<std::int64_t>> cand(n);
                for (std::size_t i = 0; i < n; ++i) {
                    if (round == 0) {
                        cand[i] = coarse[i];
                    } else {
                        for (std::int64_t d : offsets)
                            cand[i].push_back(best[i] + d * steps[round - 1]);
                    }
                    for (std::int64_t f : cand[i])
                        if (f < 0 || f >= cells) throw py::value_error("a search left the lattice");
                }
                std::vector<std::int64_t> fresh, missing;
                std::vector<F32> arrays;
                std::vector<std::uint8_t> seen(static_cast<std::size_t>(cells), 0);
                for (const auto& c : cand)
                    for (std::int64_t f : c) {
                        if (is_done[f] || seen[f]) continue;
                        seen[f] = 1;
                        const py::int_ key(f + key_offset);
                        PyObject* p = PyDict_GetItem(kept_places.ptr(), key.ptr());
                        if (p == nullptr) p = PyDict_GetItem(more_places.ptr(), key.ptr());
                        if (p == nullptr) {
                            missing.push_back(f);
                            continue;
                        }
                        auto a = py::reinterpret_borrow<py::object>(p).cast<F32>();
                        if (a.ndim() != 2 || a.shape(0) != 2 || a.shape(1) != sectors * rings)
                            throw py::value_error(
                                "each view's places must be float32 [2, sectors * rings]");
                        fresh.push_back(f);
                        arrays.push_back(std::move(a));
                    }
                if (!missing.empty())
                    return py::tuple(py::make_tuple(py::cast(missing), py::list()));
                if (!fresh.empty()) {
                    std::vector<const float*> ptrs;
                    for (const auto& a : arrays) ptrs.push_back(a.data());
                    std::vector<float> out(fresh.size() * static_cast<std::size_t>(sectors));
                    {
                        py::gil_scoped_release release;
                        disco::recentre_curves(image, ptrs, spectrum, weights.data(), out.data());
                    }
                    for (std::size_t j = 0; j < fresh.size(); ++j) {
                        std::copy(out.begin() + static_cast<std::ptrdiff_t>(j * sectors),
                                  out.begin() + static_cast<std::ptrdiff_t>((j + 1) * sectors),
                                  kept_rows + fresh[j] * sectors);
                        is_done[fresh[j]] = 1;
                    }
                }
                // Each search's best: the highest peak (in its window), the first of equals.
                for (std::size_t i = 0; i < n; ++i)
                    for (std::int64_t f : cand[i]) {
                        const float* curve = kept_rows + f * sectors;
                        float peak = -std::numeric_limits<float>::infinity();
                        if (window[i].empty()) {
                            for (std::int64_t s = 0; s < sectors; ++s) peak = std::max(peak, curve[s]);
                        } else {
                            for (std::int64_t s : window[i]) peak = std::max(peak, curve[s]);
                        }
                        if (static_cast<double>(peak) > value[i]) best[i] = f, value[i] = peak;
                    }
            }
            py::list found;
            for (std::size_t i = 0; i < n; ++i) found.append(py::make_tuple(best[i], value[i]));
            return py::tuple(py::make_tuple(py::list(), found));
        },
        py::arg("table"), py::arg("width"), py::arg("kept_places"), py::arg("more_places"),
        py::arg("key_offset"),
        py::arg("match"), py::arg("weights"), py::arg("rings_padded"),
        py::arg("kept").noconvert(), py::arg("done").noconvert(), py::arg("coarse"), py::arg("windows"), py::arg("steps"),
        py::arg("offsets"), "The re-centring searches' rounds: (missing places, best per search)");

    // --- where each re-centred view reads (src/cpp/disco/recentre_places.*) ---
    m.def(
        "recentre_places",
        [](const F32& x, const F32& y, const F32& positions, float ring_scale, float ring_cap,
           float sector_scale, float sector_shift) {
            if (x.ndim() != 1 || y.ndim() != 1 || x.shape(0) != y.shape(0) || x.shape(0) < 1)
                throw py::value_error("x and y must be float32 [cells], the same length");
            if (positions.ndim() != 2 || positions.shape(1) != 2)
                throw py::value_error("positions must be float32 [M, 2]");
            const disco::PlacesGrid grid{x.data(), y.data(), x.shape(0), ring_scale,
                                         ring_cap, sector_scale, sector_shift};
            F32 out({positions.shape(0), static_cast<py::ssize_t>(2), x.shape(0)});
            {
                py::gil_scoped_release release;
                disco::recentre_places(grid, positions.data(), positions.shape(0),
                                       out.mutable_data());
            }
            return out;
        },
        py::arg("x"), py::arg("y"), py::arg("positions"), py::arg("ring_scale"),
        py::arg("ring_cap"), py::arg("sector_scale"), py::arg("sector_shift"),
        "Each cell's fractional ring and sector [M, 2, cells] from positions [M, 2]");
}

}  // namespace disco_bindings
