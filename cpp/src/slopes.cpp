#include "soulctl/slopes.hpp"

#include <cmath>
#include <stdexcept>
#include <string>

namespace soulctl {

SlopeComputer::SlopeComputer(const std::vector<int32_t>& rows, const std::vector<int32_t>& cols,
                             int frame_rows, int frame_cols, Normalization norm)
    : frame_rows_(frame_rows), frame_cols_(frame_cols), norm_(norm) {
    if (frame_rows <= 0 || frame_cols <= 0)
        throw std::invalid_argument("frame shape must be positive, got (" + std::to_string(frame_rows) +
                                    ", " + std::to_string(frame_cols) + ")");
    if (rows.size() != cols.size() || rows.size() % 4 != 0 || rows.empty())
        throw std::invalid_argument("pixels must hold 4 (row, col) pairs per sub-aperture and at least one sub-aperture");
    n_sub_ = static_cast<int>(rows.size() / 4);
    index_.resize(rows.size());
    for (size_t k = 0; k < rows.size(); ++k) {
        if (rows[k] < 0 || rows[k] >= frame_rows || cols[k] < 0 || cols[k] >= frame_cols)
            throw std::invalid_argument("pixel (" + std::to_string(rows[k]) + ", " + std::to_string(cols[k]) +
                                        ") of sub-aperture " + std::to_string(k / 4) + " is outside the frame of shape (" +
                                        std::to_string(frame_rows) + ", " + std::to_string(frame_cols) + ")");
        index_[k] = rows[k] * frame_cols + cols[k];
    }
    background_.assign(index_.size(), 0.0f);
    reference_.assign(2 * static_cast<size_t>(n_sub_), 0.0f);
    dx_.resize(n_sub_);
    dy_.resize(n_sub_);
    flux_.resize(n_sub_);
}

void SlopeComputer::set_background(const float* frame) {
    for (size_t k = 0; k < index_.size(); ++k) background_[k] = frame[index_[k]];
    has_background_ = true;
}

void SlopeComputer::clear_background() {
    std::fill(background_.begin(), background_.end(), 0.0f);
    has_background_ = false;
}

void SlopeComputer::set_reference(const float* slopes) {
    std::copy(slopes, slopes + reference_.size(), reference_.begin());
    has_reference_ = true;
}

void SlopeComputer::clear_reference() {
    std::fill(reference_.begin(), reference_.end(), 0.0f);
    has_reference_ = false;
}

template <typename T>
SlopeStatus SlopeComputer::compute(const T* frame, float* out) {
    const int n = n_sub_;
    const int32_t* idx = index_.data();
    const float* bg = background_.data();
    double total = 0.0;
    for (int i = 0; i < n; ++i) {
        const int k = 4 * i;
        const float i1 = static_cast<float>(frame[idx[k]]) - bg[k];
        const float i2 = static_cast<float>(frame[idx[k + 1]]) - bg[k + 1];
        const float i3 = static_cast<float>(frame[idx[k + 2]]) - bg[k + 2];
        const float i4 = static_cast<float>(frame[idx[k + 3]]) - bg[k + 3];
        dx_[i] = (i1 + i2) - (i3 + i4);
        dy_[i] = (i1 + i3) - (i2 + i4);
        flux_[i] = (i1 + i2) + (i3 + i4);
        total += flux_[i];
    }
    SlopeStatus st;
    st.total_flux = total;
    float* sx = out;
    float* sy = out + n;
    const float* rx = reference_.data();
    const float* ry = reference_.data() + n;
    if (norm_ == Normalization::Global) {
        const double mean = total / n;
        // A denormal mean passes "> 0" but its float reciprocal overflows: test the reciprocal.
        const float inv = static_cast<float>(1.0 / mean);
        if (!(mean > 0.0) || !std::isfinite(mean) || !std::isfinite(inv)) {
            std::fill(out, out + 2 * n, 0.0f);
            st.flux_ok = false;
            st.n_dark = n;
        } else {
            for (int i = 0; i < n; ++i) {
                sx[i] = dx_[i] * inv - rx[i];
                sy[i] = dy_[i] * inv - ry[i];
            }
        }
    } else {
        for (int i = 0; i < n; ++i) {
            const float f = flux_[i];
            const float inv = 1.0f / f;
            if (!(f > 0.0f) || !std::isfinite(f) || !std::isfinite(inv)) {
                sx[i] = 0.0f;
                sy[i] = 0.0f;
                ++st.n_dark;
            } else {
                sx[i] = dx_[i] * inv - rx[i];
                sy[i] = dy_[i] * inv - ry[i];
            }
        }
        st.flux_ok = st.n_dark == 0;
    }
    status_ = st;
    return st;
}

template SlopeStatus SlopeComputer::compute<float>(const float*, float*);
template SlopeStatus SlopeComputer::compute<uint16_t>(const uint16_t*, float*);

}  // namespace soulctl
