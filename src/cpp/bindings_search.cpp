// Bindings of the signature search kernels (part of _core; bindings.cpp defines the module).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <cstdint>
#include <optional>
#include <vector>

#include "disco/exact_search.hpp"
#include "disco/int8_search.hpp"
#include "disco/projected_search.hpp"
#include "disco/row_selection.hpp"

#include "bindings.hpp"

namespace py = pybind11;

namespace disco_bindings {

// --- signature search: int8 first pass (src/cpp/disco/int8_search.*) ---
void add_search(py::module_& m) {
    // The Python wrapper (disco_cli.search) builds the codes and per-row tables once
    // and passes C-contiguous arrays of the right dtypes; checked again here.
    using I8 = py::array_t<std::int8_t, py::array::c_style>;
    using I16 = py::array_t<std::int16_t, py::array::c_style>;
    using F64 = py::array_t<double, py::array::c_style>;
    auto rows_of = [](const I8& codes, const F64& code_sq, const F64& code_norm,
                      const F64& err) {
        if (codes.ndim() != 2) throw py::value_error("codes must be [n, d] int8");
        const auto n = codes.shape(0);
        if (code_sq.size() != n || code_norm.size() != n || err.size() != n)
            throw py::value_error("code_sq, code_norm and err must have n entries");
        disco::Int8Rows rows;
        rows.codes = codes.data();
        rows.n = n;
        rows.d = codes.shape(1);
        rows.code_sq = code_sq.data();
        rows.code_norm = code_norm.data();
        rows.err = err.data();
        return rows;
    };
    m.def(
        "int8_candidates",
        [rows_of](const I8& codes, const F64& code_sq, const F64& code_norm, const F64& err,
                  const py::array_t<float, py::array::c_style>& q, const F64& offset,
                  const F64& scale, int k, std::int64_t limit,
                  std::optional<py::array_t<std::uint8_t, py::array::c_style>> exclude,
                  int threads) {
            const disco::Int8Rows rows = rows_of(codes, code_sq, code_norm, err);
            if (q.ndim() != 1 || q.shape(0) != rows.d || offset.size() != rows.d ||
                scale.size() != rows.d)
                throw py::value_error("q [d] float32, offset and scale [d] float64");
            const std::uint8_t* ex = nullptr;
            if (exclude) {
                if (exclude->size() < std::min<std::int64_t>(limit, rows.n))
                    throw py::value_error("exclude must cover the rows searched");
                ex = exclude->data();
            }
            std::vector<std::int64_t> out;
            {
                py::gil_scoped_release release;
                std::vector<std::int16_t> g(static_cast<std::size_t>(rows.d));
                const disco::Int8Query query =
                    disco::int8_query(q.data(), offset.data(), scale.data(), rows.d,
                                      disco::int8_query_limit(rows.d), g.data());
                out = disco::int8_candidates(rows, query, k, limit, ex, threads);
            }
            return py::array_t<std::int64_t>(static_cast<py::ssize_t>(out.size()), out.data());
        },
        py::arg("codes"), py::arg("code_sq"), py::arg("code_norm"), py::arg("err"), py::arg("q"),
        py::arg("offset"), py::arg("scale"), py::arg("k"), py::arg("limit"),
        py::arg("exclude") = py::none(), py::arg("threads") = 1,
        "Rows whose distance lower bound (codes x ~ offset + scale * c) is at most the k-th "
        "smallest upper bound");
    m.def(
        "int8_dots",
        [](const I8& codes, const I16& g, int threads) {
            if (codes.ndim() != 2 || g.ndim() != 1 || g.shape(0) != codes.shape(1))
                throw py::value_error("codes must be [n, d] int8 and g [d] int16");
            disco::Int8Rows rows;
            rows.codes = codes.data();
            rows.n = codes.shape(0);
            rows.d = codes.shape(1);
            std::vector<std::int32_t> out;
            {
                py::gil_scoped_release release;
                out = disco::int8_dots(rows, g.data(), threads);
            }
            return py::array_t<std::int32_t>(static_cast<py::ssize_t>(out.size()), out.data());
        },
        py::arg("codes"), py::arg("g"), py::arg("threads") = 1, "g . c for every row (int32)");
    m.def(
        "int8_encode",
        [](const py::array_t<float, py::array::c_style>& x, const F64& mean, const F64& scale,
           int threads) {
            if (x.ndim() != 2) throw py::value_error("x must be [n, d] float32");
            const auto n = x.shape(0), d = x.shape(1);
            if (mean.size() != d || scale.size() != d)
                throw py::value_error("mean and scale must have d entries");
            I8 codes({n, d});
            F64 code_sq(n), code_norm(n), err(n);
            {
                py::gil_scoped_release release;
                disco::int8_encode(x.data(), n, d, mean.data(), scale.data(),
                                   codes.mutable_data(), code_sq.mutable_data(),
                                   code_norm.mutable_data(), err.mutable_data(), threads);
            }
            return py::make_tuple(codes, code_sq, code_norm, err);
        },
        py::arg("x"), py::arg("mean"), py::arg("scale"), py::arg("threads") = 1,
        "int8 codes of float32 rows, with |scale c|^2, |c| and the error per row");
    m.def("int8_query_limit", &disco::int8_query_limit, py::arg("d"),
          "Largest |g_j| for which g . c cannot overflow int32 (and g_j splits in int8 halves)");

    // --- signature search: exact distances of candidate rows (src/cpp/disco/exact_search.*) ---
    using F32 = py::array_t<float, py::array::c_style>;
    using I64 = py::array_t<std::int64_t, py::array::c_style>;
    // Candidates must be rows of x; -1 (any negative) marks none.
    auto check_rows = [](const I64& rows, std::int64_t n) {
        const std::int64_t* r = rows.data();
        for (py::ssize_t i = 0; i < rows.size(); ++i)
            if (r[i] >= n) throw py::value_error("candidate rows must be below the row count");
    };
    m.def(
        "exact_topk",
        [check_rows](const F32& x, const F32& q, const I64& cand, int k) {
            if (x.ndim() != 2 || q.ndim() != 2 || q.shape(1) != x.shape(1))
                throw py::value_error("x must be [n, d] and q [b, d] float32");
            if (cand.ndim() != 2 || cand.shape(0) != q.shape(0))
                throw py::value_error("cand must be [b, m] int64");
            check_rows(cand, x.shape(0));
            const auto b = q.shape(0), kk = static_cast<py::ssize_t>(std::max(k, 0));
            I64 rows({b, kk});
            F64 dists({b, kk});
            {
                py::gil_scoped_release release;
                disco::exact_topk(x.data(), x.shape(1), q.data(), b, cand.data(), cand.shape(1),
                                  static_cast<int>(kk), rows.mutable_data(), dists.mutable_data());
            }
            return py::make_tuple(rows, dists);
        },
        py::arg("x"), py::arg("q"), py::arg("cand"), py::arg("k"),
        "Per query, the k nearest of its candidate rows (ties by row): rows [b, k] "
        "(-1 past the candidates) and distances [b, k] (inf), summed in float64");
    m.def(
        "exact_sq_distances",
        [check_rows](const F32& x, const F32& q, const I64& rows) {
            if (x.ndim() != 2 || q.ndim() != 1 || q.shape(0) != x.shape(1) || rows.ndim() != 1)
                throw py::value_error("x must be [n, d], q [d] float32 and rows [m] int64");
            check_rows(rows, x.shape(0));
            F64 out(rows.shape(0));
            {
                py::gil_scoped_release release;
                disco::exact_sq_distances(x.data(), x.shape(1), q.data(), rows.data(),
                                          rows.shape(0), out.mutable_data());
            }
            return out;
        },
        py::arg("x"), py::arg("q"), py::arg("rows"),
        "|x[rows[i]] - q|^2 in float64 (inf for a negative row)");
    m.def(
        "projected_approx",
        [](const F32& tiles, const F32& sq, const F32& q) {
            const auto n = sq.size();
            const auto t = (n + disco::kProjectedTile - 1) / disco::kProjectedTile;
            if (tiles.ndim() != 3 || tiles.shape(0) != t || tiles.shape(2) != disco::kProjectedTile)
                throw py::value_error("tiles must be [ceil(n / 64), p, 64] float32 for sq [n]");
            const auto p = tiles.shape(1);
            if (q.ndim() != 2 || q.shape(1) != p) throw py::value_error("q must be [b, p] float32");
            F32 out({q.shape(0), n});
            {
                py::gil_scoped_release release;
                disco::projected_approx(tiles.data(), p, n, sq.data(), q.data(), q.shape(0),
                                        out.mutable_data());
            }
            return out;
        },
        py::arg("tiles"), py::arg("sq"), py::arg("q"),
        "sq[j] - 2 q[i] . x_j (float32) for every projected row x_j held in column tiles");
    m.def(
        "smallest_per_row",
        [](const F32& values, std::int64_t k) {
            if (values.ndim() != 2) throw py::value_error("values must be [b, n] float32");
            if (k < 0) throw py::value_error("k must be >= 0");
            const auto b = values.shape(0), n = values.shape(1);
            py::array_t<std::int64_t> out({b, static_cast<py::ssize_t>(k)});
            {
                py::gil_scoped_release release;
                disco::smallest_per_row(values.data(), b, n, k, out.mutable_data());
            }
            return out;
        },
        py::arg("values"), py::arg("k"),
        "Per row, the columns of its k smallest finite values, ascending by (value, "
        "column); -1 past the finite ones");
    m.def(
        "search_kernel_names",
        []() {
            return py::make_tuple(disco::int8_kernel_name(), disco::exact_kernel_name(),
                                  disco::projected_kernel_name());
        },
        "The kernels that int8_candidates, exact_topk and projected_approx run now, under "
        "the level cap");
}

}  // namespace disco_bindings
