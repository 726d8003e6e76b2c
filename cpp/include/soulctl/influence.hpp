// The adaptive secondary's influence functions as a sparse matrix F (pupil pixels x actuators,
// compressed rows, float64): the mirror's shape F c and the projection F^T x of a pupil OPD
// onto the actuators, the two products of the simulated loop's mirror stage.
//
// shape_and_adjoint computes both in one pass over F's entries.  Both are memory-bound (the
// pyramid's FFTs evict F from the caches between frames), so one pass instead of two reads F
// once: at a 160-px pupil F holds 1.2 million entries (14.6 MB).
//
// The sums run in the order of scipy.sparse's CSR products (each row's entries in storage
// order; F^T x accumulated over ascending rows), and this file is compiled without
// floating-point contraction (no fused multiply-add), so the results equal scipy's bit for
// bit: the loop's numbers do not depend on which of the two computed them.
//
// F is a setting: its structure and values are checked at construction (finite values,
// ascending row pointers, column indices inside the actuators).  The vectors are data: a
// NaN or infinity propagates into the result, where the loop's divergence check sees it.
#pragma once

#include <cstdint>
#include <vector>

namespace soulctl {

class InfluenceFunctions {
public:
    // indptr: n_pixels + 1 row pointers; indices, values: one column index and value per entry.
    InfluenceFunctions(std::vector<int64_t> indptr, std::vector<int32_t> indices, std::vector<double> values,
                       int n_actuators);

    int n_pixels() const { return static_cast<int>(indptr_.size()) - 1; }
    int n_actuators() const { return n_actuators_; }
    int64_t nnz() const { return static_cast<int64_t>(values_.size()); }

    // shape[0..n_pixels) = F c
    void shape(const double* c, double* shape) const;
    // adjoint[0..n_actuators) = F^T x
    void adjoint(const double* x, double* adjoint) const;
    // Both in one pass over F.
    void shape_and_adjoint(const double* c, const double* x, double* shape, double* adjoint) const;

private:
    std::vector<int64_t> indptr_;
    std::vector<int32_t> indices_;
    std::vector<double> values_;
    int n_actuators_;
};

}  // namespace soulctl
