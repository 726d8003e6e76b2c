#include "soulctl/influence.hpp"

#include "soulctl/finite.hpp"

#include <algorithm>
#include <stdexcept>
#include <string>
#include <utility>

namespace soulctl {

InfluenceFunctions::InfluenceFunctions(std::vector<int64_t> indptr, std::vector<int32_t> indices,
                                       std::vector<double> values, int n_actuators)
    : indptr_(std::move(indptr)), indices_(std::move(indices)), values_(std::move(values)), n_actuators_(n_actuators) {
    if (n_actuators <= 0) throw std::invalid_argument("n_actuators must be positive, got " + std::to_string(n_actuators));
    if (indptr_.size() < 2) throw std::invalid_argument("indptr must hold n_pixels + 1 >= 2 row pointers");
    if (indices_.size() != values_.size())
        throw std::invalid_argument("indices and values must have the same length, got " + std::to_string(indices_.size()) +
                                    " and " + std::to_string(values_.size()));
    const auto nnz = static_cast<int64_t>(values_.size());
    if (indptr_.front() != 0 || indptr_.back() != nnz)
        throw std::invalid_argument("indptr must run from 0 to the number of entries (" + std::to_string(nnz) + "), got " +
                                    std::to_string(indptr_.front()) + ".." + std::to_string(indptr_.back()));
    for (size_t i = 1; i < indptr_.size(); ++i)
        if (indptr_[i] < indptr_[i - 1])
            throw std::invalid_argument("indptr must be non-decreasing, got " + std::to_string(indptr_[i - 1]) + " then " +
                                        std::to_string(indptr_[i]) + " at row " + std::to_string(i - 1));
    for (int64_t k = 0; k < nnz; ++k)
        if (indices_[k] < 0 || indices_[k] >= n_actuators)
            throw std::invalid_argument("indices must be in 0.." + std::to_string(n_actuators - 1) + ", got " +
                                        std::to_string(indices_[k]) + " at entry " + std::to_string(k));
    require_finite(values_.data(), static_cast<std::ptrdiff_t>(nnz), "values");
}

void InfluenceFunctions::shape(const double* c, double* shape) const {
    const int n = n_pixels();
    for (int i = 0; i < n; ++i) {
        double s = 0.0;
        for (int64_t k = indptr_[i]; k < indptr_[i + 1]; ++k) s += values_[k] * c[indices_[k]];
        shape[i] = s;
    }
}

void InfluenceFunctions::adjoint(const double* x, double* adjoint) const {
    std::fill(adjoint, adjoint + n_actuators_, 0.0);
    const int n = n_pixels();
    for (int i = 0; i < n; ++i) {
        const double xi = x[i];
        for (int64_t k = indptr_[i]; k < indptr_[i + 1]; ++k) adjoint[indices_[k]] += values_[k] * xi;
    }
}

void InfluenceFunctions::shape_and_adjoint(const double* c, const double* x, double* shape, double* adjoint) const {
    std::fill(adjoint, adjoint + n_actuators_, 0.0);
    const int n = n_pixels();
    for (int i = 0; i < n; ++i) {
        const double xi = x[i];
        double s = 0.0;
        for (int64_t k = indptr_[i]; k < indptr_[i + 1]; ++k) {
            const double f = values_[k];
            const int32_t j = indices_[k];
            s += f * c[j];
            adjoint[j] += f * xi;
        }
        shape[i] = s;
    }
}

}  // namespace soulctl
