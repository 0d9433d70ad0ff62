#pragma once
// Image similarity inside a mask: NMI = (H(I) + H(J)) / H(I, J) (the seed's measure), with
// MI and NCC beside it for comparison. Images are single-channel float in [0, 1].
#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

namespace cf {

enum class SimilarityMetric { NMI, MI, NCC };
SimilarityMetric metric_from_name(const std::string& name);
const char* metric_name(SimilarityMetric m);

/// Joint-histogram similarity with reusable buffers. Not thread-safe: one per thread.
class Similarity {
public:
    explicit Similarity(int bins = 64) { set_bins(bins); }
    void set_bins(int bins);
    int bins() const { return bins_; }
    /// Linear (partial-volume) binning: each pair adds bilinear weights to the four bins
    /// around it, so the histogram and NMI change continuously with the images instead of
    /// in steps when a pixel crosses a bin edge (Maes et al. 1997). Smoother landscapes for
    /// the simplex, at about twice the cost of hard binning.
    void set_linear_binning(bool on) { linear_ = on; }
    /// a, b: CV_32F in [0, 1] (values outside are clamped); mask: CV_8U (non-zero counts) or empty.
    double nmi(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask);
    double mi(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask);
    double ncc(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask);
    double evaluate(SimilarityMetric m, const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask);

private:
    // Fills joint_ and returns the sample count.
    size_t joint_histogram(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask);
    size_t joint_histogram_linear(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask);
    void entropies(double& ha, double& hb, double& hab) const;
    bool linear_ = false;
    std::vector<float> joint_linear_;
    int bins_ = 64;
    std::vector<uint32_t> joint_;          // bins x bins
    std::vector<uint32_t> scratch_[4];      // interleaved histograms avoid store conflicts
    size_t n_ = 0;
};

/// Gaussian blur with a full width at half maximum given in millimetres at `depth_mm`
/// from a camera of focal length `focal_px`: sigma_px = FWHM / 2.3548 * f / depth.
void blur_fwhm_mm(const cv::Mat& src, cv::Mat& dst, double fwhm_mm, double focal_px, double depth_mm);
double fwhm_mm_to_sigma_px(double fwhm_mm, double focal_px, double depth_mm);
/// The same blur over the pixels where `valid_f` (CV_32F, 1 usable, 0 not) is 1 only, a
/// normalised convolution: blur(src * valid_f) / valid_blur, where `valid_blur` is
/// blur_fwhm_mm(valid_f) at the same FWHM (passed in, so a caller blurring many images against
/// one mask blurs the mask once). Unusable pixels' values never reach the result; pixels with no
/// usable one within reach (valid_blur under 1e-3) are 0. `scratch` is a reused buffer.
void blur_fwhm_mm_masked(const cv::Mat& src, const cv::Mat& valid_f, const cv::Mat& valid_blur, cv::Mat& dst,
                         double fwhm_mm, double focal_px, double depth_mm, cv::Mat& scratch);
/// The same blur, approximated on a coarser grid when it is wide (sigma >= 4 px): within a few
/// thousandths of the exact one on a [0, 1] image, at a fraction of its cost. For smooth
/// references (the sulcal hull), not for the images the metric compares.
void blur_fwhm_mm_coarse(const cv::Mat& src, cv::Mat& dst, double fwhm_mm, double focal_px, double depth_mm);

}  // namespace cf
