// PWFS slope computation from a detector frame (the first half of the real-time path).
//
// Quadrant convention (documented in docs/physics.md): the four pupil images of a
// sub-aperture are numbered 1..4 with
//   1 = (+x, +y)   2 = (+x, -y)   3 = (-x, +y)   4 = (-x, -y)
// where +x is increasing column index and +y is increasing row index of the frame, so
//   sx = (I1 + I2 - I3 - I4) / N,   sy = (I1 - I2 + I3 - I4) / N.
// N is either the mean flux per valid sub-aperture (global normalisation, the default)
// or the sub-aperture's own flux.  The output vector is [sx_0..sx_{n-1}, sy_0..sy_{n-1}].
//
// Settings must be finite (soulctl/finite.hpp): the background frame (every pixel) and the
// reference slopes; a NaN or infinity throws std::invalid_argument naming the argument and
// keeps the background/reference in use.  Frames are data: a non-finite pixel, like zero or
// negative flux, makes light unusable instead of raising: with Subaperture normalisation its
// sub-aperture is dark (zero slopes, counted in n_dark); with Global normalisation the mean
// flux is not finite, so the whole frame is dark (all slopes zero, n_dark = n_sub).  Either
// way flux_ok is false and the slopes are finite.  Pixels outside the sub-apertures are never read.
#pragma once

#include <cstdint>
#include <vector>

namespace soulctl {

enum class Normalization { Global, Subaperture };

struct SlopeStatus {
    double total_flux = 0.0;  // background-subtracted flux summed over valid sub-apertures
    bool flux_ok = true;      // false when the normalising flux was zero, negative or not finite,
                              // or the slopes overflowed (then they are all zero)
    int n_dark = 0;           // sub-apertures whose slopes were set to zero for lack of flux
};

class SlopeComputer {
public:
    // pixels: n_sub*4 (row, col) pairs, sub-aperture major, pupil image 1..4 minor.
    SlopeComputer(const std::vector<int64_t>& rows, const std::vector<int64_t>& cols,
                  int frame_rows, int frame_cols, Normalization norm);

    int n_subapertures() const { return n_sub_; }
    int frame_rows() const { return frame_rows_; }
    int frame_cols() const { return frame_cols_; }
    Normalization normalization() const { return norm_; }

    // background: a full frame (frame_rows*frame_cols, all finite); only the used pixels are kept.
    void set_background(const float* frame);
    void clear_background();
    bool has_background() const { return has_background_; }

    // reference slopes (2*n_sub, finite), subtracted after normalisation.
    void set_reference(const float* slopes);
    void clear_reference();
    bool has_reference() const { return has_reference_; }

    // Computes 2*n_sub slopes into out. T is float or uint16_t.
    template <typename T>
    SlopeStatus compute(const T* frame, float* out);

    const std::vector<float>& subaperture_flux() const { return flux_; }
    const SlopeStatus& last_status() const { return status_; }

private:
    // compute() = gather (pixels -> dx, dy, flux; the total flux and max |dx|, |dy|), normalise.
    template <typename T>
    double gather(const T* frame, float& largest_difference);
    SlopeStatus normalise(double total_flux, float largest_difference, float* out);
    static constexpr int kBlock = 256;  // the flux is summed in float over blocks, then in double

    int n_sub_;
    int frame_rows_, frame_cols_;
    Normalization norm_;
    struct Run {  // sub-apertures [sub, sub+length) of one pupil image sit on contiguous pixels
        int sub, pixel, length;
    };
    std::vector<int32_t> index_[4];    // flat pixel index of pupil image q of each sub-aperture
    std::vector<Run> runs_[4];         // the same as runs of contiguous pixels
    std::vector<float> intensity_[4];  // I_q of each sub-aperture in the last frame
    std::vector<float> background_[4]; // background at those pixels
    std::vector<float> reference_;     // 2*n_sub
    std::vector<float> dx_, dy_, flux_;
    bool has_background_ = false;
    bool has_reference_ = false;
    double largest_reference_ = 0.0;  // max |reference slope|
    SlopeStatus status_;
};

}  // namespace soulctl
