// Argument checks shared by the bindings: every wrong shape or dtype becomes a ValueError
// that names what was expected and what was given (non-finite values are refused by the core
// itself, soulctl/finite.hpp: its std::invalid_argument is a ValueError in Python); a method
// called on an object whose __init__ never ran (Class.__new__(Class)) is a TypeError (see
// method() below).
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "soulctl/finite.hpp"

#include <cfloat>
#include <cmath>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

namespace soulctl::bind {

namespace py = pybind11;

inline std::string shape_str(const std::vector<py::ssize_t>& s) {
    std::string out = "(";
    for (size_t i = 0; i < s.size(); ++i) out += (i ? ", " : "") + std::to_string(s[i]);
    return out + (s.size() == 1 ? ",)" : ")");
}

inline std::string shape_str(const py::array& a) {
    return shape_str(std::vector<py::ssize_t>(a.shape(), a.shape() + a.ndim()));
}

inline std::string dtype_str(const py::array& a) { return py::str(a.dtype()).cast<std::string>(); }

// -1 in `expected` accepts any size on that axis.
inline void require_shape(const py::array& a, const std::vector<py::ssize_t>& expected, const char* name) {
    bool ok = a.ndim() == static_cast<py::ssize_t>(expected.size());
    for (size_t i = 0; ok && i < expected.size(); ++i) ok = expected[i] < 0 || a.shape(i) == expected[i];
    if (!ok) {
        std::string e = "(";
        for (size_t i = 0; i < expected.size(); ++i)
            e += (i ? ", " : "") + (expected[i] < 0 ? std::string("any") : std::to_string(expected[i]));
        e += expected.size() == 1 ? ",)" : ")";
        throw py::value_error(std::string(name) + ": expected shape " + e + ", got " + shape_str(a));
    }
}

template <typename T>
inline bool has_dtype(const py::array& a) {
    return a.dtype().is(py::dtype::of<T>());
}

// A float32 array of the given shape, C-contiguous (a contiguous copy is made only when the
// given array is a non-contiguous view; a different dtype is an error, never a silent cast).
inline py::array_t<float, py::array::c_style> float32_input(const py::array& a,
                                                             const std::vector<py::ssize_t>& shape,
                                                             const char* name) {
    if (!has_dtype<float>(a))
        throw py::value_error(std::string(name) + ": expected dtype float32, got " + dtype_str(a));
    require_shape(a, shape, name);
    return py::array_t<float, py::array::c_style>::ensure(a);
}

// An output array: float32, C-contiguous, writeable, of exactly this shape.
inline void check_output(const py::array& a, const std::vector<py::ssize_t>& shape, const char* name) {
    if (!has_dtype<float>(a)) throw py::value_error(std::string(name) + ": expected dtype float32, got " + dtype_str(a));
    require_shape(a, shape, name);
    if (!(a.flags() & py::array::c_style)) throw py::value_error(std::string(name) + ": must be C-contiguous");
    if (!a.writeable()) throw py::value_error(std::string(name) + ": must be writeable");
}

// The `out=` argument of a computing method: a new float32 array when None, else the given
// array after check_output.
inline py::array_t<float> output_or_new(py::object out, const std::vector<py::ssize_t>& shape, const char* name) {
    if (out.is_none()) return py::array_t<float>(shape);
    // Only a real ndarray: anything else would be converted to a temporary and never filled.
    if (!py::isinstance<py::array>(out)) throw py::value_error(std::string(name) + ": expected a numpy array");
    py::array o = py::reinterpret_borrow<py::array>(out);
    check_output(o, shape, name);
    return py::reinterpret_borrow<py::array_t<float>>(o);
}

// Matrices given at construction: float32 or float64 accepted (copied to float32 anyway).
inline py::array_t<float, py::array::c_style> matrix_input(const py::array& a, const char* name) {
    if (!has_dtype<float>(a) && !has_dtype<double>(a))
        throw py::value_error(std::string(name) + ": expected dtype float32 or float64, got " + dtype_str(a));
    if (a.ndim() != 2) throw py::value_error(std::string(name) + ": expected a 2-D matrix, got shape " + shape_str(a));
    if (has_dtype<double>(a)) {
        // Checked before the cast: numpy would warn (an error under -W error) on values beyond
        // float32's range, which the core's own check then reports as inf.
        auto d = py::array_t<double, py::array::c_style>::ensure(a);
        const double* x = d.data();
        const py::ssize_t n = d.size(), cols = d.shape(1);
        for (py::ssize_t i = 0; i < n; ++i) {
            if (!std::isfinite(x[i])) throw py::value_error(soulctl::non_finite_error(name, static_cast<float>(x[i]), i, cols));
            if (std::fabs(x[i]) > static_cast<double>(FLT_MAX))
                throw py::value_error(std::string(name) + ": values must fit in float32 (|x| <= 3.4e38), got " +
                                      py::str(py::float_(x[i])).cast<std::string>() + " at [" + std::to_string(i / cols) + ", " +
                                      std::to_string(i % cols) + "]");
        }
    }
    return py::array_t<float, py::array::c_style | py::array::forcecast>::ensure(a);
}

// --- The object a method is called on -----------------------------------------------------
// Class.__new__(Class) (or copy/pickle machinery, or a subclass's __new__) makes an instance
// whose __init__ never ran.  pybind11 does not refuse it: it hands the method freshly
// allocated, unconstructed memory (both for member-function pointers and for lambdas taking
// Class&), and the method reads garbage sizes and pointers.  Every method and property is
// therefore bound through method(), whose first argument is Self<Class>: its caster checks
// that the instance was constructed and raises TypeError otherwise, before any other argument
// is looked at.  tests/core/test_uninitialised.py calls every public member this way.

template <class C>
struct Self {
    C* ptr;
};

}  // namespace soulctl::bind

namespace pybind11::detail {

template <class C>
struct type_caster<soulctl::bind::Self<C>> {
    static constexpr auto name = make_caster<C>::name;  // signatures show the class, as usual
    template <typename>
    using cast_op_type = soulctl::bind::Self<C>;
    operator soulctl::bind::Self<C>() const { return {ptr_}; }

    bool load(handle src, bool) {
        static type_info* const tinfo = get_type_info(typeid(C));  // registered once, by class_<C>
        if (tinfo == nullptr || !PyObject_TypeCheck(src.ptr(), tinfo->type))
            return false;  // not a C at all: pybind11's usual TypeError
        auto* inst = reinterpret_cast<instance*>(src.ptr());
        value_and_holder vh = inst->get_value_and_holder(tinfo);
        if (!vh.holder_constructed() || vh.value_ptr() == nullptr)
            throw type_error(str(type::handle_of(src).attr("__name__")).cast<std::string>() +
                             " object is not initialised (its __init__ was not called)");
        ptr_ = vh.value_ptr<C>();
        return true;
    }

private:
    C* ptr_ = nullptr;
};

}  // namespace pybind11::detail

namespace soulctl::bind {

// method(f): f as a pybind11 method or property getter that refuses uninitialised objects.
// f is a member function (const or not) or a callable whose first parameter is C& / const C&.
template <class C, class R, class... A, bool NE>
auto method(R (C::*f)(A...) noexcept(NE)) {
    return [f](Self<C> self, A... a) -> R { return (self.ptr->*f)(std::forward<A>(a)...); };
}

template <class C, class R, class... A, bool NE>
auto method(R (C::*f)(A...) const noexcept(NE)) {
    return [f](Self<C> self, A... a) -> R { return (self.ptr->*f)(std::forward<A>(a)...); };
}

namespace method_impl {
template <class F, class R, class S, class... A>
auto method_from(F f) {
    static_assert(std::is_lvalue_reference_v<S>, "method(): the first parameter must be C& or const C&");
    using C = std::remove_const_t<std::remove_reference_t<S>>;
    return [f](Self<C> self, A... a) -> R { return f(*self.ptr, std::forward<A>(a)...); };
}
template <class F, class L, class R, class S, class... A>
auto method_from_call(F f, R (L::*)(S, A...) const) {
    return method_from<F, R, S, A...>(std::move(f));
}
}  // namespace method_impl

template <class R, class S, class... A>
auto method(R (*f)(S, A...)) {
    return method_impl::method_from<R (*)(S, A...), R, S, A...>(f);
}

template <class F, class = decltype(&F::operator())>
auto method(F f) {
    return method_impl::method_from_call(std::move(f), &F::operator());
}

}  // namespace soulctl::bind
