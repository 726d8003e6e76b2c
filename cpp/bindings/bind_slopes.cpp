#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "checks.hpp"
#include "soulctl/slopes.hpp"

namespace py = pybind11;
using namespace soulctl;
using namespace soulctl::bind;

namespace {

SlopeComputer make_slope_computer(const py::array& pixels, std::pair<int, int> frame_shape,
                                  const std::string& normalization) {
    if (!(has_dtype<int32_t>(pixels) || has_dtype<int64_t>(pixels)))
        throw py::value_error("pixels: expected an integer array (int32 or int64), got " + dtype_str(pixels));
    require_shape(pixels, {-1, 4, 2}, "pixels");
    Normalization norm;
    if (normalization == "global") norm = Normalization::Global;
    else if (normalization == "subaperture") norm = Normalization::Subaperture;
    else throw py::value_error("normalization: expected 'global' or 'subaperture', got '" + normalization + "'");
    auto p = py::array_t<int64_t, py::array::c_style | py::array::forcecast>::ensure(pixels);
    const py::ssize_t n = p.shape(0) * 4;
    std::vector<int64_t> rows(n), cols(n);
    auto v = p.unchecked<3>();
    for (py::ssize_t i = 0; i < p.shape(0); ++i)
        for (int q = 0; q < 4; ++q) {
            rows[4 * i + q] = v(i, q, 0);  // bounds are checked by the constructor
            cols[4 * i + q] = v(i, q, 1);
        }
    try {
        return SlopeComputer(rows, cols, frame_shape.first, frame_shape.second, norm);
    } catch (const std::invalid_argument& e) {
        throw py::value_error(e.what());
    }
}

py::array_t<float> compute(SlopeComputer& sc, const py::array& frame, py::object out) {
    const std::vector<py::ssize_t> fshape{sc.frame_rows(), sc.frame_cols()};
    const py::ssize_t ns = 2 * static_cast<py::ssize_t>(sc.n_subapertures());
    py::array_t<float> result = output_or_new(out, {ns}, "out");
    float* dst = result.mutable_data();
    if (has_dtype<float>(frame)) {
        require_shape(frame, fshape, "frame");
        auto f = py::array_t<float, py::array::c_style>::ensure(frame);
        sc.compute<float>(f.data(), dst);
    } else if (has_dtype<uint16_t>(frame)) {
        require_shape(frame, fshape, "frame");
        auto f = py::array_t<uint16_t, py::array::c_style>::ensure(frame);
        sc.compute<uint16_t>(f.data(), dst);
    } else {
        throw py::value_error("frame: expected dtype float32 or uint16, got " + dtype_str(frame));
    }
    return result;
}

}  // namespace

void bind_slopes(py::module_& m) {
    py::class_<SlopeComputer>(m, "SlopeComputer", R"doc(
PWFS slope computer: detector frame -> slopes, at full rate.

pixels: int array (n_subapertures, 4, 2) with the (row, col) of pupil image 1..4 of each
valid sub-aperture, at the frame's binning.  Pupil images: 1 = (+x, +y), 2 = (+x, -y),
3 = (-x, +y), 4 = (-x, -y), x along columns, y along rows, so
    sx = (I1 + I2 - I3 - I4) / N,   sy = (I1 - I2 + I3 - I4) / N.
normalization: 'global' (N = mean flux per valid sub-aperture, default) or 'subaperture'
(N = the sub-aperture's own flux).  Slopes come out as [sx_0..sx_{n-1}, sy_0..sy_{n-1}].
Zero, negative or non-finite flux gives zero slopes and sets flux_ok False / n_dark.

Inputs: settings must be finite -- the background (set_background: every pixel of the frame)
and the reference slopes (set_reference).  A NaN or infinity raises ValueError naming the
argument and the first bad position (e.g. "reference: values must be finite, got nan at
index 3"), and the background or reference in use is unchanged.  Frames are data: a
non-finite pixel in a valid sub-aperture is unusable light, never an error.  With
'subaperture' normalisation that sub-aperture is dark (zero slopes, counted in n_dark); with
'global' normalisation the mean flux is not finite, so the whole frame is dark (all slopes
zero, n_dark = n_subapertures).  Either way flux_ok is False and the slopes are finite; pixels
outside the valid sub-apertures are never read.  A wrong dtype or shape is a ValueError naming
what was expected and what was given.  Calling a method of an object whose __init__ never ran
(SlopeComputer.__new__) raises TypeError.
)doc")
        .def(py::init(&make_slope_computer), py::arg("pixels"), py::arg("frame_shape"),
             py::arg("normalization") = "global")
        .def("compute", method(&compute), py::arg("frame"), py::arg("out") = py::none(),
             "Slopes of a frame (float32 or uint16, shape frame_shape) as float32 (2*n_subapertures,).")
        .def(
            "set_background",
            method([](SlopeComputer& sc, const py::array& frame) {
                auto f = float32_input(frame, {sc.frame_rows(), sc.frame_cols()}, "background");
                sc.set_background(f.data());
            }),
            py::arg("frame"), "Background frame (float32, shape frame_shape) subtracted before the slopes.")
        .def("clear_background", method(&SlopeComputer::clear_background))
        .def(
            "set_reference",
            method([](SlopeComputer& sc, const py::array& slopes) {
                auto s = float32_input(slopes, {2 * static_cast<py::ssize_t>(sc.n_subapertures())}, "reference");
                sc.set_reference(s.data());
            }),
            py::arg("slopes"), "Reference slopes (float32, 2*n_subapertures) subtracted after normalisation.")
        .def("clear_reference", method(&SlopeComputer::clear_reference))
        .def_property_readonly("n_subapertures", method(&SlopeComputer::n_subapertures))
        .def_property_readonly("frame_shape", method([](const SlopeComputer& sc) {
            return py::make_tuple(sc.frame_rows(), sc.frame_cols());
        }))
        .def_property_readonly("normalization", method([](const SlopeComputer& sc) {
            return sc.normalization() == Normalization::Global ? "global" : "subaperture";
        }))
        .def_property_readonly("has_background", method(&SlopeComputer::has_background))
        .def_property_readonly("has_reference", method(&SlopeComputer::has_reference))
        .def_property_readonly("total_flux", method([](const SlopeComputer& sc) { return sc.last_status().total_flux; }),
                               "Background-subtracted flux over the valid sub-apertures in the last frame.")
        .def_property_readonly("flux_ok", method([](const SlopeComputer& sc) { return sc.last_status().flux_ok; }),
                               "False if the last frame's normalising flux was zero, negative or not finite.")
        .def_property_readonly("n_dark", method([](const SlopeComputer& sc) { return sc.last_status().n_dark; }),
                               "Sub-apertures whose slopes were zeroed in the last frame.")
        .def_property_readonly("subaperture_flux", method([](const SlopeComputer& sc) {
            const auto& f = sc.subaperture_flux();
            return py::array_t<float>(f.size(), f.data());
        }), "Flux of each valid sub-aperture in the last frame (a copy).");
}
