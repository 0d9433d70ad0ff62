// Skull stripping of a T1 head: a thresholding + morphology pipeline (see docs/skull-stripping.md).
// Morphology by large radii goes through signed Maurer distance maps, so an erosion or dilation
// costs the same for 1 mm and 10 mm (a structuring-element filter grows with r^3).
// ITK code only: this file must include no Eigen header (ITK 5.2 bundles a clashing one).
#include <itkBinaryFillholeImageFilter.h>
#include <itkConnectedComponentImageFilter.h>
#include <itkImage.h>
#include <itkSmoothingRecursiveGaussianImageFilter.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <queue>
#include <numbers>
#include <string>

#include "cortexfuse/core/error.hpp"
#include "itk_image.hpp"
#include "itk_skull_strip.hpp"

namespace cf::itkb {
namespace {

using MaskImage = itk::Image<uint8_t, 3>;
using DistImage = itk::Image<float, 3>;
using LabelImage = itk::Image<uint32_t, 3>;

const std::string kInput = "skull strip";

std::string fmt(double v, int prec = 0) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.*f", prec, v);
    return buf;
}

// A sub-block of the volume: the work happens on the head's bounding box only.
struct Block {
    std::array<int, 3> lo{0, 0, 0};
    std::array<int, 3> dims{0, 0, 0};
    std::array<double, 3> spacing_mm{1, 1, 1};
    size_t count() const { return size_t(dims[0]) * dims[1] * dims[2]; }
    size_t linear(int i, int j, int k) const { return (size_t(k) * dims[1] + j) * dims[0] + i; }
};

/// The block as an ITK grid: spacing in mm (so radii are in mm on anisotropic grids), origin 0.
Grid block_grid(const Block& b) {
    Grid g;
    g.dims = b.dims;
    g.spacing = b.spacing_mm;
    return g;
}

MaskImage::Pointer new_mask(const Block& b) {
    auto img = make_image<MaskImage>(block_grid(b));
    img->FillBuffer(0);
    return img;
}

size_t count_on(const MaskImage* m) {
    const uint8_t* p = m->GetBufferPointer();
    const size_t n = m->GetBufferedRegion().GetNumberOfPixels();
    return size_t(std::count_if(p, p + n, [](uint8_t v) { return v != 0; }));
}

// Signed distance in mm: negative inside, positive outside.
DistImage::Pointer signed_distance(const MaskImage* m) { return signed_maurer_distance<DistImage>(m); }

// Grows (radius_mm > 0) or shrinks (radius_mm < 0) a mask by a Euclidean ball.
MaskImage::Pointer morph(const MaskImage* m, const Block& b, double radius_mm) {
    auto out = new_mask(b);
    const size_t n = b.count();
    const size_t on = count_on(m);
    if (on == 0 || on == n) {  // the distance map is undefined without a boundary
        std::copy_n(m->GetBufferPointer(), n, out->GetBufferPointer());
        return out;
    }
    const auto d = signed_distance(m);
    const float* dp = d->GetBufferPointer();
    uint8_t* op = out->GetBufferPointer();
    const float limit = float(radius_mm);
    for (size_t i = 0; i < n; ++i) op[i] = dp[i] <= limit ? 1 : 0;
    return out;
}

// Face-connected components (6-connectivity leaks least through thin bridges).
LabelImage::Pointer components(const MaskImage* m, size_t& n_labels) {
    auto cc = itk::ConnectedComponentImageFilter<MaskImage, LabelImage>::New();
    cc->SetInput(m);
    cc->FullyConnectedOff();
    cc->Update();
    n_labels = size_t(cc->GetObjectCount());
    return cc->GetOutput();
}

void and_into(MaskImage* a, const MaskImage* b) {
    uint8_t* ap = a->GetBufferPointer();
    const uint8_t* bp = b->GetBufferPointer();
    const size_t n = a->GetBufferedRegion().GetNumberOfPixels();
    for (size_t i = 0; i < n; ++i) ap[i] = ap[i] & bp[i];
}

MaskImage::Pointer close(const MaskImage* m, const Block& b, double radius_mm) {
    if (radius_mm <= 0) return morph(m, b, 0.0);
    auto dil = morph(m, b, radius_mm);
    return morph(dil, b, -radius_mm);
}

MaskImage::Pointer fill_holes(const MaskImage* m) {
    auto fill = itk::BinaryFillholeImageFilter<MaskImage>::New();
    fill->SetInput(m);
    fill->SetForegroundValue(1);
    fill->FullyConnectedOff();
    fill->Update();
    return fill->GetOutput();
}

// The component of `m` that overlaps most a sphere (centre/radius given by dist2_mm and
// radius_mm); ties go to the larger. Null when no component reaches the sphere.
template <class Dist2>
MaskImage::Pointer pick_central(const MaskImage* m, const Block& b, const Dist2& dist2_mm, double radius_mm) {
    size_t n_labels = 0;
    const auto labels = components(m, n_labels);
    std::vector<size_t> central(n_labels + 1, 0), sizes(n_labels + 1, 0);
    const uint32_t* lp = labels->GetBufferPointer();
    const double r2 = radius_mm * radius_mm;
    for (int k = 0; k < b.dims[2]; ++k)
        for (int j = 0; j < b.dims[1]; ++j)
            for (int i = 0; i < b.dims[0]; ++i) {
                const uint32_t l = lp[b.linear(i, j, k)];
                if (l == 0) continue;
                ++sizes[l];
                if (dist2_mm(i, j, k) < r2) ++central[l];
            }
    uint32_t best = 0;
    for (uint32_t l = 1; l <= n_labels; ++l)
        if (central[l] > central[best] || (best != 0 && central[l] == central[best] && sizes[l] > sizes[best]))
            best = l;
    if (best == 0 || central[best] == 0) return nullptr;
    auto out = new_mask(b);
    uint8_t* op = out->GetBufferPointer();
    for (size_t i = 0; i < b.count(); ++i) op[i] = lp[i] == best ? 1 : 0;
    return out;
}

// The components of `m` that touch `seed` (seed is a subset of m).
MaskImage::Pointer pick_overlapping(const MaskImage* m, const MaskImage* seed) {
    size_t n_labels = 0;
    const auto labels = components(m, n_labels);
    std::vector<uint8_t> keep(n_labels + 1, 0);
    const uint32_t* lp = labels->GetBufferPointer();
    const uint8_t* sp = seed->GetBufferPointer();
    const size_t n = m->GetBufferedRegion().GetNumberOfPixels();
    for (size_t i = 0; i < n; ++i)
        if (sp[i]) keep[lp[i]] = 1;
    keep[0] = 0;
    auto out = MaskImage::New();
    out->CopyInformation(m);
    out->SetRegions(m->GetBufferedRegion());
    out->Allocate();
    uint8_t* op = out->GetBufferPointer();
    for (size_t i = 0; i < n; ++i) op[i] = keep[lp[i]];
    return out;
}

// The voxels of `allowed` within `reach_mm` of `seed` by paths through `allowed` (26-neighbour
// steps of their length in mm, Dijkstra): a geodesic reach. A layer of voxels not allowed in
// between stops it; going round the edge of such a layer takes the length of the way round.
std::vector<uint8_t> geodesic_reach(const Block& b, const uint8_t* seed, const std::vector<uint8_t>& allowed,
                                    double reach_mm, std::vector<float>* dist_out = nullptr) {
    const size_t n = b.count();
    std::vector<float> dist(n, std::numeric_limits<float>::infinity());
    using Item = std::pair<float, size_t>;
    std::priority_queue<Item, std::vector<Item>, std::greater<>> queue;
    for (size_t i = 0; i < n; ++i)
        if (seed[i]) {
            dist[i] = 0.f;
            queue.push({0.f, i});
        }
    struct Step {
        int di, dj, dk;
        ptrdiff_t offset;
        float mm;
    };
    std::vector<Step> steps;
    const ptrdiff_t sj = b.dims[0], sk = ptrdiff_t(b.dims[0]) * b.dims[1];
    for (int dk = -1; dk <= 1; ++dk)
        for (int dj = -1; dj <= 1; ++dj)
            for (int di = -1; di <= 1; ++di)
                if (di || dj || dk)
                    steps.push_back({di, dj, dk, di + dj * sj + dk * sk,
                                     float(std::sqrt(std::pow(di * b.spacing_mm[0], 2) + std::pow(dj * b.spacing_mm[1], 2) +
                                                     std::pow(dk * b.spacing_mm[2], 2)))});
    const float limit = float(reach_mm);
    while (!queue.empty()) {
        const auto [d, li] = queue.top();
        queue.pop();
        if (d > dist[li]) continue;
        const int i = int(li % size_t(b.dims[0])), j = int((li / size_t(b.dims[0])) % size_t(b.dims[1])),
                  k = int(li / size_t(sk));
        for (const Step& st : steps) {
            const int a = i + st.di, c = j + st.dj, e = k + st.dk;
            if (a < 0 || c < 0 || e < 0 || a >= b.dims[0] || c >= b.dims[1] || e >= b.dims[2]) continue;
            const size_t nb = size_t(ptrdiff_t(li) + st.offset);
            const float nd = d + st.mm;
            if (!allowed[nb] || nd > limit || nd >= dist[nb]) continue;
            dist[nb] = nd;
            queue.push({nd, nb});
        }
    }
    std::vector<uint8_t> reached(n);
    for (size_t i = 0; i < n; ++i) reached[i] = dist[i] <= limit;
    if (dist_out) *dist_out = std::move(dist);
    return reached;
}

using FloatImage = itk::Image<float, 3>;

FloatImage::Pointer new_float(const Block& b) { return make_image<FloatImage>(block_grid(b)); }

FloatImage::Pointer smooth(const FloatImage* f, double sigma_mm) {
    auto g = itk::SmoothingRecursiveGaussianImageFilter<FloatImage, FloatImage>::New();
    g->SetInput(f);
    g->SetSigma(sigma_mm);
    g->Update();
    return g->GetOutput();
}

// Robust percentiles on a strided sample (the exact value does not matter, the stability does).
std::array<double, 2> percentiles(const float* v, size_t n, double qa, double qb) {
    const size_t stride = std::max<size_t>(1, n / 2'000'000);
    std::vector<float> s;
    s.reserve(n / stride + 1);
    for (size_t i = 0; i < n; i += stride) s.push_back(v[i]);
    auto at = [&](double q) {
        const size_t k = std::min(s.size() - 1, size_t(q * double(s.size() - 1)));
        std::nth_element(s.begin(), s.begin() + std::ptrdiff_t(k), s.end());
        return double(s[k]);
    };
    return {at(qa), at(qb)};
}

// 1-D k-means with 3 classes (CSF, GM, WM on T1) over a histogram of the sample.
std::array<double, 3> three_means(std::vector<float>& s) {
    std::sort(s.begin(), s.end());
    const double lo = s.front(), hi = s.back();
    std::array<double, 3> c{s[s.size() / 5], s[s.size() / 2], s[s.size() * 4 / 5]};
    if (!(hi > lo)) return c;
    constexpr int kBins = 512;
    std::vector<double> hist(kBins, 0.0);
    const double w = (hi - lo) / kBins;
    for (float x : s) hist[std::min(kBins - 1, int((x - lo) / w))] += 1.0;
    for (int it = 0; it < 100; ++it) {
        std::array<double, 3> sum{0, 0, 0}, cnt{0, 0, 0};
        for (int b = 0; b < kBins; ++b) {
            const double x = lo + (b + 0.5) * w;
            int best = 0;
            for (int k = 1; k < 3; ++k)
                if (std::abs(x - c[k]) < std::abs(x - c[best])) best = k;
            sum[best] += hist[b] * x;
            cnt[best] += hist[b];
        }
        std::array<double, 3> next = c;
        for (int k = 0; k < 3; ++k)
            if (cnt[k] > 0) next[k] = sum[k] / cnt[k];
        if (next == c) break;
        c = next;
    }
    std::sort(c.begin(), c.end());
    return c;
}

}  // namespace

void check_config(const SkullStripConfig& c) {
    auto in = [](double v, double lo, double hi) { return std::isfinite(v) && v >= lo && v <= hi; };
    auto bad = [](const char* field, double v, const char* range) {
        throw InputError(std::string("SkullStripParams.") + field,
                         "value " + fmt(v, 3) + " out of range " + range);
    };
    if (!in(c.background_frac, 0.01, 0.5)) bad("background_frac", c.background_frac, "[0.01, 0.5]");
    if (!in(c.csf_gm_split, -2.0, 1.0)) bad("csf_gm_split", c.csf_gm_split, "[-2, 1]");
    if (!in(c.bright_limit, 0.2, 20.0)) bad("bright_limit", c.bright_limit, "[0.2, 20]");
    if (!in(c.erode_mm, 0.5, 20.0)) bad("erode_mm", c.erode_mm, "[0.5, 20]");
    if (!in(c.close_mm, 0.0, 30.0)) bad("close_mm", c.close_mm, "[0, 30]");
    if (!in(c.csf_split, -2.0, 1.0)) bad("csf_split", c.csf_split, "[-2, 1]");
    if (!in(c.csf_margin_mm, 0.0, 20.0)) bad("csf_margin_mm", c.csf_margin_mm, "[0, 20]");
    if (!in(c.reconstruct_mm, 0.0, 30.0)) bad("reconstruct_mm", c.reconstruct_mm, "[0, 30]");
    if (!in(c.bias_sigma_mm, 0.0, 100.0)) bad("bias_sigma_mm", c.bias_sigma_mm, "[0, 100]");
    if (!in(c.envelope_margin_mm, 0.0, 20.0)) bad("envelope_margin_mm", c.envelope_margin_mm, "[0, 20]");
    if (!in(c.open_mm, 0.0, 20.0)) bad("open_mm", c.open_mm, "[0, 20]");
    if (!in(c.support_gate_mm, 0.0, 30.0)) bad("support_gate_mm", c.support_gate_mm, "[0, 30]");
    if (!in(c.final_dilate_mm, -10.0, 10.0)) bad("final_dilate_mm", c.final_dilate_mm, "[-10, 10]");
    if (!in(c.min_brain_ml, 0.0, 1e5) || !in(c.max_brain_ml, c.min_brain_ml, 1e6))
        bad("max_brain_ml", c.max_brain_ml, "[min_brain_ml, 1e6]");
}

void skull_strip_mask(const Grid& grid, const float* voxels, const uint8_t* envelope, const uint8_t* support,
                      const SkullStripConfig& cfg,
                      const StepFn& step, std::vector<uint8_t>& mask, SkullStripReport& rep) {
    check_config(cfg);
    for (int a = 0; a < 3; ++a)
        if (grid.dims[a] < 8)
            throw InputError(kInput, "volume too small (" + std::to_string(grid.dims[a]) +
                                         " voxels along an axis) to hold a head");
    const size_t n_all = grid.count();
    const double voxel_ml = grid.spacing[0] * grid.spacing[1] * grid.spacing[2] / 1000.0;

    // 1. Robust range and background threshold (as BET: 10 % between the 2nd and 98th percentiles),
    //    so uint8, int16 and scaled volumes all work.
    step("intensity range", 0.0);
    const auto [p02, p98] = percentiles(voxels, n_all, 0.02, 0.98);
    rep.p02 = p02;
    rep.p98 = p98;
    if (!(p98 - p02 > 1e-6 * std::max(1.0, std::abs(p98))))
        throw InputError(kInput, "no intensity contrast (constant volume): there is no head to skull-strip");
    const double t_bg = p02 + cfg.background_frac * (p98 - p02);
    rep.t_background = t_bg;

    // 2. Head = largest bright component; its bounding box bounds all later work.
    step("head mask", 0.08);
    Block full;
    full.dims = grid.dims;
    full.spacing_mm = grid.spacing;
    Block box;
    {
        auto head = new_mask(full);
        uint8_t* hp = head->GetBufferPointer();
        for (size_t i = 0; i < n_all; ++i) hp[i] = voxels[i] > t_bg ? 1 : 0;
        size_t n_labels = 0;
        const auto labels = components(head, n_labels);
        if (n_labels == 0) throw InputError(kInput, "no head found (nothing above the background level)");
        std::vector<size_t> sizes(n_labels + 1, 0);
        const uint32_t* lp = labels->GetBufferPointer();
        for (size_t i = 0; i < n_all; ++i) ++sizes[lp[i]];
        const uint32_t best = uint32_t(std::max_element(sizes.begin() + 1, sizes.end()) - sizes.begin());
        rep.head_ml = double(sizes[best]) * voxel_ml;
        if (rep.head_ml < cfg.min_brain_ml)
            throw InputError(kInput, "no head found (largest bright region is " + fmt(rep.head_ml) +
                                         " mL, a brain alone is at least " + fmt(cfg.min_brain_ml) + " mL)");
        std::array<int, 3> lo{grid.dims}, hi{-1, -1, -1};
        for (int k = 0; k < grid.dims[2]; ++k)
            for (int j = 0; j < grid.dims[1]; ++j)
                for (int i = 0; i < grid.dims[0]; ++i)
                    if (lp[full.linear(i, j, k)] == best) {
                        const std::array<int, 3> p{i, j, k};
                        for (int a = 0; a < 3; ++a) {
                            lo[a] = std::min(lo[a], p[a]);
                            hi[a] = std::max(hi[a], p[a]);
                        }
                    }
        // Margin: the closing dilates past the brain before eroding back.
        const double margin_mm = cfg.close_mm + cfg.csf_margin_mm + std::max(0.0, cfg.final_dilate_mm) + 2.0;
        for (int a = 0; a < 3; ++a) {
            const int m = int(std::ceil(margin_mm / grid.spacing[a])) + 1;
            box.lo[a] = std::max(0, lo[a] - m);
            box.dims[a] = std::min(grid.dims[a] - 1, hi[a] + m) - box.lo[a] + 1;
        }
        box.spacing_mm = grid.spacing;
    }
    const size_t n = box.count();
    std::vector<float> img(n);
    for (int k = 0; k < box.dims[2]; ++k)
        for (int j = 0; j < box.dims[1]; ++j) {
            const float* src = voxels + full.linear(box.lo[0], box.lo[1] + j, box.lo[2] + k);
            std::copy_n(src, box.dims[0], img.data() + box.linear(0, j, k));
        }

    // 3. Centre and radius of the head (as BET), then tissue classes in a sphere at its centre,
    //    which holds mostly brain whatever the scalp, fat and neck look like.
    step("tissue classes", 0.2);
    std::array<double, 3> cog_mm{0, 0, 0};
    size_t n_head = 0;
    for (int k = 0; k < box.dims[2]; ++k)
        for (int j = 0; j < box.dims[1]; ++j)
            for (int i = 0; i < box.dims[0]; ++i)
                if (img[box.linear(i, j, k)] > t_bg) {
                    cog_mm[0] += i * box.spacing_mm[0];
                    cog_mm[1] += j * box.spacing_mm[1];
                    cog_mm[2] += k * box.spacing_mm[2];
                    ++n_head;
                }
    for (double& c : cog_mm) c /= double(n_head);
    const double radius_mm = std::cbrt(3.0 * double(n_head) * voxel_ml * 1000.0 / (4.0 * std::numbers::pi));
    auto dist2_mm = [&](int i, int j, int k) {
        const double dx = i * box.spacing_mm[0] - cog_mm[0], dy = j * box.spacing_mm[1] - cog_mm[1],
                     dz = k * box.spacing_mm[2] - cog_mm[2];
        return dx * dx + dy * dy + dz * dz;
    };
    const double r_stats2 = std::pow(0.6 * radius_mm, 2.0);
    std::vector<float> sample;
    for (int k = 0; k < box.dims[2]; ++k)
        for (int j = 0; j < box.dims[1]; ++j)
            for (int i = 0; i < box.dims[0]; ++i) {
                const float v = img[box.linear(i, j, k)];
                if (v > t_bg && dist2_mm(i, j, k) < r_stats2) sample.push_back(v);
            }
    if (sample.size() < 1000)
        throw InputError(kInput, "no head found (too few bright voxels near the centre of the head)");
    const auto cls = three_means(sample);
    rep.csf = cls[0];
    rep.gm = cls[1];
    rep.wm = cls[2];
    if (cls[2] - cls[0] < 0.1 * (p98 - p02) || cls[2] - cls[1] < 0.02 * (p98 - p02))
        throw InputError(kInput, "no T1 brain contrast found at the centre of the head (is this a T1 head MRI?)");
    const double t_low = cls[0] + cfg.csf_gm_split * (cls[1] - cls[0]);
    const double t_high = cls[2] + cfg.bright_limit * (cls[2] - cls[1]);
    const double t_csf = cls[0] + cfg.csf_split * (cls[1] - cls[0]);
    rep.t_low = t_low;
    rep.t_high = t_high;

    // The envelope (BET surface) bounds everything: it stops the leaks through the skull base,
    // the optic nerves and the foramen magnum that thresholds and morphology alone let through.
    MaskImage::Pointer env;
    if (envelope) {
        auto e = new_mask(box);
        uint8_t* ep = e->GetBufferPointer();
        for (int k = 0; k < box.dims[2]; ++k)
            for (int j = 0; j < box.dims[1]; ++j)
                std::copy_n(envelope + full.linear(box.lo[0], box.lo[1] + j, box.lo[2] + k), box.dims[0],
                            ep + box.linear(0, j, k));
        env = morph(e, box, cfg.envelope_margin_mm);
    }

    // 4-7. Brain tissue: threshold, erode, pick the central component, reconstruct.
    const double max_sp = std::max({box.spacing_mm[0], box.spacing_mm[1], box.spacing_mm[2]});
    auto tissue = [&](double f0, double f1) {
        // Candidate tissue: between CSF/GM and a bit above WM (drops most scalp fat and marrow).
        step("tissue threshold", f0);
        auto cand = new_mask(box);
        uint8_t* cp = cand->GetBufferPointer();
        for (size_t i = 0; i < n; ++i) cp[i] = (img[i] >= t_low && img[i] <= t_high) ? 1 : 0;
        if (env) and_into(cand, env);
        // Erosion cuts the thin bridges (dura, vessels, optic nerves, muscle contacts) between
        // brain and scalp, so the brain becomes its own component: the one nearest the head centre.
        step("erosion", f0 + 0.25 * (f1 - f0));
        auto core = morph(cand, box, -cfg.erode_mm);
        step("components", f0 + 0.5 * (f1 - f0));
        auto seed = pick_central(core, box, dist2_mm, 0.5 * radius_mm);
        if (!seed)
            throw InputError(kInput, "no brain-like region found at the centre of the head (is this a T1 head MRI?)");
        core = nullptr;
        // Reconstruction: the candidate tissue connected to the seed within reconstruct_mm of it
        // (at least the erosion radius plus half a voxel for the distance-map rounding). This
        // brings back thin gyri the erosion cut off, and the distance bound stops leaks.
        step("reconstruction", f0 + 0.75 * (f1 - f0));
        auto grown = morph(seed, box, std::max(cfg.reconstruct_mm, cfg.erode_mm + 0.5 * max_sp));
        and_into(grown, cand);
        return pick_overlapping(grown, seed);
    };
    auto seed = tissue(0.25, 0.4);

    // Bias field: cortex far from the coil is darker (seg3d's vertex), so one threshold cuts it.
    // Estimate the field as the smoothed WM intensity of the tissue found (normalised convolution),
    // flatten it, and find the tissue again.
    if (cfg.bias_sigma_mm > 0) {
        step("bias field", 0.4);
        const double t_wm = 0.5 * (cls[1] + cls[2]);
        auto num = new_float(box), den = new_float(box);
        {
            float* np = num->GetBufferPointer();
            float* dp = den->GetBufferPointer();
            const uint8_t* sp = seed->GetBufferPointer();
            for (size_t i = 0; i < n; ++i) {
                const bool wm = sp[i] && img[i] >= t_wm;
                np[i] = wm ? img[i] : 0.f;
                dp[i] = wm ? 1.f : 0.f;
            }
        }
        const auto sn = smooth(num, cfg.bias_sigma_mm), sd = smooth(den, cfg.bias_sigma_mm);
        const float* np = sn->GetBufferPointer();
        const float* dp = sd->GetBufferPointer();
        for (size_t i = 0; i < n; ++i) {
            if (dp[i] < 0.05f) continue;  // too far from any WM to know the field
            const double b = double(np[i]) / double(dp[i]);
            img[i] = float(img[i] * std::clamp(cls[2] / b, 0.67, 1.5));
        }
        seed = tissue(0.45, 0.55);
    }

    // Over the convexity the surface model is reliable where one threshold is not (bias field,
    // thin dark cortex at the vertex): the `support` voxels (surface interior above its centre)
    // are brain too.
    if (support) {
        std::vector<uint8_t> sup(n, 0);
        for (int k = 0; k < box.dims[2]; ++k)
            for (int j = 0; j < box.dims[1]; ++j)
                std::copy_n(support + full.linear(box.lo[0], box.lo[1] + j, box.lo[2] + k), box.dims[0],
                            sup.data() + box.linear(0, j, k));
        // The surface model often ends beyond the brain: on seg3d it encloses 250 mL more than the
        // reference, a grey layer under the inner table (dura, a thin CSF space greyed by partial
        // volume) and the skull's fatty marrow. Taken as brain, those layers rendered as smooth
        // opaque sheets over the cortex. So the support only counts where the brain tissue
        // reaches it within support_gate_mm by a path through tissue-like voxels (above the CSF
        // class mean, at least 1 mm from any voxel that dark, below WM + half the GM-WM step)
        // that is at most 1 mm longer than the straight distance: a dark layer in between
        // (the CSF over the cortex, the inner table) stops it, and going round a gap does not
        // count. Dark cortex under the bias field (the support's purpose) is reached through
        // the gyrus it belongs to.
        if (cfg.support_gate_mm > 0) {
            const double t_dark = cls[0], t_bright = 0.5 * (cls[1] + cls[2]);
            auto dark = new_mask(box);
            {
                uint8_t* dp = dark->GetBufferPointer();
                for (size_t i = 0; i < n; ++i) dp[i] = img[i] <= t_dark ? 1 : 0;
            }
            const auto near_dark = morph(dark, box, 0.99 * max_sp);
            const uint8_t* ndp = near_dark->GetBufferPointer();
            const uint8_t* sd = seed->GetBufferPointer();
            std::vector<uint8_t> passable(n, 0);
            for (size_t i = 0; i < n; ++i)
                passable[i] = sup[i] && img[i] > t_dark && img[i] < t_bright && (sd[i] || !ndp[i]);
            std::vector<float> path_mm;
            const auto reached = geodesic_reach(box, sd, passable, cfg.support_gate_mm, &path_mm);
            const auto straight = signed_distance(seed);
            const float* st = straight->GetBufferPointer();
            for (size_t i = 0; i < n; ++i)
                sup[i] = sup[i] && reached[i] && path_mm[i] <= std::max(0.f, st[i]) + 1.f;
        }
        uint8_t* sp = seed->GetBufferPointer();
        for (size_t i = 0; i < n; ++i) sp[i] |= sup[i];
    }

    // 8. Closing takes in the sulcal CSF and smooths the outer surface: the brain envelope.
    step("closing", 0.52);
    seed = close(seed, box, cfg.close_mm);
    seed = fill_holes(seed);

    // 9. Extra-axial CSF: the dark layer right outside the cortex. Take the voxels darker than
    //    t_csf = csf + csf_split (gm - csf) that lie within csf_margin_mm of the envelope and are
    //    connected to it; the grey band beyond (dura, partial volume with the diploe, the skull on
    //    intensity-normalised scans) is brighter and stops the growth, the margin stops it in
    //    dark bone and air. Measured (docs/skull-stripping.md): FreeSurfer's mask of mne_ecog holds
    //    that dark CSF layer (4-5 mm over the convexity), Seg3D's mask of seg3d stops at the grey
    //    band on the cortex; the former "bright enough to be CSF, not bone" rule took seg3d's grey
    //    band and left mne_ecog's CSF out, the opposite of both references.
    step("intracranial CSF", 0.62);
    if (cfg.csf_margin_mm > 0) {
        rep.t_csf = t_csf;
        // Thick slices (the erosion was raised to cut one-slice-thick bridges, see skull_strip.cpp):
        // the extra erosion thins the cortex the reconstruction returns and partial volume greys
        // the CSF layer, so the CSF reach grows by the extra erosion (2 mm is the default).
        const double reach_mm = cfg.csf_margin_mm + std::max(0.0, cfg.erode_mm - 2.0);
        MaskImage::Pointer ic;
        if (cfg.csf_geodesic) {
            // Geodesic: the dark voxels reached within the reach through voxels no brighter than
            // csf + 0.3 (gm - csf). The
            // Euclidean band let the growth wrap round a bright layer (seg3d's marrow under a
            // thin outer table) into the dark bone beyond it, and the closing then filled the
            // layer in between: a bright sheet over the cortex.
            const double t_pass = std::max(t_csf, cls[0] + 0.3 * (cls[1] - cls[0]));
            const uint8_t* ep = env ? env->GetBufferPointer() : nullptr;
            std::vector<uint8_t> passage(n, 0);
            for (size_t i = 0; i < n; ++i) passage[i] = img[i] <= t_pass && (!ep || ep[i]);
            const auto reached = geodesic_reach(box, seed->GetBufferPointer(), passage, reach_mm);
            ic = new_mask(box);
            uint8_t* ip = ic->GetBufferPointer();
            const uint8_t* sp = seed->GetBufferPointer();
            for (size_t i = 0; i < n; ++i) ip[i] = (sp[i] || (reached[i] && img[i] <= t_csf)) ? 1 : 0;
            step("intracranial CSF", 0.7);
            ic = pick_overlapping(ic, seed);
        } else {
            ic = morph(seed, box, reach_mm);
            {
                uint8_t* ip = ic->GetBufferPointer();
                const uint8_t* sp = seed->GetBufferPointer();
                for (size_t i = 0; i < n; ++i) ip[i] = (sp[i] || (ip[i] && img[i] <= t_csf)) ? 1 : 0;
            }
            if (env) and_into(ic, env);
            step("intracranial CSF", 0.7);
            ic = pick_overlapping(ic, seed);
        }
        step("closing", 0.75);
        seed = close(ic, box, cfg.close_mm);
    }

    if (env) and_into(seed, env);

    // Opening: thin sheets that leaked along the dura or into the temporal muscle are narrower
    // than 2 * open_mm, the brain is not; keep the central part and grow it back inside the mask.
    if (cfg.open_mm > 0) {
        step("opening", 0.8);
        auto core = morph(seed, box, -cfg.open_mm);
        core = pick_central(core, box, dist2_mm, 0.5 * radius_mm);
        if (core) {
            // + 1.5 voxels: the distance maps count from boundary voxel centres (no net shrink).
            auto back = morph(core, box, cfg.open_mm + 1.5 * max_sp);
            and_into(back, seed);
            seed = back;
        }
    }

    // 10. Fill enclosed cavities (ventricles, dark lesions).
    step("hole filling", 0.85);
    seed = fill_holes(seed);

    // 11. Final margin (positive: outwards).
    step("final margin", 0.93);
    if (cfg.final_dilate_mm != 0.0) seed = morph(seed, box, cfg.final_dilate_mm);

    const size_t n_brain = count_on(seed);
    rep.brain_ml = double(n_brain) * voxel_ml;
    if (rep.brain_ml < cfg.min_brain_ml || rep.brain_ml > cfg.max_brain_ml)
        throw InputError(kInput, "the brain found is " + fmt(rep.brain_ml) + " mL, outside the plausible range " +
                                     fmt(cfg.min_brain_ml) + ".." + fmt(cfg.max_brain_ml) +
                                     " mL (is this a T1 head MRI?)");

    mask.assign(n_all, 0);
    const uint8_t* sp = seed->GetBufferPointer();
    for (int k = 0; k < box.dims[2]; ++k)
        for (int j = 0; j < box.dims[1]; ++j)
            std::copy_n(sp + box.linear(0, j, k), box.dims[0],
                        mask.data() + full.linear(box.lo[0], box.lo[1] + j, box.lo[2] + k));
    step("done", 1.0);
}

void valley_snap(const Grid& grid, const float* voxels, std::vector<uint8_t>& mask, double cap, double max_mm) {
    Block full;
    full.dims = grid.dims;
    full.spacing_mm = grid.spacing;
    const size_t n = full.count();
    if (mask.size() != n || max_mm <= 0) return;
    // Lightly smoothed (sigma one voxel of the finest axis), so noise does not end the descent.
    auto f = new_float(full);
    std::copy_n(voxels, n, f->GetBufferPointer());
    const double min_sp = std::min({grid.spacing[0], grid.spacing[1], grid.spacing[2]});
    const auto sm = smooth(f, min_sp);
    const float* sv = sm->GetBufferPointer();
    const float top = float(cap);
    const std::array<ptrdiff_t, 3> stride{1, ptrdiff_t(grid.dims[0]), ptrdiff_t(grid.dims[0]) * grid.dims[1]};
    auto inside = [&](int i, int j, int k) {
        return i > 0 && j > 0 && k > 0 && i + 1 < grid.dims[0] && j + 1 < grid.dims[1] && k + 1 < grid.dims[2];
    };
    std::vector<size_t> front, next;
    for (int k = 0; k < grid.dims[2]; ++k)
        for (int j = 0; j < grid.dims[1]; ++j)
            for (int i = 0; i < grid.dims[0]; ++i) {
                const size_t li = full.linear(i, j, k);
                if (!mask[li] || !inside(i, j, k)) continue;
                bool edge = false;
                for (int a = 0; a < 3 && !edge; ++a)
                    edge = !mask[li + size_t(stride[a])] || !mask[li - size_t(stride[a])];
                if (edge) front.push_back(li);
            }
    // Steps of the finest axis; a step along a coarse axis (a thick slice) counts as one too: it
    // takes in the next slice out where that slice is darker, which is what the ray caster's
    // interpolation between slices needs.
    const int steps = int(std::lround(max_mm / min_sp));
    for (int it = 0; it < steps && !front.empty(); ++it) {
        next.clear();
        for (const size_t li : front) {
            const int i = int(li % size_t(grid.dims[0])), j = int((li / size_t(grid.dims[0])) % size_t(grid.dims[1])),
                      k = int(li / size_t(stride[2]));
            const std::array<int, 3> at{i, j, k};
            for (int a = 0; a < 3; ++a)
                for (int sgn = -1; sgn <= 1; sgn += 2) {
                    std::array<int, 3> nb3 = at;
                    nb3[a] += sgn;
                    if (!inside(nb3[0], nb3[1], nb3[2])) continue;
                    const size_t nb = size_t(ptrdiff_t(li) + sgn * stride[a]);
                    if (mask[nb] || !(sv[nb] < sv[li]) || sv[nb] > top) continue;
                    mask[nb] = 1;
                    next.push_back(nb);
                }
        }
        front.swap(next);
    }
    // A ring of voxels taken round a pocket closes it: fill enclosed cavities again.
    auto m = new_mask(full);
    std::copy_n(mask.data(), n, m->GetBufferPointer());
    const auto filled = fill_holes(m);
    std::copy_n(filled->GetBufferPointer(), n, mask.data());
}

}  // namespace cf::itkb
