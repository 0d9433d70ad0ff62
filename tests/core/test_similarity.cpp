// Similarity measures and the FWHM blur of core/similarity.hpp, against their definitions.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/similarity.hpp"

namespace {

cv::Mat noise_image(int w, int h, uint64_t seed) {
    // std::mt19937: cv::RNG streams from small neighbouring seeds are correlated.
    cv::Mat m(h, w, CV_32F);
    std::mt19937 rng{static_cast<uint32_t>(seed)};
    std::uniform_real_distribution<float> u(0.f, 1.f);
    for (int i = 0; i < w * h; ++i) m.ptr<float>()[i] = u(rng);
    return m;
}

// Entropies from a hard-binned joint histogram written out here, independently of the class.
double nmi_by_definition(const cv::Mat& a, const cv::Mat& b, int bins) {
    std::vector<double> joint(size_t(bins) * bins, 0.0), pa(size_t(bins), 0.0), pb(size_t(bins), 0.0);
    const int n = a.rows * a.cols;
    const float scale = float(bins) - 1e-3f;  // a value of exactly 1 lands in the last bin
    for (int i = 0; i < n; ++i) {
        const int ia = int(a.ptr<float>()[i] * scale);
        const int ib = int(b.ptr<float>()[i] * scale);
        joint[size_t(ia) * bins + ib] += 1.0 / n;
        pa[size_t(ia)] += 1.0 / n;
        pb[size_t(ib)] += 1.0 / n;
    }
    auto H = [](const std::vector<double>& p) {
        double h = 0;
        for (double x : p)
            if (x > 0) h -= x * std::log(x);
        return h;
    };
    return (H(pa) + H(pb)) / H(joint);
}

}  // namespace

TEST(Similarity, NmiMatchesItsDefinitionAndIsTwoForIdenticalImages) {
    const cv::Mat a = noise_image(120, 80, 1);
    cf::Similarity s(32);
    EXPECT_NEAR(s.nmi(a, a, cv::Mat()), 2.0, 1e-9);
    // A monotone remapping keeps all the information: still 2 with hard bins of 1/32 when
    // the remap keeps each bin's values within one bin (here: a permutation of whole bins).
    cv::Mat flipped = 1.0f - a;
    flipped = cv::max(cv::min(flipped, 1.0f - 1e-6f), 0.0f);
    EXPECT_GT(s.nmi(a, flipped, cv::Mat()), 1.9);
    const cv::Mat b = noise_image(120, 80, 2);
    EXPECT_NEAR(s.nmi(a, b, cv::Mat()), nmi_by_definition(a, b, 32), 1e-6);
    // Independent images: close to 1 (with few bins; 9600 pixels fill 32 x 32 joint bins too
    // sparsely, which underestimates the joint entropy).
    cf::Similarity s8(8);
    EXPECT_NEAR(s8.nmi(a, b, cv::Mat()), nmi_by_definition(a, b, 8), 1e-6);
    EXPECT_LT(s8.nmi(a, b, cv::Mat()), 1.01);
    // MI of an image with itself is its entropy (log 32 for uniform noise, within sampling).
    EXPECT_NEAR(s.mi(a, a, cv::Mat()), std::log(32.0), 0.05);
    EXPECT_NEAR(s.ncc(a, a, cv::Mat()), 1.0, 1e-6);
    EXPECT_NEAR(s.ncc(a, 1.0f - a, cv::Mat()), -1.0, 1e-6);
}

TEST(Similarity, OnlyMaskedPixelsCount) {
    const cv::Mat a = noise_image(100, 100, 3);
    cv::Mat b = a.clone();
    // Outside the left half, b is unrelated noise.
    noise_image(50, 100, 4).copyTo(b(cv::Rect(50, 0, 50, 100)));
    cv::Mat mask = cv::Mat::zeros(100, 100, CV_8U);
    mask(cv::Rect(0, 0, 50, 100)).setTo(1);
    cf::Similarity s(16);
    EXPECT_NEAR(s.nmi(a, b, mask), 2.0, 1e-9);
    EXPECT_LT(s.nmi(a, b, cv::Mat()), 1.9);
    EXPECT_NEAR(s.ncc(a, b, mask), 1.0, 1e-6);
}

TEST(Similarity, LinearBinningChangesContinuously) {
    const cv::Mat a = noise_image(80, 60, 5);
    cf::Similarity s(32);
    s.set_linear_binning(true);
    // A tiny intensity shift moves pixels across bin edges: with linear binning the value
    // moves by a tiny amount too.
    const double n0 = s.nmi(a, a, cv::Mat());
    cv::Mat shifted = cv::min(a + 1e-4f, 1.0f);
    const double n1 = s.nmi(a, shifted, cv::Mat());
    EXPECT_NEAR(n0, n1, 2e-3);
    EXPECT_GT(n0, 1.5);
}

TEST(Blur, FwhmInMillimetresBecomesSigmaInPixels) {
    // 2.3548 = 2 sqrt(2 ln 2); at 200 mm with f = 800 px, 1 mm is 4 px.
    EXPECT_NEAR(cf::fwhm_mm_to_sigma_px(2.3548, 800, 200), 4.0, 1e-3);
    const cv::Mat a = noise_image(64, 48, 6);
    cv::Mat d;
    cf::blur_fwhm_mm(a, d, 0.01, 800, 200);  // sigma < 0.3 px: a copy
    EXPECT_EQ(cv::norm(a, d, cv::NORM_INF), 0.0);
    // blur_fwhm_mm is OpenCV's Gaussian itself, at any width; the coarse variant too when narrow.
    for (double fwhm_mm : {1.0, 5.0}) {
        cv::Mat ref, coarse;
        const double sigma = cf::fwhm_mm_to_sigma_px(fwhm_mm, 800, 200);
        cv::GaussianBlur(a, ref, cv::Size(0, 0), sigma, sigma, cv::BORDER_REPLICATE);
        cf::blur_fwhm_mm(a, d, fwhm_mm, 800, 200);
        EXPECT_EQ(cv::norm(ref, d, cv::NORM_INF), 0.0);
        cf::blur_fwhm_mm_coarse(a, coarse, fwhm_mm, 800, 200);
        if (sigma < 4.0) {
            EXPECT_EQ(cv::norm(ref, coarse, cv::NORM_INF), 0.0);
        }
    }
}

// RegistrationParams::masked_blur: gauze, blood and glare, which the photo's mask drops, must
// not spread their light into the usable pixels around them.
TEST(Blur, TheMaskedBlurNeverReadsUnusablePixels) {
    const cv::Mat a = noise_image(96, 64, 11);
    cv::Mat valid(a.size(), CV_32F, cv::Scalar(1.f));
    valid(cv::Rect(30, 20, 25, 18)).setTo(0.f);  // a patch of gauze
    valid(cv::Rect(0, 0, 6, 64)).setTo(0.f);     // a drape along the edge
    const double fwhm_mm = 4.0;                  // sigma 6.8 px at 4 px per mm
    cv::Mat valid_blur, d, scratch;
    cf::blur_fwhm_mm(valid, valid_blur, fwhm_mm, 800, 200);
    cf::blur_fwhm_mm_masked(a, valid, valid_blur, d, fwhm_mm, 800, 200, scratch);
    // Anything painted where the mask is 0 leaves the result at every usable pixel as it was.
    cv::Mat painted = a.clone();
    painted.setTo(5.f, valid == 0.f);
    cv::Mat d2;
    cf::blur_fwhm_mm_masked(painted, valid, valid_blur, d2, fwhm_mm, 800, 200, scratch);
    EXPECT_LT(cv::norm(d, d2, cv::NORM_INF, valid != 0.f), 1e-5);
    // The plain blur is not so: the paint reaches the pixels next to the patch.
    cv::Mat p1, p2;
    cf::blur_fwhm_mm(a, p1, fwhm_mm, 800, 200);
    cf::blur_fwhm_mm(painted, p2, fwhm_mm, 800, 200);
    EXPECT_GT(cv::norm(p1, p2, cv::NORM_INF, valid != 0.f), 0.5);
    // A constant over the usable pixels stays that constant there, whatever lies beside it.
    cv::Mat flat(a.size(), CV_32F, cv::Scalar(0.25f));
    flat.setTo(1.f, valid == 0.f);
    cf::blur_fwhm_mm_masked(flat, valid, valid_blur, d, fwhm_mm, 800, 200, scratch);
    EXPECT_LT(cv::norm(d - 0.25f, cv::NORM_INF, valid != 0.f), 1e-5);
    // With every pixel usable it is the plain blur, up to rounding.
    cv::Mat all(a.size(), CV_32F, cv::Scalar(1.f)), all_blur;
    cf::blur_fwhm_mm(all, all_blur, fwhm_mm, 800, 200);
    cf::blur_fwhm_mm_masked(a, all, all_blur, d, fwhm_mm, 800, 200, scratch);
    EXPECT_LT(cv::norm(d, p1, cv::NORM_INF), 1e-5);
}

TEST(Blur, WideBlursOnACoarserGridStayCloseToTheFullSizeGaussian) {
    // A smooth picture with edges (a rendered brain has both) and the sigmas of the 12 mm
    // high-pass at registration sizes (4-8 px) and of a close DSLR view (~30 px).
    cv::Mat a(250, 375, CV_32F);
    for (int y = 0; y < a.rows; ++y)
        for (int x = 0; x < a.cols; ++x)
            a.at<float>(y, x) = 0.5f + 0.3f * std::sin(x * 0.05f) * std::cos(y * 0.07f) + (x > 190 && y > 90 ? 0.2f : 0.f);
    cv::add(a, noise_image(375, 250, 7) * 0.1f, a);
    for (double sigma : {4.0, 5.5, 8.0, 30.0}) {
        const double fwhm_mm = sigma * 2.0 * std::sqrt(2.0 * std::log(2.0)) / 4.0;  // 4 px per mm
        cv::Mat d, ref;
        cf::blur_fwhm_mm_coarse(a, d, fwhm_mm, 800, 200);
        cv::GaussianBlur(a, ref, cv::Size(0, 0), sigma, sigma, cv::BORDER_REPLICATE);
        ASSERT_EQ(d.size(), a.size());
        ASSERT_EQ(d.type(), CV_32F);
        const cv::Rect inner(int(2 * sigma), int(2 * sigma), a.cols - int(4 * sigma), a.rows - int(4 * sigma));
        const double mean_abs = cv::mean(cv::abs(d - ref))[0];
        const double max_inner = cv::norm(d(inner), ref(inner), cv::NORM_INF);
        // The image spans ~1.0; a grey level is 1/255 ~ 0.004.
        EXPECT_LT(mean_abs, 0.004) << "sigma " << sigma;
        EXPECT_LT(max_inner, 0.012) << "sigma " << sigma;
    }
}
