#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "checks.hpp"
#include "soulctl/rtc.hpp"

namespace py = pybind11;
using namespace soulctl;
using namespace soulctl::bind;

namespace {

using MapR = Eigen::Map<const RowMatrixXf>;

// n_threads as Python gives it: any integer (not a bool, as everywhere in soulctl).  One
// outside 0..kMaxThreads is a ValueError naming the range, even when it does not fit a C int.
int threads_argument(const py::object& n) {
    if (PyBool_Check(n.ptr()) || !PyIndex_Check(n.ptr()))
        throw py::type_error("n_threads: expected an integer, got " +
                             py::str(py::type::handle_of(n).attr("__name__")).cast<std::string>());
    auto i = py::reinterpret_steal<py::int_>(PyNumber_Index(n.ptr()));
    if (!i) throw py::error_already_set();
    int overflow = 0;
    const long long v = PyLong_AsLongLongAndOverflow(i.ptr(), &overflow);
    if (overflow != 0 || v < 0 || v > RealTimeController::kMaxThreads)
        throw py::value_error(n_threads_error(py::str(i).cast<std::string>()));
    return static_cast<int>(v);
}

RealTimeController make_rtc(const py::array& lambda, const py::array& xi, const py::array& sigma,
                            const py::object& n_threads_arg) {
    const int n_threads = threads_argument(n_threads_arg);
    auto l = matrix_input(lambda, "Lambda");
    auto x = matrix_input(xi, "Xi");
    auto s = matrix_input(sigma, "Sigma");
    try {
        return RealTimeController(MapR(l.data(), l.shape(0), l.shape(1)), MapR(x.data(), x.shape(0), x.shape(1)),
                                  MapR(s.data(), s.shape(0), s.shape(1)), n_threads);
    } catch (const std::invalid_argument& e) {
        throw py::value_error(e.what());
    }
}

py::array_t<float> vec(const Eigen::VectorXf& v) { return py::array_t<float>(v.size(), v.data()); }

}  // namespace

void bind_rtc(py::module_& m) {
    py::class_<RealTimeController>(m, "RealTimeController", R"doc(
The SOUL RTC equation:  zeta(k) = Lambda zeta(k-1) + Delta Xi s(k),  c(k) = Sigma zeta(k).

Lambda (n_states x n_states), Xi (n_states x n_slopes) and Sigma (n_commands x n_states) are
fixed at construction (float32 or float64, stored as float32: a float64 value beyond float32's
range becomes inf and is refused, see Inputs).  Delta is diagonal: set its diagonal with
set_state_gains(); it may change between any two steps.

n_threads: OpenMP threads for step(), an integer in 0..64; 0 = automatic (OpenMP's maximum,
at most 4).  Outside 0..64 is a ValueError naming the range (a bool or a float is a
TypeError).  The controller may use fewer threads than asked (no more than the state's blocks
can be split into; one without OpenMP): the n_threads property tells how many it uses.

Inputs: every float array given must be finite -- Lambda, Xi, Sigma, the gains of set_state_gains()
and run(state_gains=), the slopes of step() and run().  A NaN or infinity raises ValueError naming
the argument and the first bad position (e.g. "slopes: values must be finite, got nan at
index 17"), and changes nothing: the state, the gains and out= are as before the call (run()
checks the whole block first).  A wrong dtype or shape is a ValueError naming what was
expected and what was given.  Calling a method of an object whose __init__ never ran
(RealTimeController.__new__) raises TypeError.
)doc")
        .def(py::init(&make_rtc), py::arg("Lambda"), py::arg("Xi"), py::arg("Sigma"), py::arg_v("n_threads", py::int_(0), "0"))
        .def(
            "set_state_gains",
            method([](RealTimeController& r, const py::array& delta) {
                auto d = float32_input(delta, {r.n_states()}, "state_gains");
                r.set_state_gains(d.data());
            }),
            py::arg("delta"), "Set the diagonal of Delta (float32, n_states); used from the next step on.")
        .def_property_readonly("state_gains", method([](const RealTimeController& r) { return vec(r.state_gains()); }),
                               "The diagonal of Delta (a copy).")
        .def_property_readonly("state", method([](const RealTimeController& r) { return vec(r.state()); }),
                               "The state zeta after the last step (a copy).")
        .def("reset", method(&RealTimeController::reset), "Set the state zeta to zero.")
        .def(
            "step",
            method([](RealTimeController& r, const py::array& slopes, py::object out) {
                auto s = float32_input(slopes, {r.n_slopes()}, "slopes");
                auto c = output_or_new(out, {r.n_commands()}, "out");
                r.step(s.data(), c.mutable_data());
                return c;
            }),
            py::arg("slopes"), py::arg("out") = py::none(),
            "One frame: slopes (float32, n_slopes) -> commands (float32, n_commands).")
        .def(
            "run",
            method([](RealTimeController& r, const py::array& slopes, py::object gains) {
                auto s = float32_input(slopes, {-1, r.n_slopes()}, "slopes");
                const py::ssize_t n = s.shape(0);
                if (n > INT32_MAX) throw py::value_error("slopes: at most 2147483647 steps per run, got " + std::to_string(n));
                py::array_t<float> c({n, static_cast<py::ssize_t>(r.n_commands())});
                const float* g = nullptr;
                py::array_t<float, py::array::c_style> gk;
                if (!gains.is_none()) {
                    if (!py::isinstance<py::array>(gains)) throw py::value_error("state_gains: expected a numpy array");
                    gk = float32_input(py::reinterpret_borrow<py::array>(gains), {n, r.n_states()}, "state_gains");
                    g = gk.data();
                }
                r.run(s.data(), static_cast<int>(n), c.mutable_data(), g);
                return c;
            }),
            py::arg("slopes"), py::arg("state_gains") = py::none(),
            "A block of frames for offline replays: slopes (n_steps, n_slopes) -> commands (n_steps, n_commands).\n"
            "state_gains, optional (n_steps, n_states): Delta at each step.  Continues from the current state.")
        .def_property_readonly("n_states", method(&RealTimeController::n_states))
        .def_property_readonly("n_slopes", method(&RealTimeController::n_slopes))
        .def_property_readonly("n_commands", method(&RealTimeController::n_commands))
        .def_property_readonly("n_threads", method(&RealTimeController::n_threads),
                               "Threads step() uses: at most the n_threads asked for (0 asked: automatic).")
        .def_property_readonly("structure", method([](const RealTimeController& r) {
            py::list sizes;
            for (const auto& b : r.blocks()) sizes.append(b.size);
            py::dict d;
            d["diagonal_states"] = r.n_diagonal_states();
            d["block_sizes"] = sizes;
            d["input_rows"] = r.n_input_rows();
            d["output_states"] = r.n_output_states();
            return d;
        }), "The structure found at construction: diagonal states, dense block sizes, non-zero Xi rows, non-zero Sigma columns.");
}
