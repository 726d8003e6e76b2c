// The SOUL real-time controller equation (paper, Eq. stateRTC):
//     zeta(k) = Lambda zeta(k-1) + Delta Xi s(k)
//     c(k)    = Sigma zeta(k)
// Lambda, Xi, Sigma are fixed at construction; Delta (diagonal gains) may change between
// any two steps.  Working precision is float32.
//
// Every float input must be finite (soulctl/finite.hpp): Lambda, Xi, Sigma, the gains of
// set_state_gains() and run(), the slopes of step() and run().  A NaN or infinity throws
// std::invalid_argument naming the argument before anything changes, so one bad frame never
// poisons the integrators: the state, Delta and the outputs are as before the call.
//
// Structure is found once, at construction, and exploited at every step:
//  * Lambda is split into its diagonal blocks (connected components of its non-zero
//    pattern): 1x1 blocks (forgetting factors) become an element-wise product, larger
//    blocks (the IIR filters) small dense products.
//  * Rows of Xi that are entirely zero (IIR states that do not take the input) and
//    columns of Sigma that are entirely zero (states that are not an output) are dropped.
//  * With n_threads > 1 the state is split into contiguous ranges on block boundaries,
//    balancing the Xi rows; each OpenMP thread updates its range, then, after a barrier,
//    computes a slice of the commands (rows of Sigma: long dot products, which measured
//    faster than splitting Sigma by columns and summing partial commands).
#pragma once

#include <Eigen/Dense>
#include <string>
#include <vector>

namespace soulctl {

using RowMatrixXf = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

struct LambdaBlock {
    int offset;
    int size;
    RowMatrixXf a;  // size x size
};

class RealTimeController {
public:
    // n_threads: OpenMP threads for step(), 0 = automatic (OpenMP's maximum, at most 4), else
    // 1..kMaxThreads; anything else throws std::invalid_argument (n_threads_error).  Fewer may
    // be used (no more ranges than the state's blocks allow; one without OpenMP): n_threads().
    static constexpr int kMaxThreads = 64;

    RealTimeController(const RowMatrixXf& lambda, const RowMatrixXf& xi, const RowMatrixXf& sigma,
                       int n_threads);

    int n_states() const { return n_states_; }
    int n_slopes() const { return n_slopes_; }
    int n_commands() const { return n_commands_; }
    int n_threads() const { return n_threads_; }

    void set_state_gains(const float* delta);  // n_states finite values, the diagonal of Delta
    const Eigen::VectorXf& state_gains() const { return delta_; }
    const Eigen::VectorXf& state() const { return zeta_; }
    void reset();

    // One frame: s (n_slopes, finite) -> c (n_commands).
    void step(const float* s, float* c);

    // A block of frames for offline replays: S is n_steps x n_slopes (row-major), C receives
    // n_steps x n_commands.  gains, when not null, is n_steps x n_states: Delta at each step.
    // Leaves the controller in the state it would have after the same steps one by one.  The
    // whole block (S and gains) is checked before the first step: refused, nothing changes.
    void run(const float* S, int n_steps, float* C, const float* gains);

    // Structure found at construction (for reports and tests).
    int n_diagonal_states() const { return static_cast<int>(diag_index_.size()); }
    const std::vector<LambdaBlock>& blocks() const { return blocks_; }
    int n_input_rows() const { return static_cast<int>(xi_rows_.size()); }
    int n_output_states() const { return static_cast<int>(sigma_cols_.size()); }

private:
    struct Range {
        int state_begin, state_end;  // [begin, end) in state space
        int xi_begin, xi_end;        // rows of the compressed Xi
        int out_begin, out_end;      // entries of the compressed output-state vector
        int cmd_begin, cmd_end;      // rows of Sigma (commands)
        std::vector<int> diag;       // diagonal states in this range
        std::vector<int> blocks;     // indices into blocks_
        Eigen::VectorXf scratch;     // largest block of this range
    };

    void update_range(Range& r, const float* u, const float* delta);
    void input_range(const Range& r, const float* s);   // u = Xi s on the range's rows
    void output_range(const Range& r, float* c) const;  // c = Sigma zeta on the range's commands
    void advance(int r, const float* s);                // input_range + update_range of range r

    int n_states_, n_slopes_, n_commands_, n_threads_;
    Eigen::VectorXf lambda_diag_;      // n_states (only used on diagonal states)
    std::vector<int> diag_index_;      // states whose block is 1x1
    std::vector<LambdaBlock> blocks_;  // blocks larger than 1x1
    std::vector<int> xi_rows_;         // state index of each compressed Xi row
    std::vector<int> xi_pos_;          // n_states: row in compressed Xi or -1
    RowMatrixXf xi_;                   // n_input_rows x n_slopes
    std::vector<int> sigma_cols_;      // state index of each compressed Sigma column
    RowMatrixXf sigma_;                // n_commands x n_output_states
    std::vector<Range> ranges_;

    Eigen::VectorXf delta_;   // n_states
    Eigen::VectorXf zeta_;    // n_states
    Eigen::VectorXf u_;       // n_input_rows: Xi s
    Eigen::VectorXf zout_;    // n_output_states: zeta at the output states
};

// The message for an n_threads outside 0..kMaxThreads (`given` as the caller wrote it).
inline std::string n_threads_error(const std::string& given) {
    return "n_threads: expected an integer in 0.." + std::to_string(RealTimeController::kMaxThreads) +
           " (0 = automatic), got " + given;
}

}  // namespace soulctl
