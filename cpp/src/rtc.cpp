#include "soulctl/rtc.hpp"

#include "soulctl/finite.hpp"

#include <algorithm>
#include <numeric>
#include <stdexcept>
#include <string>

#ifdef SOULCTL_HAVE_OPENMP
#include <omp.h>
#endif

namespace soulctl {

namespace {

std::string shape(long r, long c) { return "(" + std::to_string(r) + ", " + std::to_string(c) + ")"; }

// Connected components of the non-zero pattern of a square matrix, as contiguous blocks.
// A component that is not contiguous is widened to the contiguous range covering it, so
// the result is always a partition of [0, n) into diagonal blocks.
std::vector<std::pair<int, int>> diagonal_blocks(const RowMatrixXf& a) {
    const int n = static_cast<int>(a.rows());
    std::vector<int> reach(n);  // furthest index coupled to i
    for (int i = 0; i < n; ++i) {
        int far = i;
        for (int j = 0; j < n; ++j)
            if (a(i, j) != 0.0f || a(j, i) != 0.0f) far = std::max(far, j);
        reach[i] = far;
    }
    std::vector<std::pair<int, int>> blocks;
    int start = 0, end = 0;
    for (int i = 0; i < n; ++i) {
        end = std::max(end, reach[i]);
        if (i == end) {
            blocks.emplace_back(start, end - start + 1);
            start = i + 1;
            end = i + 1;
        }
    }
    return blocks;
}

}  // namespace

RealTimeController::RealTimeController(const RowMatrixXf& lambda, const RowMatrixXf& xi,
                                       const RowMatrixXf& sigma, int n_threads) {
    n_states_ = static_cast<int>(lambda.rows());
    if (lambda.rows() != lambda.cols() || n_states_ == 0)
        throw std::invalid_argument("Lambda must be square and non-empty, got shape " + shape(lambda.rows(), lambda.cols()));
    if (xi.rows() != n_states_ || xi.cols() == 0)
        throw std::invalid_argument("Xi must have shape (" + std::to_string(n_states_) + ", n_slopes), got " +
                                    shape(xi.rows(), xi.cols()));
    if (sigma.cols() != n_states_ || sigma.rows() == 0)
        throw std::invalid_argument("Sigma must have shape (n_commands, " + std::to_string(n_states_) + "), got " +
                                    shape(sigma.rows(), sigma.cols()));
    require_finite(lambda.data(), lambda.size(), "Lambda", lambda.cols());
    require_finite(xi.data(), xi.size(), "Xi", xi.cols());
    require_finite(sigma.data(), sigma.size(), "Sigma", sigma.cols());
    // Refused, not clamped: -5 or 1000 threads is a mistake in the caller's configuration.
    if (n_threads < 0 || n_threads > kMaxThreads) throw std::invalid_argument(n_threads_error(std::to_string(n_threads)));
    n_slopes_ = static_cast<int>(xi.cols());
    n_commands_ = static_cast<int>(sigma.rows());

#ifdef SOULCTL_HAVE_OPENMP
    if (n_threads == 0) n_threads = std::min(omp_get_max_threads(), 4);
#else
    n_threads = 1;
#endif
    n_threads_ = std::max(1, n_threads);

    // Lambda: diagonal entries and dense blocks.
    lambda_diag_ = Eigen::VectorXf::Zero(n_states_);
    for (auto [off, size] : diagonal_blocks(lambda)) {
        if (size == 1) {
            diag_index_.push_back(off);
            lambda_diag_[off] = lambda(off, off);
        } else {
            blocks_.push_back({off, size, lambda.block(off, off, size, size)});
        }
    }

    // Xi: keep non-zero rows.
    xi_pos_.assign(n_states_, -1);
    for (int i = 0; i < n_states_; ++i)
        if ((xi.row(i).array() != 0.0f).any()) {
            xi_pos_[i] = static_cast<int>(xi_rows_.size());
            xi_rows_.push_back(i);
        }
    xi_ = RowMatrixXf(xi_rows_.size(), n_slopes_);
    for (size_t r = 0; r < xi_rows_.size(); ++r) xi_.row(r) = xi.row(xi_rows_[r]);

    // Sigma: keep non-zero columns.
    for (int j = 0; j < n_states_; ++j)
        if ((sigma.col(j).array() != 0.0f).any()) sigma_cols_.push_back(j);
    sigma_ = RowMatrixXf(n_commands_, sigma_cols_.size());
    for (size_t c = 0; c < sigma_cols_.size(); ++c) sigma_.col(c) = sigma.col(sigma_cols_[c]);

    // Thread ranges: contiguous state ranges cut on block boundaries, balancing Xi rows.
    std::vector<int> cuts{0};
    {
        std::vector<int> boundary_ok(n_states_ + 1, 1);
        for (const auto& b : blocks_)
            for (int k = b.offset + 1; k < b.offset + b.size; ++k) boundary_ok[k] = 0;
        const int total_rows = std::max<int>(1, static_cast<int>(xi_rows_.size()));
        int rows_seen = 0, t = 1;
        for (int i = 0; i < n_states_ && t < n_threads_; ++i) {
            if (xi_pos_[i] >= 0) ++rows_seen;
            if (boundary_ok[i + 1] && rows_seen * n_threads_ >= t * total_rows && i + 1 > cuts.back()) {
                cuts.push_back(i + 1);
                ++t;
            }
        }
        if (cuts.back() != n_states_) cuts.push_back(n_states_);
    }
    n_threads_ = static_cast<int>(cuts.size()) - 1;
    for (int t = 0; t < n_threads_; ++t) {
        Range r;
        r.state_begin = cuts[t];
        r.state_end = cuts[t + 1];
        auto lo = [&](const std::vector<int>& v, int x) {
            return static_cast<int>(std::lower_bound(v.begin(), v.end(), x) - v.begin());
        };
        r.xi_begin = lo(xi_rows_, r.state_begin);
        r.xi_end = lo(xi_rows_, r.state_end);
        r.out_begin = lo(sigma_cols_, r.state_begin);
        r.out_end = lo(sigma_cols_, r.state_end);
        r.cmd_begin = static_cast<int>(static_cast<long>(n_commands_) * t / n_threads_);
        r.cmd_end = static_cast<int>(static_cast<long>(n_commands_) * (t + 1) / n_threads_);
        for (int i : diag_index_)
            if (i >= r.state_begin && i < r.state_end) r.diag.push_back(i);
        int largest = 1;
        for (size_t b = 0; b < blocks_.size(); ++b)
            if (blocks_[b].offset >= r.state_begin && blocks_[b].offset < r.state_end) {
                r.blocks.push_back(static_cast<int>(b));
                largest = std::max(largest, blocks_[b].size);
            }
        r.scratch = Eigen::VectorXf::Zero(largest);
        ranges_.push_back(std::move(r));
    }

    delta_ = Eigen::VectorXf::Zero(n_states_);
    zeta_ = Eigen::VectorXf::Zero(n_states_);
    u_ = Eigen::VectorXf::Zero(xi_rows_.size());
    zout_ = Eigen::VectorXf::Zero(sigma_cols_.size());
}

void RealTimeController::set_state_gains(const float* delta) {
    require_finite(delta, n_states_, "state_gains");
    delta_ = Eigen::Map<const Eigen::VectorXf>(delta, n_states_);
}

void RealTimeController::reset() {
    zeta_.setZero();
    zout_.setZero();
}

// u = Xi s on the compressed Xi rows of one range.
void RealTimeController::input_range(const Range& r, const float* s) {
    const int nrows = r.xi_end - r.xi_begin;
    if (nrows > 0)
        u_.segment(r.xi_begin, nrows).noalias() =
            xi_.middleRows(r.xi_begin, nrows) * Eigen::Map<const Eigen::VectorXf>(s, n_slopes_);
}

// zeta <- Lambda zeta + Delta u on the states of one range, then gather its output states.
// u is indexed by compressed Xi row.
void RealTimeController::update_range(Range& r, const float* u, const float* delta) {
    float* z = zeta_.data();
    const float* ld = lambda_diag_.data();
    const int* pos = xi_pos_.data();
    for (int i : r.diag) {
        const int p = pos[i];
        z[i] = ld[i] * z[i] + (p >= 0 ? delta[i] * u[p] : 0.0f);
    }
    for (int b : r.blocks) {
        const LambdaBlock& blk = blocks_[b];
        auto t = r.scratch.head(blk.size);
        t.noalias() = blk.a * zeta_.segment(blk.offset, blk.size);
        for (int k = 0; k < blk.size; ++k) {
            const int i = blk.offset + k;
            const int p = pos[i];
            z[i] = t[k] + (p >= 0 ? delta[i] * u[p] : 0.0f);
        }
    }
    for (int o = r.out_begin; o < r.out_end; ++o) zout_[o] = z[sigma_cols_[o]];
}

// c = Sigma zeta on the command rows of one range.
void RealTimeController::output_range(const Range& r, float* c) const {
    const int n = r.cmd_end - r.cmd_begin;
    if (n > 0) Eigen::Map<Eigen::VectorXf>(c + r.cmd_begin, n).noalias() = sigma_.middleRows(r.cmd_begin, n) * zout_;
}

void RealTimeController::advance(int r, const float* s) {
    input_range(ranges_[r], s);
    update_range(ranges_[r], u_.data(), delta_.data());
}

void RealTimeController::step(const float* s, float* c) {
    require_finite(s, n_slopes_, "slopes");  // before the state is touched
#ifdef SOULCTL_HAVE_OPENMP
    if (n_threads_ > 1) {
        // If the runtime grants fewer threads than asked, each thread takes several ranges.
#pragma omp parallel num_threads(n_threads_)
        {
            const int tid = omp_get_thread_num(), nt = omp_get_num_threads();
            for (int t = tid; t < n_threads_; t += nt) advance(t, s);
#pragma omp barrier
            for (int t = tid; t < n_threads_; t += nt) output_range(ranges_[t], c);
        }
        return;
    }
#endif
    for (int t = 0; t < n_threads_; ++t) advance(t, s);
    for (const Range& r : ranges_) output_range(r, c);
}

void RealTimeController::run(const float* S, int n_steps, float* C, const float* gains) {
    if (n_steps <= 0) return;
    // The whole block is checked before the first step, so that a refused block leaves the
    // state as it was.
    require_finite(S, static_cast<std::ptrdiff_t>(n_steps) * n_slopes_, "slopes", n_slopes_);
    if (gains) require_finite(gains, static_cast<std::ptrdiff_t>(n_steps) * n_states_, "state_gains", n_states_);
    using MapR = Eigen::Map<const RowMatrixXf>;
    using MapW = Eigen::Map<RowMatrixXf>;
    const int chunk = 1024;
    RowMatrixXf U, Z;  // U: chunk x n_input_rows, Z: chunk x n_output_states
    for (int k0 = 0; k0 < n_steps; k0 += chunk) {
        const int m = std::min(chunk, n_steps - k0);
        MapR Sk(S + static_cast<long>(k0) * n_slopes_, m, n_slopes_);
        U.noalias() = Sk * xi_.transpose();  // all inputs of the chunk at once (GEMM)
        Z.resize(m, sigma_cols_.size());
        for (int k = 0; k < m; ++k) {
            const float* dk = gains ? gains + static_cast<long>(k0 + k) * n_states_ : delta_.data();
            for (Range& r : ranges_) update_range(r, U.row(k).data(), dk);
            Z.row(k) = zout_.transpose();
        }
        MapW Ck(C + static_cast<long>(k0) * n_commands_, m, n_commands_);
        Ck.noalias() = Z * sigma_.transpose();  // all commands of the chunk at once (GEMM)
    }
    if (gains) delta_ = Eigen::Map<const Eigen::VectorXf>(gains + static_cast<long>(n_steps - 1) * n_states_, n_states_);
}

}  // namespace soulctl
