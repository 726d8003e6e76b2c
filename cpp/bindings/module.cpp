#include <pybind11/pybind11.h>

namespace py = pybind11;

void bind_slopes(py::module_& m);
void bind_rtc(py::module_& m);
void bind_influence(py::module_& m);

PYBIND11_MODULE(_core, m) {
    m.doc() = "soulctl real-time core: PWFS slope computation and the SOUL RTC state update (float32); the mirror's influence functions (float64).";
    bind_slopes(m);
    bind_rtc(m);
    bind_influence(m);
#ifdef SOULCTL_HAVE_OPENMP
    m.attr("openmp") = true;
#else
    m.attr("openmp") = false;
#endif
}
