// The one pybind11 file: turns the plain C++ library in src/cpp/disco/ into the
// private module disco_cli._core. Users never import _core; the Python wrappers
// (disco_cli.bev, ...) check shapes and dtypes and call it.
#include <pybind11/eigen.h>  // relative pose: 4 x 4 transforms
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "bindings.hpp"

#include "disco/conv3x3.hpp"      // U-Net convolutions
#include "disco/icp.hpp"          // relative pose
#include "disco/polar_bev.hpp"    // polar BEV voxelizer
#include "disco/raycast.hpp"      // simulator ray casting
#include "disco/version.hpp"

namespace py = pybind11;

PYBIND11_MODULE(_core, m) {
    m.doc() = "disco's compiled core (private; use the disco_cli package)";
    m.attr("__version__") = disco::core_version();

    // --- polar BEV voxelizer (src/cpp/disco/polar_bev.*) ---
    {
        // Points arrive as any float32/float64 numpy array of N x >=3 with positive
        // strides and are read in place (no copy); the Python wrapper (disco_cli.bev)
        // converts anything else once before calling.
        auto view_of = [](const py::handle& obj) -> disco::AnyBEVPointsView {
            if (!py::isinstance<py::array>(obj))
                throw py::type_error("points must be a numpy array");
            auto a = py::reinterpret_borrow<py::array>(obj);
            if (a.ndim() != 2 || a.shape(1) < 3)
                throw py::value_error("points must be N x 3 or wider");
            const auto item = a.itemsize();
            const auto rows = a.shape(0);
            // Strides of an empty or one-row array are never used to step, and NumPy
            // may report them as 0.
            const auto rs = rows > 1 ? a.strides(0) : item * a.shape(1);
            const auto cs = rows > 0 ? a.strides(1) : item;
            if (rs <= 0 || cs <= 0 || rs % item != 0 || cs % item != 0)
                throw py::value_error("points need positive strides in whole elements");
            const Eigen::Index n = rows;
            const Eigen::Stride<Eigen::Dynamic, Eigen::Dynamic> stride(rs / item, cs / item);
            if (py::isinstance<py::array_t<float>>(a))
                return disco::BEVPointsView<float>(static_cast<const float*>(a.data()), n, 3,
                                                   stride);
            if (py::isinstance<py::array_t<double>>(a))
                return disco::BEVPointsView<double>(static_cast<const double*>(a.data()), n, 3,
                                                    stride);
            throw py::type_error("points must be float32 or float64");
        };

        py::enum_<disco::BEVMode>(m, "BEVMode")
            .value("occupancy", disco::BEVMode::kOccupancy)
            .value("density", disco::BEVMode::kDensity)
            .value("max_height", disco::BEVMode::kMaxHeight);
        py::class_<disco::BEVConfig>(m, "BEVConfig")
            .def(py::init<>())
            .def_readwrite("rings", &disco::BEVConfig::rings)
            .def_readwrite("sectors", &disco::BEVConfig::sectors)
            .def_readwrite("heights", &disco::BEVConfig::heights)
            .def_readwrite("max_range", &disco::BEVConfig::max_range)
            .def_readwrite("min_range", &disco::BEVConfig::min_range)
            .def_readwrite("z_min", &disco::BEVConfig::z_min)
            .def_readwrite("z_max", &disco::BEVConfig::z_max)
            .def_readwrite("mode", &disco::BEVConfig::mode)
            .def("validate", &disco::BEVConfig::validate)
            .def_property_readonly("layers", &disco::BEVConfig::layers);

        m.def(
            "polar_bev",
            [view_of](const py::object& points, const disco::BEVConfig& config) {
                config.validate();
                const auto view = view_of(points);
                py::array_t<float> out({config.layers(), config.rings, config.sectors});
                float* dst = out.mutable_data();
                {
                    py::gil_scoped_release release;
                    std::visit([&](const auto& v) { disco::polar_bev(v, config, dst); }, view);
                }
                return out;
            },
            py::arg("points"), py::arg("config"),
            "[layers, rings, sectors] float32 BEV of one scan");
        m.def(
            "polar_bev_batch",
            [view_of](const py::list& scans, const disco::BEVConfig& config, int threads) {
                config.validate();
                std::vector<disco::AnyBEVPointsView> views;
                std::vector<py::object> alive;  // another thread may empty the list meanwhile
                views.reserve(scans.size());
                alive.reserve(scans.size());
                for (const auto& s : scans) {
                    views.push_back(view_of(s));
                    alive.push_back(py::reinterpret_borrow<py::object>(s));
                }
                const auto count = static_cast<py::ssize_t>(views.size());
                py::array_t<float> out({count, static_cast<py::ssize_t>(config.layers()),
                                        static_cast<py::ssize_t>(config.rings),
                                        static_cast<py::ssize_t>(config.sectors)});
                float* dst = out.mutable_data();
                {
                    py::gil_scoped_release release;
                    disco::polar_bev_batch(views, config, dst, threads);
                }
                return out;
            },
            py::arg("scans"), py::arg("config"), py::arg("threads") = 0,
            "[B, layers, rings, sectors] float32 BEVs, scans spread over threads (0: all cores)");
        // For tests and benchmarks: cap the SIMD kernel (x86-64: 3 AVX-512, 2 AVX2, 1 SSE2;
        // aarch64: 1 NEON; 0 plain) and name it.
        m.def("_set_bev_kernel_level", &disco::set_bev_kernel_level, py::arg("cap"));
        m.def("_bev_kernel_level", &disco::bev_kernel_level);
        m.def("_bev_kernel_name", &disco::bev_kernel_name, py::arg("level") = -1,
              "the kernel of `level` (-1: the one in use): avx512, avx2, sse2, neon, plain; "
              "'' where this CPU has no such level");
    }

    // --- simulator ray casting (src/cpp/disco/raycast.*) ---
    {
        // The Python wrapper (disco_cli.simulator.world) builds the primitive table
        // and checks shapes; here only what C++ itself relies on is checked.
        py::class_<disco::RaycastWorld>(m, "RaycastWorld")
            .def(py::init(
                     [](const py::array_t<double, py::array::c_style | py::array::forcecast>& table,
                        double a, double b, double c, double cell_size) {
                         // table: N x 9 rows of kind, cx, cy, cz, hx, hy, hz, yaw, hit_prob.
                         if (table.ndim() != 2 || table.shape(1) != 9)
                             throw py::value_error("primitive table must be N x 9");
                         std::vector<disco::Primitive> prims(
                             static_cast<std::size_t>(table.shape(0)));
                         auto t = table.unchecked<2>();
                         for (py::ssize_t k = 0; k < table.shape(0); ++k) {
                             const int kind = static_cast<int>(t(k, 0));
                             if (kind < 0 || kind > 2)
                                 throw py::value_error("unknown primitive kind");
                             auto& p = prims[static_cast<std::size_t>(k)];
                             p.kind = static_cast<disco::PrimitiveKind>(kind);
                             p.cx = t(k, 1), p.cy = t(k, 2), p.cz = t(k, 3);
                             p.hx = t(k, 4), p.hy = t(k, 5), p.hz = t(k, 6);
                             p.yaw = t(k, 7), p.hit_prob = t(k, 8);
                         }
                         disco::GroundPlane ground{a, b, c};
                         py::gil_scoped_release release;
                         return new disco::RaycastWorld(std::move(prims), ground, cell_size);
                     }),
                 py::arg("table"), py::arg("a"), py::arg("b"), py::arg("c"), py::arg("cell_size"))
            .def_property_readonly("size", &disco::RaycastWorld::size)
            .def_property_readonly("grid_shape",
                                   [](const disco::RaycastWorld& w) {
                                       return py::make_tuple(w.grid_nx(), w.grid_ny());
                                   })
            .def(
                "cast_scans",
                [](const disco::RaycastWorld& world,
                   const py::array_t<double, py::array::c_style | py::array::forcecast>& poses,
                   const py::array_t<float, py::array::c_style | py::array::forcecast>& dirs,
                   double max_range,
                   const py::array_t<std::uint64_t, py::array::c_style | py::array::forcecast>&
                       seeds,
                   int threads,
                   std::optional<py::array_t<double, py::array::c_style | py::array::forcecast>>
                       poses_end,
                   std::optional<py::array_t<float, py::array::c_style | py::array::forcecast>>
                       fractions) {
                    if (poses.ndim() != 3 || poses.shape(1) != 4 || poses.shape(2) != 4)
                        throw py::value_error("poses must be B x 4 x 4");
                    if (dirs.ndim() != 2 || dirs.shape(1) != 3)
                        throw py::value_error("directions must be N x 3");
                    if (seeds.ndim() != 1 || seeds.shape(0) != poses.shape(0))
                        throw py::value_error("need one seed per pose");
                    const py::ssize_t b = poses.shape(0), n = dirs.shape(0);
                    if (poses_end.has_value() != fractions.has_value())
                        throw py::value_error("give poses_end and fractions together");
                    if (poses_end && (poses_end->ndim() != 3 || poses_end->shape(0) != b ||
                                      poses_end->shape(1) != 4 || poses_end->shape(2) != 4))
                        throw py::value_error("poses_end must be B x 4 x 4 like poses");
                    if (fractions && (fractions->ndim() != 1 || fractions->shape(0) != n))
                        throw py::value_error("need one fraction per direction");
                    const double* pe = poses_end ? poses_end->data() : nullptr;
                    const float* fr = fractions ? fractions->data() : nullptr;
                    py::array_t<float> range({b, n});
                    py::array_t<std::int32_t> id({b, n});
                    py::array_t<float> cosi({b, n});
                    const double* pp = poses.data();
                    const float* dp = dirs.data();
                    const std::uint64_t* sp = seeds.data();
                    float* rp = range.mutable_data();
                    std::int32_t* ip = id.mutable_data();
                    float* cp = cosi.mutable_data();
                    {
                        py::gil_scoped_release release;
                        disco::cast_scans(world, pp, b, dp, n, max_range, sp, threads, rp, ip, cp,
                                          pe, fr);
                    }
                    return py::make_tuple(range, id, cosi);
                },
                py::arg("poses"), py::arg("dirs"), py::arg("max_range"), py::arg("seeds"),
                py::arg("threads") = 1, py::arg("poses_end") = py::none(),
                py::arg("fractions") = py::none());
        m.attr("RAYCAST_GROUND") = disco::kGround;
        m.attr("RAYCAST_MISS") = disco::kMiss;
    }

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
            .def(py::init(
                     [icp_view](const py::array_t<float>& points, const disco::IcpConfig& config) {
                         const disco::CloudView view = icp_view(points);
                         py::gil_scoped_release release;
                         return new disco::PlaneTarget(view, config);
                     }),
                 py::arg("points"), py::arg("config"))
            .def(
                "align",
                [](const disco::PlaneTarget& target, const Eigen::Ref<const RowsX3d>& source,
                   const Eigen::Matrix4d& initial, int first_stage, int last_stage,
                   int max_iterations) {
                    disco::Points3d src(static_cast<std::size_t>(source.rows()));
                    for (Eigen::Index i = 0; i < source.rows(); ++i) src[i] = source.row(i);
                    py::gil_scoped_release release;
                    return target.align(src, initial, first_stage, last_stage, max_iterations);
                },
                py::arg("source"), py::arg("initial"), py::arg("first_stage") = 0,
                py::arg("last_stage") = -1, py::arg("max_iterations") = -1)
            .def_property_readonly(
                "points",
                [icp_to_matrix](const disco::PlaneTarget& t) { return icp_to_matrix(t.points()); })
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

    disco_bindings::add_search(m);  // bindings_search.cpp
    disco_bindings::add_yaw(m);     // bindings_yaw.cpp
    disco_bindings::add_rerank(m);  // bindings_rerank.cpp

    // --- the U-Net's 3 x 3 convolution (src/cpp/disco/conv3x3.*) ---
    {
        // Weights are converted to float32 once; inputs must already be float32
        // C-contiguous [C_i, B, R, S] (unet_numpy.py makes them so): a copy here would
        // cost as much as the arithmetic of the small levels.
        using F32In = py::array_t<float, py::array::c_style | py::array::forcecast>;
        const auto conv_algorithm = [](const std::string& name) {
            if (name == "auto") return disco::ConvAlgorithm::automatic;
            if (name == "direct") return disco::ConvAlgorithm::direct;
            if (name == "winograd") return disco::ConvAlgorithm::winograd;
            throw py::value_error("algorithm must be 'auto', 'direct' or 'winograd', not '" +
                                  name + "'");
        };
        py::class_<disco::Conv3x3>(m, "Conv3x3")
            .def(py::init([](const F32In& weight, const F32In& bias) {
                     if (weight.ndim() != 4 || weight.shape(2) != 3 || weight.shape(3) != 3 ||
                         weight.shape(0) < 1 || weight.shape(1) < 1)
                         throw py::value_error("weight must be [cout, cin, 3, 3], cout, cin >= 1");
                     if (bias.ndim() != 1 || bias.shape(0) != weight.shape(0))
                         throw py::value_error("bias must be [cout]");
                     return new disco::Conv3x3(weight.data(), bias.data(), weight.shape(0),
                                               weight.shape(1));
                 }),
                 py::arg("weight"), py::arg("bias"),
                 "A 3 x 3 convolution from weight [cout, cin, 3, 3] and bias [cout]")
            .def_property_readonly("cout", &disco::Conv3x3::cout)
            .def_property_readonly("cin", &disco::Conv3x3::cin)
            .def(
                "__call__",
                [conv_algorithm](const disco::Conv3x3& conv, const py::sequence& inputs,
                                 bool circular, bool relu, const std::string& algorithm) {
                    const auto algo = conv_algorithm(algorithm);
                    if (py::len(inputs) == 0) throw py::value_error("need at least one input");
                    std::vector<py::array> keep;  // holds the arrays while the GIL is released
                    std::vector<disco::ConvPart> parts;
                    py::ssize_t b = 0, r = 0, s = 0, channels = 0;
                    for (const auto& item : inputs) {
                        if (!py::isinstance<py::array_t<float>>(item))
                            throw py::value_error("inputs must be float32 numpy arrays");
                        auto a = py::reinterpret_borrow<py::array>(item);
                        if (a.ndim() != 4)
                            throw py::value_error("each input must be [C, B, R, S]");
                        if (!(a.flags() & py::array::c_style))
                            throw py::value_error("inputs must be C-contiguous");
                        if (keep.empty()) b = a.shape(1), r = a.shape(2), s = a.shape(3);
                        if (a.shape(1) != b || a.shape(2) != r || a.shape(3) != s)
                            throw py::value_error("inputs must share B, R and S");
                        channels += a.shape(0);
                        parts.push_back({static_cast<const float*>(a.data()), a.shape(0)});
                        keep.push_back(a);
                    }
                    if (channels != conv.cin())
                        throw py::value_error("inputs have " + std::to_string(channels) +
                                              " channels, the convolution takes " +
                                              std::to_string(conv.cin()));
                    py::array_t<float> out({static_cast<py::ssize_t>(conv.cout()), b, r, s});
                    float* dst = out.mutable_data();
                    {
                        py::gil_scoped_release release;
                        conv.run(parts, b, r, s, circular, relu, dst, algo);
                    }
                    return out;
                },
                py::arg("inputs"), py::arg("circular"), py::arg("relu"),
                py::arg("algorithm") = "auto",
                "[cout, B, R, S] of inputs [C_i, B, R, S] joined along channels; sectors "
                "padded circularly or with zeros, rings with zeros; max(0, .) with relu; "
                "algorithm 'direct', 'winograd' or 'auto' (the one `choose` names)")
            .def(
                "choose",
                [](const disco::Conv3x3& conv, py::ssize_t rings, py::ssize_t sectors) {
                    return conv.choose(rings, sectors) == disco::ConvAlgorithm::winograd
                               ? "winograd"
                               : "direct";
                },
                py::arg("rings"), py::arg("sectors"),
                "the algorithm 'auto' runs on rings x sectors images at the kernel level in "
                "use: 'direct' or 'winograd'");
        using F32C = py::array_t<float, py::array::c_style>;
        m.def(
            "max_pool2",
            [](const F32C& x) {
                if (x.ndim() < 2) throw py::value_error("x must have 2 or more dimensions");
                std::vector<py::ssize_t> shape(x.shape(), x.shape() + x.ndim());
                const py::ssize_t rows = shape[shape.size() - 2], cols = shape.back();
                shape[shape.size() - 2] = rows / 2, shape.back() = cols / 2;
                const py::ssize_t images = rows > 0 && cols > 0 ? x.size() / (rows * cols) : 0;
                py::array_t<float> out(shape);
                const float* src = x.data();
                float* dst = out.mutable_data();
                {
                    py::gil_scoped_release release;
                    disco::max_pool2(src, images, rows, cols, dst);
                }
                return out;
            },
            py::arg("x"), "2 x 2 max-pooling over the last two axes (float32)");
        m.def(
            "resize_separable",
            [](const F32C& x, const F32C& row_w, const F32C& col_w) {
                if (x.ndim() < 2) throw py::value_error("x must have 2 or more dimensions");
                std::vector<py::ssize_t> shape(x.shape(), x.shape() + x.ndim());
                const py::ssize_t rows = shape[shape.size() - 2], cols = shape.back();
                if (row_w.ndim() != 2 || row_w.shape(1) != rows)
                    throw py::value_error("row weights must be [out_rows, rows of x]");
                if (col_w.ndim() != 2 || col_w.shape(0) != cols)
                    throw py::value_error("column weights must be [columns of x, out_cols]");
                shape[shape.size() - 2] = row_w.shape(0), shape.back() = col_w.shape(1);
                const py::ssize_t images = rows > 0 && cols > 0 ? x.size() / (rows * cols) : 0;
                py::array_t<float> out(shape);
                float* dst = out.mutable_data();
                {
                    py::gil_scoped_release release;
                    disco::resize_separable(x.data(), images, rows, cols, row_w.data(),
                                            row_w.shape(0), col_w.data(), col_w.shape(1), dst);
                }
                return out;
            },
            py::arg("x"), py::arg("row_w"), py::arg("col_w"),
            "row_w @ x @ col_w over the last two axes of x (float32), skipping zero weights");
        m.def("_conv3x3_kernel_name", &disco::conv3x3_kernel_name, py::arg("level") = -1,
              "the convolution kernel at `level` of the BEV kernel cap (-1: the one in use): "
              "avx512, avx2, plain; '' where this CPU has no such level");
    }
}
