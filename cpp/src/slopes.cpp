#include "soulctl/slopes.hpp"

#include "soulctl/finite.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>

namespace soulctl {

SlopeComputer::SlopeComputer(const std::vector<int64_t>& rows, const std::vector<int64_t>& cols,
                             int frame_rows, int frame_cols, Normalization norm)
    : frame_rows_(frame_rows), frame_cols_(frame_cols), norm_(norm) {
    if (frame_rows <= 0 || frame_cols <= 0)
        throw std::invalid_argument("frame shape must be positive, got (" + std::to_string(frame_rows) +
                                    ", " + std::to_string(frame_cols) + ")");
    if (rows.size() != cols.size() || rows.size() % 4 != 0 || rows.empty())
        throw std::invalid_argument("pixels must hold 4 (row, col) pairs per sub-aperture and at least one sub-aperture");
    if (static_cast<int64_t>(frame_rows) * frame_cols > INT32_MAX)
        throw std::invalid_argument("frame shape (" + std::to_string(frame_rows) + ", " + std::to_string(frame_cols) +
                                    ") has more than 2^31-1 pixels");
    n_sub_ = static_cast<int>(rows.size() / 4);
    for (int q = 0; q < 4; ++q) {
        index_[q].resize(n_sub_);
        background_[q].assign(n_sub_, 0.0f);
    }
    for (size_t k = 0; k < rows.size(); ++k) {
        if (rows[k] < 0 || rows[k] >= frame_rows || cols[k] < 0 || cols[k] >= frame_cols)
            throw std::invalid_argument("pixel (" + std::to_string(rows[k]) + ", " + std::to_string(cols[k]) +
                                        ") of sub-aperture " + std::to_string(k / 4) + " is outside the frame of shape (" +
                                        std::to_string(frame_rows) + ", " + std::to_string(frame_cols) + ")");
        index_[k % 4][k / 4] = static_cast<int32_t>(rows[k] * frame_cols + cols[k]);  // < 2^31: checked above
    }
    for (int q = 0; q < 4; ++q) {
        intensity_[q].assign(n_sub_, 0.0f);
        for (int i = 0; i < n_sub_; ++i) {
            if (i > 0 && index_[q][i] == index_[q][i - 1] + 1) ++runs_[q].back().length;
            else runs_[q].push_back({i, index_[q][i], 1});
        }
    }
    reference_.assign(2 * static_cast<size_t>(n_sub_), 0.0f);
    dx_.resize(n_sub_);
    dy_.resize(n_sub_);
    flux_.resize(n_sub_);
}

void SlopeComputer::set_background(const float* frame) {
    require_finite(frame, static_cast<std::ptrdiff_t>(frame_rows_) * frame_cols_, "background", frame_cols_);
    for (int q = 0; q < 4; ++q)
        for (int i = 0; i < n_sub_; ++i) background_[q][i] = frame[index_[q][i]];
    has_background_ = true;
}

void SlopeComputer::clear_background() {
    for (auto& b : background_) std::fill(b.begin(), b.end(), 0.0f);
    has_background_ = false;
}

void SlopeComputer::set_reference(const float* slopes) {
    require_finite(slopes, static_cast<std::ptrdiff_t>(reference_.size()), "reference");
    std::copy(slopes, slopes + reference_.size(), reference_.begin());
    largest_reference_ = 0.0;
    for (float r : reference_) largest_reference_ = std::max(largest_reference_, static_cast<double>(std::fabs(r)));
    has_reference_ = true;
}

void SlopeComputer::clear_reference() {
    std::fill(reference_.begin(), reference_.end(), 0.0f);
    largest_reference_ = 0.0;
    has_reference_ = false;
}

// Pixels are read run by run (sub-apertures along a detector row sit on contiguous pixels),
// so the loads and conversions vectorise; then the four images are combined element-wise.
template <typename T>
double SlopeComputer::gather(const T* frame, float& largest_difference) {
    for (int q = 0; q < 4; ++q) {
        float* iq = intensity_[q].data();
        const float* bq = background_[q].data();
        for (const Run& r : runs_[q]) {
            const T* src = frame + r.pixel;
            float* dst = iq + r.sub;
            const float* bg = bq + r.sub;
#pragma omp simd
            for (int j = 0; j < r.length; ++j) dst[j] = static_cast<float>(src[j]) - bg[j];
        }
    }
    const float *i1 = intensity_[0].data(), *i2 = intensity_[1].data(), *i3 = intensity_[2].data(),
                *i4 = intensity_[3].data();
    float* dx = dx_.data();
    float* dy = dy_.data();
    float* fl = flux_.data();
    double total = 0.0;
    float largest = 0.0f;  // max |dx|, |dy|: tells normalise() whether the slopes can overflow
    for (int b0 = 0; b0 < n_sub_; b0 += kBlock) {
        const int b1 = std::min(n_sub_, b0 + kBlock);
        float partial = 0.0f;  // short float sums, added in double
#pragma omp simd reduction(+ : partial) reduction(max : largest)
        for (int i = b0; i < b1; ++i) {
            dx[i] = (i1[i] + i2[i]) - (i3[i] + i4[i]);
            dy[i] = (i1[i] + i3[i]) - (i2[i] + i4[i]);
            fl[i] = (i1[i] + i2[i]) + (i3[i] + i4[i]);
            partial += fl[i];
            largest = std::max(largest, std::max(std::fabs(dx[i]), std::fabs(dy[i])));
        }
        total += partial;
    }
    largest_difference = largest;
    return total;
}

SlopeStatus SlopeComputer::normalise(double total, float largest_difference, float* out) {
    const int n = n_sub_;
    float* sx = out;
    float* sy = out + n;
    const float* rx = reference_.data();
    const float* ry = reference_.data() + n;
    SlopeStatus st;
    st.total_flux = total;
    if (norm_ == Normalization::Global) {
        const double mean = total / n;
        // A denormal mean passes "> 0" but its float reciprocal overflows: test the reciprocal.
        const float inv = static_cast<float>(1.0 / mean);
        // Negative pixels (after background) can make |dx| exceed the flux, and a large dx over
        // a tiny mean flux overflows: such a frame is unusable, like a dark one.  The bound is
        // checked once, in double, from the largest |dx|, |dy| and |reference|.
        st.flux_ok = (mean > 0.0) && std::isfinite(mean) && std::isfinite(inv) &&
                     static_cast<double>(largest_difference) / mean + largest_reference_ <=
                         std::numeric_limits<float>::max();
        if (!st.flux_ok) {
            std::fill(out, out + 2 * n, 0.0f);
            st.n_dark = n;
            return st;
        }
#pragma omp simd
        for (int i = 0; i < n; ++i) {
            sx[i] = dx_[i] * inv - rx[i];
            sy[i] = dy_[i] * inv - ry[i];
        }
    } else {
        for (int i = 0; i < n; ++i) {
            const float f = flux_[i];
            const float inv = 1.0f / f;
            const float x = dx_[i] * inv - rx[i], y = dy_[i] * inv - ry[i];
            const bool dark = !(f > 0.0f) || !std::isfinite(f) || !std::isfinite(x) || !std::isfinite(y);
            st.n_dark += dark;
            sx[i] = dark ? 0.0f : x;
            sy[i] = dark ? 0.0f : y;
        }
        st.flux_ok = st.n_dark == 0;
    }
    return st;
}

template <typename T>
SlopeStatus SlopeComputer::compute(const T* frame, float* out) {
    float largest_difference = 0.0f;
    const double total = gather(frame, largest_difference);
    status_ = normalise(total, largest_difference, out);
    return status_;
}

template SlopeStatus SlopeComputer::compute<float>(const float*, float*);
template SlopeStatus SlopeComputer::compute<uint16_t>(const uint16_t*, float*);

}  // namespace soulctl
