// The one pybind11 file: turns the plain C++ library in src/cpp/disco/ into the
// private module disco_cli._core. Users never import _core; the Python wrappers
// (disco_cli.bev, ...) check shapes and dtypes and call it.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "disco/version.hpp"
#include "disco/icp.hpp"  // relative pose
#include <pybind11/eigen.h>  // relative pose: 4 x 4 transforms

namespace py = pybind11;

PYBIND11_MODULE(_core, m) {
    m.doc() = "disco's compiled core (private; use the disco_cli package)";
    m.attr("__version__") = disco::core_version();

    // --- polar BEV voxelizer (src/cpp/disco/polar_bev.*) ---

    // --- simulator ray casting (src/cpp/disco/raycast.*) ---

    // --- relative pose: ICP (src/cpp/disco/icp.*) ---
    {
        // N x C float32 NumPy array (C >= 3) -> a strided Eigen view, no copy.
        // The Python wrapper (disco_cli.relative_pose) checks dtype, shape and strides.
        auto icp_view = [](const py::array_t<float>& a) {
            if (a.ndim() != 2 || a.shape(1) < 3)
                throw py::value_error("points must be N x 3 or more float32");
            if (a.strides(0) < 0 || a.strides(1) < 0 || a.strides(0) % sizeof(float) != 0 ||
                a.strides(1) % sizeof(float) != 0)
                throw py::value_error("points must have positive float-aligned strides");
            return disco::CloudView(
                a.data(), a.shape(0), a.shape(1),
                Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic>(a.strides(0) / sizeof(float),
                                                              a.strides(1) / sizeof(float)));
        };
        using RowsX3d = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
        auto icp_to_matrix = [](const disco::Points3d& p) {
            RowsX3d out(static_cast<Eigen::Index>(p.size()), 3);
            for (std::size_t i = 0; i < p.size(); ++i) out.row(i) = p[i].transpose();
            return out;
        };

        py::class_<disco::IcpConfig>(m, "IcpConfig")
            .def(py::init<>())
            .def_readwrite("source_voxel", &disco::IcpConfig::source_voxel)
            .def_readwrite("target_voxel", &disco::IcpConfig::target_voxel)
            .def_readwrite("max_range", &disco::IcpConfig::max_range)
            .def_readwrite("normal_radius", &disco::IcpConfig::normal_radius)
            .def_readwrite("normal_min_neighbors", &disco::IcpConfig::normal_min_neighbors)
            .def_readwrite("stages", &disco::IcpConfig::stages)
            .def_readwrite("max_iterations", &disco::IcpConfig::max_iterations)
            .def_readwrite("convergence", &disco::IcpConfig::convergence)
            .def_readwrite("inlier_distance", &disco::IcpConfig::inlier_distance)
            .def_readwrite("horizontal_cos", &disco::IcpConfig::horizontal_cos);

        py::class_<disco::IcpResult>(m, "IcpResult")
            .def_readonly("transform", &disco::IcpResult::transform)
            .def_readonly("fitness", &disco::IcpResult::fitness)
            .def_readonly("fitness_all", &disco::IcpResult::fitness_all)
            .def_readonly("rmse", &disco::IcpResult::rmse)
            .def_readonly("iterations", &disco::IcpResult::iterations)
            .def_readonly("source_points", &disco::IcpResult::source_points)
            .def_readonly("target_points", &disco::IcpResult::target_points)
            .def_readonly("inliers", &disco::IcpResult::inliers);

        py::class_<disco::PlaneTarget>(m, "PlaneTarget")
            .def(py::init([icp_view](const py::array_t<float>& points,
                                     const disco::IcpConfig& config) {
                     const disco::CloudView view = icp_view(points);
                     py::gil_scoped_release release;
                     return new disco::PlaneTarget(view, config);
                 }),
                 py::arg("points"), py::arg("config"))
            .def(
                "align",
                [](const disco::PlaneTarget& target, const Eigen::Ref<const RowsX3d>& source,
                   const Eigen::Matrix4d& initial) {
                    disco::Points3d src(static_cast<std::size_t>(source.rows()));
                    for (Eigen::Index i = 0; i < source.rows(); ++i) src[i] = source.row(i);
                    py::gil_scoped_release release;
                    return target.align(src, initial);
                },
                py::arg("source"), py::arg("initial"))
            .def_property_readonly("points",
                                   [icp_to_matrix](const disco::PlaneTarget& t) {
                                       return icp_to_matrix(t.points());
                                   })
            .def_property_readonly("normals", [icp_to_matrix](const disco::PlaneTarget& t) {
                return icp_to_matrix(t.normals());
            });

        m.def(
            "icp_prepare_source",
            [icp_view, icp_to_matrix](const py::array_t<float>& points,
                                      const disco::IcpConfig& config) {
                const disco::CloudView view = icp_view(points);
                disco::Points3d out;
                {
                    py::gil_scoped_release release;
                    out = disco::prepare_source(view, config);
                }
                return icp_to_matrix(out);
            },
            py::arg("points"), py::arg("config"));

        m.def(
            "icp_voxel_downsample",
            [icp_view, icp_to_matrix](const py::array_t<float>& points, double voxel) {
                const disco::CloudView view = icp_view(points);
                disco::Points3d out;
                {
                    py::gil_scoped_release release;
                    out = disco::voxel_downsample(disco::crop_points(view, 0.0), voxel);
                }
                return icp_to_matrix(out);
            },
            py::arg("points"), py::arg("voxel"));

        m.def(
            "height_image",
            [icp_view](const py::array_t<float>& points, double yaw, double cell,
                       double half_extent) {
                const disco::CloudView view = icp_view(points);
                py::gil_scoped_release release;
                return disco::height_image(view, yaw, cell, half_extent);
            },
            py::arg("points"), py::arg("yaw"), py::arg("cell"), py::arg("half_extent"));
    }
}
