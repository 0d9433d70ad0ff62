#include "cortexfuse/core/similarity.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "cortexfuse/core/error.hpp"

namespace cf {

SimilarityMetric metric_from_name(const std::string& n) {
    if (n == "nmi") return SimilarityMetric::NMI;
    if (n == "mi") return SimilarityMetric::MI;
    if (n == "ncc") return SimilarityMetric::NCC;
    throw InputError("metric \"" + n + "\"", "unknown (nmi, mi, ncc)");
}

const char* metric_name(SimilarityMetric m) {
    switch (m) {
        case SimilarityMetric::NMI: return "nmi";
        case SimilarityMetric::MI: return "mi";
        case SimilarityMetric::NCC: return "ncc";
    }
    return "?";
}

void Similarity::set_bins(int bins) {
    if (bins < 2 || bins > 1024) throw std::invalid_argument("Similarity: bins must be 2..1024");
    bins_ = bins;
    joint_.assign(size_t(bins) * bins, 0);
    for (auto& s : scratch_) s.assign(size_t(bins) * bins, 0);
}

namespace {

/// Calls add(va, vb, count) for every pixel pair where the mask is set (all when empty), values
/// clamped to [0, 1]; returns how many. The one traversal both binnings share.
template <class Add>
size_t for_each_masked_pair(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask, Add&& add) {
    CV_Assert(a.type() == CV_32F && b.type() == CV_32F && a.size() == b.size());
    CV_Assert(mask.empty() || (mask.type() == CV_8U && mask.size() == a.size()));
    size_t count = 0;
    for (int y = 0; y < a.rows; ++y) {
        const float* pa = a.ptr<float>(y);
        const float* pb = b.ptr<float>(y);
        const uint8_t* pm = mask.empty() ? nullptr : mask.ptr<uint8_t>(y);
        for (int x = 0; x < a.cols; ++x) {
            if (pm && !pm[x]) continue;
            add(std::clamp(pa[x], 0.f, 1.f), std::clamp(pb[x], 0.f, 1.f), count);
            ++count;
        }
    }
    return count;
}

}  // namespace

size_t Similarity::joint_histogram(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
    for (auto& s : scratch_) std::fill(s.begin(), s.end(), 0u);
    const float scale = float(bins_) - 1e-3f;
    const int B = bins_;
    const size_t count = for_each_masked_pair(a, b, mask, [&](float va, float vb, size_t k) {
        ++scratch_[k & 3][size_t(int(va * scale) * B + int(vb * scale))];
    });
    for (size_t i = 0; i < joint_.size(); ++i) joint_[i] = scratch_[0][i] + scratch_[1][i] + scratch_[2][i] + scratch_[3][i];
    n_ = count;
    return count;
}

size_t Similarity::joint_histogram_linear(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
    const int B = bins_;
    joint_linear_.assign(size_t(B) * B, 0.f);
    // Bin centres at 0 .. B-1 over [0, 1]: value v sits at v * (B - 1).
    const float scale = float(B - 1);
    float* h = joint_linear_.data();
    const size_t count = for_each_masked_pair(a, b, mask, [&](float va, float vb, size_t) {
        const float fa = va * scale, fb = vb * scale;
        const int ia = std::min(int(fa), B - 2), ib = std::min(int(fb), B - 2);
        const float wa = fa - float(ia), wb = fb - float(ib);
        float* row0 = h + size_t(ia) * B + ib;
        float* row1 = row0 + B;
        row0[0] += (1 - wa) * (1 - wb);
        row0[1] += (1 - wa) * wb;
        row1[0] += wa * (1 - wb);
        row1[1] += wa * wb;
    });
    n_ = count;
    return count;
}

void Similarity::entropies(double& ha, double& hb, double& hab) const {
    ha = hb = hab = 0;
    if (n_ == 0) return;
    const double inv = 1.0 / double(n_);
    const int B = bins_;
    std::vector<double> ma(size_t(B), 0.0), mb(size_t(B), 0.0);
    for (int i = 0; i < B; ++i)
        for (int j = 0; j < B; ++j) {
            const double c = linear_ ? double(joint_linear_[size_t(i * B + j)]) : double(joint_[size_t(i * B + j)]);
            if (c <= 0) continue;
            const double p = c * inv;
            hab -= p * std::log(p);
            ma[size_t(i)] += p;
            mb[size_t(j)] += p;
        }
    for (int i = 0; i < B; ++i) {
        if (ma[size_t(i)] > 0) ha -= ma[size_t(i)] * std::log(ma[size_t(i)]);
        if (mb[size_t(i)] > 0) hb -= mb[size_t(i)] * std::log(mb[size_t(i)]);
    }
}

double Similarity::nmi(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
    if ((linear_ ? joint_histogram_linear(a, b, mask) : joint_histogram(a, b, mask)) < 2) return 1.0;
    double ha, hb, hab;
    entropies(ha, hb, hab);
    return hab > 0 ? (ha + hb) / hab : 1.0;  // two constant images: no information either way
}

double Similarity::mi(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
    if ((linear_ ? joint_histogram_linear(a, b, mask) : joint_histogram(a, b, mask)) < 2) return 0.0;
    double ha, hb, hab;
    entropies(ha, hb, hab);
    return ha + hb - hab;
}

double Similarity::ncc(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
    CV_Assert(a.type() == CV_32F && b.type() == CV_32F && a.size() == b.size());
    double sa = 0, sb = 0, saa = 0, sbb = 0, sab = 0;
    size_t n = 0;
    for (int y = 0; y < a.rows; ++y) {
        const float* pa = a.ptr<float>(y);
        const float* pb = b.ptr<float>(y);
        const uint8_t* pm = mask.empty() ? nullptr : mask.ptr<uint8_t>(y);
        for (int x = 0; x < a.cols; ++x) {
            if (pm && !pm[x]) continue;
            const double u = pa[x], v = pb[x];
            sa += u; sb += v; saa += u * u; sbb += v * v; sab += u * v;
            ++n;
        }
    }
    if (n < 2) return 0.0;
    const double ma = sa / n, mb = sb / n;
    const double va = saa / n - ma * ma, vb = sbb / n - mb * mb;
    if (va <= 1e-12 || vb <= 1e-12) return 0.0;
    return (sab / n - ma * mb) / std::sqrt(va * vb);
}

double Similarity::evaluate(SimilarityMetric m, const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
    switch (m) {
        case SimilarityMetric::NMI: return nmi(a, b, mask);
        case SimilarityMetric::MI: return mi(a, b, mask);
        case SimilarityMetric::NCC: return ncc(a, b, mask);
    }
    return 0;
}

double fwhm_mm_to_sigma_px(double fwhm_mm, double focal_px, double depth_mm) {
    return fwhm_mm / (2.0 * std::sqrt(2.0 * std::log(2.0))) * focal_px / std::max(depth_mm, 1e-6);
}

void blur_fwhm_mm(const cv::Mat& src, cv::Mat& dst, double fwhm_mm, double focal_px, double depth_mm) {
    const double sigma = fwhm_mm_to_sigma_px(fwhm_mm, focal_px, depth_mm);
    if (sigma < 0.3) {
        src.copyTo(dst);
        return;
    }
    cv::GaussianBlur(src, dst, cv::Size(0, 0), sigma, sigma, cv::BORDER_REPLICATE);
}

void blur_fwhm_mm_masked(const cv::Mat& src, const cv::Mat& valid_f, const cv::Mat& valid_blur, cv::Mat& dst,
                         double fwhm_mm, double focal_px, double depth_mm, cv::Mat& scratch) {
    CV_Assert(src.type() == CV_32F && valid_f.type() == CV_32F && valid_blur.type() == CV_32F);
    CV_Assert(src.size() == valid_f.size() && src.size() == valid_blur.size());
    cv::multiply(src, valid_f, scratch);
    blur_fwhm_mm(scratch, dst, fwhm_mm, focal_px, depth_mm);
    const float* w = valid_blur.ptr<float>();
    float* d = dst.ptr<float>();
    const size_t n = dst.total();
    for (size_t i = 0; i < n; ++i) d[i] = w[i] > 1e-3f ? d[i] / w[i] : 0.f;
}

void blur_fwhm_mm_coarse(const cv::Mat& src, cv::Mat& dst, double fwhm_mm, double focal_px, double depth_mm) {
    const double sigma = fwhm_mm_to_sigma_px(fwhm_mm, focal_px, depth_mm);
    if (sigma < 4.0) {
        blur_fwhm_mm(src, dst, fwhm_mm, focal_px, depth_mm);
        return;
    }
    // On a grid f times coarser: area-averaging down and bilinear interpolation up add a
    // variance of about (f^2 - 1) / 4 px^2, taken off the Gaussian's. OpenCV's separable
    // kernel has ~8 sigma taps a pixel and pass, which for the 12 mm sulcal hull (sigma 4-8 px
    // at registration sizes, ~30 px on a close DSLR view) costs more than the ray cast of a
    // small frame; here it costs a fraction of that.
    const int f = std::clamp(int(sigma / 2.0), 2, 16);
    const cv::Size small_size(std::max(1, (src.cols + f - 1) / f), std::max(1, (src.rows + f - 1) / f));
    cv::Mat small;
    cv::resize(src, small, small_size, 0, 0, cv::INTER_AREA);
    const double sigma_small = std::sqrt(std::max(sigma * sigma - (f * f - 1) / 4.0, 0.25)) / f;
    cv::GaussianBlur(small, small, cv::Size(0, 0), sigma_small, sigma_small, cv::BORDER_REPLICATE);
    cv::resize(small, dst, src.size(), 0, 0, cv::INTER_LINEAR);
}

}  // namespace cf
