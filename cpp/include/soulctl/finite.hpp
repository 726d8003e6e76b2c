// The rule for float inputs of the core: every float array given to it as a setting or an
// input of the controller (Lambda, Xi, Sigma, gains, slopes, reference slopes, background)
// must be finite; a NaN or infinity throws std::invalid_argument naming the argument, before
// anything is changed.  Detector frames are data instead: see SlopeComputer::compute.
// The check is one vectorised pass, cheap enough for every real-time step.
#pragma once

#include <cmath>
#include <cstddef>
#include <limits>
#include <stdexcept>
#include <string>

namespace soulctl {

// Index of the first value of x[0..n) that is NaN or infinite, or -1 when all are finite.
// T is float or double.  The common case (all finite) is one branch-free pass: |x| <= the
// type's largest value is false exactly for NaN and +-inf, and an integer OR-reduction
// vectorises without reordering float arithmetic.
template <typename T>
inline std::ptrdiff_t first_non_finite(const T* x, std::ptrdiff_t n) {
    constexpr T largest = std::numeric_limits<T>::max();
    unsigned bad = 0;
#pragma omp simd reduction(| : bad)
    for (std::ptrdiff_t i = 0; i < n; ++i) bad |= !(std::fabs(x[i]) <= largest);
    if (!bad) return -1;
    for (std::ptrdiff_t i = 0; i < n; ++i)
        if (!std::isfinite(x[i])) return i;
    return -1;  // not reached
}

// The one wording of the rule: "NAME: values must be finite, got nan at index 3" (vectors) or
// "... at [2, 0]" (matrices of `cols` columns, `at` the row-major flat index).
inline std::string non_finite_error(const char* name, double value, std::ptrdiff_t at, std::ptrdiff_t cols = 0) {
    const std::string v = std::isnan(value) ? "nan" : (value > 0 ? "inf" : "-inf");
    const std::string where = cols > 0 ? "[" + std::to_string(at / cols) + ", " + std::to_string(at % cols) + "]"
                                       : "index " + std::to_string(at);
    return std::string(name) + ": values must be finite, got " + v + " at " + where;
}

// Throws std::invalid_argument(non_finite_error(...)) unless x[0..n) is all finite.
template <typename T>
inline void require_finite(const T* x, std::ptrdiff_t n, const char* name, std::ptrdiff_t cols = 0) {
    const std::ptrdiff_t at = first_non_finite(x, n);
    if (at >= 0) throw std::invalid_argument(non_finite_error(name, x[at], at, cols));
}

}  // namespace soulctl
