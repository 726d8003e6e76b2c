#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "checks.hpp"
#include "soulctl/influence.hpp"

#include <limits>
#include <stdexcept>
#include <utility>

namespace py = pybind11;
using namespace soulctl;
using namespace soulctl::bind;

namespace {

template <typename T>
std::vector<T> integer_vector(const py::array& a, const char* name) {
    if (!(has_dtype<int32_t>(a) || has_dtype<int64_t>(a)))
        throw py::value_error(std::string(name) + ": expected an integer array (int32 or int64), got " + dtype_str(a));
    require_shape(a, {-1}, name);
    auto v = py::array_t<int64_t, py::array::c_style | py::array::forcecast>::ensure(a);
    std::vector<T> out(static_cast<size_t>(v.size()));
    for (py::ssize_t i = 0; i < v.size(); ++i) {
        const int64_t x = v.data()[i];
        if (x < std::numeric_limits<T>::min() || x > std::numeric_limits<T>::max())
            throw py::value_error(std::string(name) + ": value " + std::to_string(x) + " at index " + std::to_string(i) +
                                  " does not fit the index type");
        out[i] = static_cast<T>(x);
    }
    return out;
}

// A float64 vector of the given length (a contiguous copy only for a non-contiguous view;
// another dtype is an error, never a silent cast).
py::array_t<double, py::array::c_style> float64_vector(const py::array& a, py::ssize_t n, const char* name) {
    if (!has_dtype<double>(a)) throw py::value_error(std::string(name) + ": expected dtype float64, got " + dtype_str(a));
    require_shape(a, {n}, name);
    return py::array_t<double, py::array::c_style>::ensure(a);
}

InfluenceFunctions make_influence(const py::array& indptr, const py::array& indices, const py::array& values,
                                  int n_actuators) {
    if (!has_dtype<double>(values)) throw py::value_error("values: expected dtype float64, got " + dtype_str(values));
    require_shape(values, {-1}, "values");
    auto v = py::array_t<double, py::array::c_style>::ensure(values);
    std::vector<double> vals(v.data(), v.data() + v.size());
    try {
        return InfluenceFunctions(integer_vector<int64_t>(indptr, "indptr"), integer_vector<int32_t>(indices, "indices"),
                                  std::move(vals), n_actuators);
    } catch (const std::invalid_argument& e) {
        throw py::value_error(e.what());
    }
}

// One product of F or F^T: `in` (float64, n_in) -> a new float64 vector of n_out.
using Product = void (InfluenceFunctions::*)(const double*, double*) const;
py::array_t<double> product(const InfluenceFunctions& f, Product p, const py::array& in, py::ssize_t n_in, py::ssize_t n_out,
                            const char* name) {
    auto x = float64_vector(in, n_in, name);
    py::array_t<double> out(n_out);
    double* dst = out.mutable_data();
    {
        py::gil_scoped_release release;
        (f.*p)(x.data(), dst);
    }
    return out;
}

py::array_t<double> shape(const InfluenceFunctions& f, const py::array& commands) {
    return product(f, &InfluenceFunctions::shape, commands, f.n_actuators(), f.n_pixels(), "commands");
}

py::array_t<double> adjoint(const InfluenceFunctions& f, const py::array& opd) {
    return product(f, &InfluenceFunctions::adjoint, opd, f.n_pixels(), f.n_actuators(), "opd");
}

std::pair<py::array_t<double>, py::array_t<double>> shape_and_adjoint(const InfluenceFunctions& f, const py::array& commands, const py::array& opd) {
    auto c = float64_vector(commands, f.n_actuators(), "commands");
    auto x = float64_vector(opd, f.n_pixels(), "opd");
    py::array_t<double> s(f.n_pixels()), a(f.n_actuators());
    double *ds = s.mutable_data(), *da = a.mutable_data();
    {
        py::gil_scoped_release release;
        f.shape_and_adjoint(c.data(), x.data(), ds, da);
    }
    return {s, a};
}

}  // namespace

void bind_influence(py::module_& m) {
    py::class_<InfluenceFunctions>(m, "InfluenceFunctions", R"doc(
The adaptive secondary's influence functions F (pupil pixels x actuators) as a sparse matrix
in compressed rows, float64: scipy.sparse.csr_array's indptr, indices and data.

shape(c) = F c (the mirror's OPD), adjoint(x) = F^T x (a pupil OPD seen by the actuators),
shape_and_adjoint(c, x) both in one pass over F's entries: the loop's two memory-bound sparse
products at the price of one.  The sums run in scipy.sparse's order without fused
multiply-add, so the results equal scipy's CSR products bit for bit.

F is checked at construction (ValueError naming the problem): finite values, row pointers from
0 to the number of entries and non-decreasing, column indices in 0..n_actuators-1.  The vectors
are data: NaN or infinity propagates into the result.  A wrong dtype (float64 expected) or
length is a ValueError.  Calling a method of an object whose __init__ never ran raises TypeError.
)doc")
        .def(py::init(&make_influence), py::arg("indptr"), py::arg("indices"), py::arg("values"), py::arg("n_actuators"))
        .def("shape", method(&shape), py::arg("commands"), "F c: float64 (n_pixels,) from commands float64 (n_actuators,).")
        .def("adjoint", method(&adjoint), py::arg("opd"), "F^T x: float64 (n_actuators,) from an OPD float64 (n_pixels,).")
        .def("shape_and_adjoint", method(&shape_and_adjoint), py::arg("commands"), py::arg("opd"),
             "(F c, F^T x) in one pass over F.")
        .def_property_readonly("n_pixels", method(&InfluenceFunctions::n_pixels))
        .def_property_readonly("n_actuators", method(&InfluenceFunctions::n_actuators))
        .def_property_readonly("nnz", method(&InfluenceFunctions::nnz), "Stored entries.");
}
