// Public skull-stripping API over the ITK pipeline (itk_skull_strip.cpp), and its check image.
#include "cortexfuse/core/skull_strip.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/error.hpp"
#include "bet_surface.hpp"
#include "itk_skull_strip.hpp"

namespace cf {

namespace {

// Working spacing: anisotropic scans (thick DICOM slices) are resampled to an isotropic grid,
// because both the surface model and the distance-map morphology assume similar reach in every
// direction. Returns 0 when the volume is used as it is.
double working_spacing_mm(const VolumeGeometry& g) {
    const double lo = g.spacing_mm.minCoeff(), hi = g.spacing_mm.maxCoeff();
    if (hi <= 1.3 * lo) return 0.0;
    return std::clamp(std::cbrt(g.spacing_mm.prod()), 1.0, 2.0);
}

}  // namespace

LabelVolume skull_strip(const Volume& t1, const SkullStripParams& p, const Progress* progress,
                        SkullStripInfo* info) {
    const std::string kName = "skull strip";
    if (t1.voxels.size() != t1.geom.voxel_count() || t1.voxels.empty())
        throw InputError(kName, "volume voxels do not match its dimensions");
    float lo = t1.voxels.front(), hi = t1.voxels.front();
    for (float x : t1.voxels) {
        if (!std::isfinite(x)) throw InputError(kName, "volume holds NaN or infinite intensities");
        lo = std::min(lo, x);
        hi = std::max(hi, x);
    }
    for (int a = 0; a < 3; ++a)
        if (t1.geom.dims[a] < 8)
            throw InputError(kName, "volume too small (" + std::to_string(t1.geom.dims[a]) +
                                        " voxels along an axis) to hold a head");
    // Before any work: the surface model alone would spend seconds (16-30 s under the sanitizers)
    // evolving over a volume with nothing in it. A nearly constant one is caught after it, on
    // the robust range (itk_skull_strip.cpp).
    if (lo == hi)
        throw InputError(kName, "no intensity contrast (constant volume, every voxel " + std::to_string(lo) +
                                    "): there is no head to skull-strip");

    // All parameters are checked before any work.
    if (!(p.bet_fraction >= 0.05 && p.bet_fraction <= 0.95))
        throw InputError("SkullStripParams.bet_fraction", "value out of range [0.05, 0.95]");
    itkb::SkullStripConfig cfg;
    cfg.background_frac = p.background_frac;
    cfg.csf_gm_split = p.tissue_split;
    cfg.csf_split = p.csf_split;
    cfg.csf_margin_mm = p.target == SkullStripTarget::intracranial ? p.csf_margin_mm : p.brain_csf_margin_mm;
    cfg.bright_limit = p.bright_limit;
    cfg.erode_mm = p.erode_mm;
    cfg.bias_sigma_mm = p.bias_sigma_mm;
    cfg.reconstruct_mm = p.reconstruct_mm;
    cfg.close_mm = p.close_mm;
    cfg.envelope_margin_mm = p.envelope_margin_mm;
    cfg.open_mm = p.open_mm;
    cfg.final_dilate_mm = p.final_dilate_mm;
    cfg.min_brain_ml = p.min_brain_ml;
    cfg.max_brain_ml = p.max_brain_ml;
    cfg.support_gate_mm = p.support_gate_mm;
    itkb::check_config(cfg);
    if (!(p.valley_snap_mm >= 0 && p.valley_snap_mm <= 20))
        throw InputError("SkullStripParams.valley_snap_mm", "value out of range [0, 20]");
    if (!(p.brain_csf_margin_mm >= 0 && p.brain_csf_margin_mm <= 20))
        throw InputError("SkullStripParams.brain_csf_margin_mm", "value out of range [0, 20]");
    // Partial-volume bridges between brain and scalp are as thick as the thickest voxel side:
    // the erosion must reach across one.
    cfg.erode_mm = std::max(cfg.erode_mm, 0.85 * t1.geom.spacing_mm.maxCoeff());

    const itkb::StepFn step = [progress](const char* stage, double fraction) {
        if (!progress) return;
        progress->check();
        (*progress)(std::string("skull strip: ") + stage, fraction);
    };
    step("start", 0.0);

    // Work on an isotropic copy when the scan is strongly anisotropic.
    const double iso_mm = working_spacing_mm(t1.geom);
    Volume resampled;
    if (iso_mm > 0) {
        step("resampling to an isotropic grid", 0.01);
        resampled = resample(t1, isotropic_grid(t1.geom, iso_mm), 0.f);
    }
    const Volume& v = iso_mm > 0 ? resampled : t1;
    // Which rules fit the grid (docs/skull-stripping.md, "Rendered"): on fine grids the dark
    // layers between brain and skull are resolved and act as barriers (the support's gate, the
    // geodesic CSF growth); on coarse ones partial volume greys them, the barriers would stop
    // at cortex, and the mask's edge is moved into the intensity valley instead.
    const bool fine_grid = v.geom.spacing_mm.maxCoeff() <= 1.3;
    if (fine_grid)
        cfg.csf_geodesic = cfg.support_gate_mm > 0;
    else
        cfg.support_gate_mm = 0;

    itkb::Grid grid;
    grid.dims = v.geom.dims;
    for (int a = 0; a < 3; ++a) grid.spacing[a] = v.geom.spacing_mm[a];
    // Only dims and spacing matter: both stages work in index space with mm distances.
    const std::array<double, 3> sp{grid.spacing[0], grid.spacing[1], grid.spacing[2]};
    const double voxel_ml = sp[0] * sp[1] * sp[2] / 1000.0;

    // 1. The BET surface: a smooth envelope of the brain that cannot leak through thin bridges.
    bet::BetParams bp;
    bp.fractional_threshold = p.bet_fraction;
    bet::BetStats bs;
    bet::HeadFrame frame;
    {
        // Superior (world +S of LPS) in index-space mm: the direction cosines are orthonormal.
        const Eigen::Vector3d up = v.geom.direction.transpose() * Eigen::Vector3d::UnitZ();
        frame.up = {up[0], up[1], up[2]};
    }
    std::vector<uint8_t> envelope;
    double envelope_ml = 0;
    if (p.surface_model) {
        const auto mesh = bet::bet_surface(v.voxels.data(), grid.dims, sp, frame, bp, bs,
                                           [&](double f) { step("surface model", 0.02 + 0.2 * f); });
        envelope = bet::fill_mesh(mesh, grid.dims, sp);
        envelope_ml = double(std::count(envelope.begin(), envelope.end(), uint8_t(1))) * voxel_ml;
        // A surface that collapsed or swallowed the head bounds nothing: morphology alone then.
        if (envelope_ml < 0.5 * p.min_brain_ml || envelope_ml > 2.0 * p.max_brain_ml) envelope.clear();
    }
    // Above the surface's centre (the convexity) its interior is brain; below, the skull base
    // is where BET-like models leak, and the tissue pipeline decides.
    std::vector<uint8_t> support;
    if (!envelope.empty()) {
        support.assign(envelope.size(), 0);
        const double h_cog = bs.cog_mm[0] * frame.up[0] + bs.cog_mm[1] * frame.up[1] + bs.cog_mm[2] * frame.up[2];
        for (int k = 0; k < grid.dims[2]; ++k)
            for (int j = 0; j < grid.dims[1]; ++j)
                for (int i = 0; i < grid.dims[0]; ++i) {
                    const size_t li = (size_t(k) * grid.dims[1] + j) * grid.dims[0] + i;
                    const double h = i * sp[0] * frame.up[0] + j * sp[1] * frame.up[1] + k * sp[2] * frame.up[2];
                    support[li] = envelope[li] && h > h_cog + p.support_above_mm;
                }
        if (p.support_above_mm >= 100.0) support.clear();
    }

    // 2. Tissue classes, thresholds and morphology inside the envelope (itk_skull_strip.cpp).
    const itkb::StepFn step2 = [&](const char* stage, double f) { step(stage, 0.22 + 0.75 * f); };
    LabelVolume work;
    work.geom = v.geom;
    itkb::SkullStripReport rep;
    itkb::skull_strip_mask(grid, v.voxels.data(), envelope.empty() ? nullptr : envelope.data(),
                           support.empty() ? nullptr : support.data(), cfg, step2,
                           work.voxels, rep);

    LabelVolume out = iso_mm > 0 ? resample_nearest(work, t1.geom) : std::move(work);
    // Isotropic coarse scans only: on thick slices (the DICOM series, 4.8 mm) the descent wandered
    // through the noisy grey of the 1 mm in-plane grid (1396 -> 1527 mL, a ragged edge) and the
    // staircase between slices stayed; that one needs the renderer (docs/skull-stripping.md).
    if (!fine_grid && iso_mm == 0 && p.valley_snap_mm > 0) {
        step("valley", 0.98);
        itkb::Grid og;
        og.dims = t1.geom.dims;
        for (int a = 0; a < 3; ++a) og.spacing[a] = t1.geom.spacing_mm[a];
        itkb::valley_snap(og, t1.voxels.data(), out.voxels, rep.csf + 0.5 * (rep.gm - rep.csf), p.valley_snap_mm);
    }
    if (info) {
        info->p02 = rep.p02;
        info->p98 = rep.p98;
        info->t_background = rep.t_background;
        info->t_low = rep.t_low;
        info->t_high = rep.t_high;
        info->t_csf = rep.t_csf;
        info->csf = rep.csf;
        info->gm = rep.gm;
        info->wm = rep.wm;
        info->head_ml = rep.head_ml;
        info->brain_ml = double(out.count_nonzero()) * t1.geom.spacing_mm.prod() / 1000.0;
        info->working_spacing_mm = iso_mm > 0 ? iso_mm : 0.0;
        info->envelope_ml = envelope_ml;
        info->envelope_used = !envelope.empty();
    }
    step("done", 1.0);
    return out;
}

namespace {

// Maps the volume's voxel axes onto the patient axes (L, P, S of LPS world) by the nearest
// direction cosine, so the check image shows standard views whatever the file orientation.
struct PatientAxes {
    std::array<int, 3> axis{0, 1, 2};  // voxel axis along world axis w
    std::array<bool, 3> flip{false, false, false};
    std::array<int, 3> n{0, 0, 0};     // voxels along world axis w
    std::array<double, 3> spacing_mm{1, 1, 1};

    explicit PatientAxes(const VolumeGeometry& g) {
        std::array<bool, 3> used{false, false, false};
        for (int w = 0; w < 3; ++w) {
            int best = -1;
            for (int a = 0; a < 3; ++a)
                if (!used[a] && (best < 0 || std::abs(g.direction(w, a)) > std::abs(g.direction(w, best)))) best = a;
            used[best] = true;
            axis[w] = best;
            flip[w] = g.direction(w, best) < 0;
            n[w] = g.dims[best];
            spacing_mm[w] = g.spacing_mm[best];
        }
    }
    // Voxel linear index of patient-ordered index x (x[w] grows towards L, P, S).
    size_t linear(const VolumeGeometry& g, const std::array<int, 3>& x) const {
        std::array<int, 3> ijk{};
        for (int w = 0; w < 3; ++w) ijk[axis[w]] = flip[w] ? n[w] - 1 - x[w] : x[w];
        return g.linear(ijk[0], ijk[1], ijk[2]);
    }
};

}  // namespace

void write_mask_check_png(const Volume& v, const LabelVolume& mask, const std::filesystem::path& png,
                          const LabelVolume* reference) {
    const std::string name = png.string();
    if (!v.geom.same_grid(mask.geom) || mask.voxels.size() != v.voxels.size())
        throw InputError(name, "mask and volume are not on the same grid");
    if (reference && (!v.geom.same_grid(reference->geom) || reference->voxels.size() != v.voxels.size()))
        throw InputError(name, "reference mask and volume are not on the same grid");
    const PatientAxes pa(v.geom);

    // Display window from robust percentiles (any intensity range).
    std::vector<float> s;
    const size_t stride = std::max<size_t>(1, v.voxels.size() / 1'000'000);
    for (size_t i = 0; i < v.voxels.size(); i += stride) s.push_back(v.voxels[i]);
    std::sort(s.begin(), s.end());
    const double lo = s[size_t(0.01 * double(s.size() - 1))], hi = s[size_t(0.995 * double(s.size() - 1))];
    const double scale = hi > lo ? 255.0 / (hi - lo) : 1.0;

    // Mask extent along each patient axis, to place slices at 30/50/70 % through it.
    std::array<int, 3> mlo{pa.n}, mhi{-1, -1, -1};
    for (int z = 0; z < pa.n[2]; ++z)
        for (int y = 0; y < pa.n[1]; ++y)
            for (int x = 0; x < pa.n[0]; ++x)
                if (mask.voxels[pa.linear(v.geom, {x, y, z})]) {
                    const std::array<int, 3> p{x, y, z};
                    for (int w = 0; w < 3; ++w) {
                        mlo[w] = std::min(mlo[w], p[w]);
                        mhi[w] = std::max(mhi[w], p[w]);
                    }
                }
    for (int w = 0; w < 3; ++w)
        if (mhi[w] < 0) {  // empty mask: slices through the middle
            mlo[w] = 0;
            mhi[w] = pa.n[w] - 1;
        }

    constexpr int kPanel = 300;  // pixels per panel side
    cv::Mat montage(3 * kPanel, 3 * kPanel, CV_8UC3, cv::Scalar(0, 0, 0));
    const char* view_names[3] = {"axial", "coronal", "sagittal"};
    for (int view = 0; view < 3; ++view) {
        // view 0 axial: cols L (patient right on the left), rows P (anterior up); slice axis S.
        // view 1 coronal: cols L, rows S flipped (superior up); slice axis P.
        // view 2 sagittal: cols P (anterior on the left), rows S flipped; slice axis L.
        const int col_w = view == 2 ? 1 : 0;
        const int row_w = view == 0 ? 1 : 2;
        const int slice_w = view == 0 ? 2 : (view == 1 ? 1 : 0);
        const bool row_flip = view != 0;
        for (int c = 0; c < 3; ++c) {
            const double frac = 0.3 + 0.2 * c;
            const int sl = int(std::lround(mlo[slice_w] + frac * (mhi[slice_w] - mlo[slice_w])));
            cv::Mat gray(pa.n[row_w], pa.n[col_w], CV_8U), m(gray.size(), CV_8U), r(gray.size(), CV_8U);
            for (int row = 0; row < gray.rows; ++row)
                for (int col = 0; col < gray.cols; ++col) {
                    std::array<int, 3> x{};
                    x[slice_w] = sl;
                    x[col_w] = col;
                    x[row_w] = row_flip ? pa.n[row_w] - 1 - row : row;
                    const size_t li = pa.linear(v.geom, x);
                    gray.at<uint8_t>(row, col) = cv::saturate_cast<uint8_t>((v.voxels[li] - lo) * scale);
                    m.at<uint8_t>(row, col) = mask.voxels[li] ? 255 : 0;
                    r.at<uint8_t>(row, col) = reference && reference->voxels[li] ? 255 : 0;
                }
            // Square pixels in mm, fitted into the panel.
            const double w_mm = pa.n[col_w] * pa.spacing_mm[col_w], h_mm = pa.n[row_w] * pa.spacing_mm[row_w];
            const double px_per_mm = double(kPanel) / std::max(w_mm, h_mm);
            const cv::Size size(std::max(1, int(w_mm * px_per_mm)), std::max(1, int(h_mm * px_per_mm)));
            cv::Mat g2, m2, r2, rgb;
            cv::resize(gray, g2, size, 0, 0, cv::INTER_LINEAR);
            cv::resize(m, m2, size, 0, 0, cv::INTER_NEAREST);
            cv::resize(r, r2, size, 0, 0, cv::INTER_NEAREST);
            cv::cvtColor(g2, rgb, cv::COLOR_GRAY2BGR);
            std::vector<std::vector<cv::Point>> contours;
            if (reference) {
                cv::findContours(r2, contours, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);
                cv::drawContours(rgb, contours, -1, cv::Scalar(0, 220, 0), 1);
            }
            cv::findContours(m2, contours, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);
            cv::drawContours(rgb, contours, -1, cv::Scalar(0, 0, 255), 1);
            const cv::Rect roi(c * kPanel + (kPanel - size.width) / 2, view * kPanel + (kPanel - size.height) / 2,
                               size.width, size.height);
            rgb.copyTo(montage(roi));
            cv::putText(montage, std::string(view_names[view]) + " " + std::to_string(sl),
                        cv::Point(c * kPanel + 4, view * kPanel + 14), cv::FONT_HERSHEY_SIMPLEX, 0.45,
                        cv::Scalar(0, 255, 255), 1);
        }
    }
    cv::putText(montage, reference ? "red: mask  green: reference  (R on left)" : "red: mask  (R on left)",
                cv::Point(4, 3 * kPanel - 6), cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 255, 255), 1);
    try {
        if (!cv::imwrite(name, montage)) throw InputError(name, "cannot write the check image");
    } catch (const cv::Exception& e) {
        throw InputError(name, std::string("cannot write the check image: ") + e.what());
    }
}

}  // namespace cf
