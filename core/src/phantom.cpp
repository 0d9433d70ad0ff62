// The phantom generator: pose, craniotomy, procedural surgical appearance, landmarks, ROI
// and truth for one synthetic case (see phantom.hpp). Writing and batching: phantom_io.cpp.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <random>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"

namespace cf {

void PhantomParams::validate() const {
    auto bad = [](const std::string& field, const std::string& why) { throw InputError("phantom " + field, why); };
    auto range2 = [&](const std::string& f, const std::array<double, 2>& r, double lo, double hi) {
        if (!(r[0] >= lo && r[1] <= hi && r[0] <= r[1]))
            bad(f, "range [" + std::to_string(r[0]) + ", " + std::to_string(r[1]) + "] must lie within [" +
                       std::to_string(lo) + ", " + std::to_string(hi) + "]");
    };
    auto prob = [&](const std::string& f, double p) {
        if (!(p >= 0 && p <= 1)) bad(f, "probability " + std::to_string(p) + " must be in [0, 1]");
    };
    if (width < 64 || height < 64 || width > 4000 || height > 4000)
        bad("size", std::to_string(width) + "x" + std::to_string(height) + " out of range (64..4000 each)");
    if (dslr_width < 64 || dslr_height < 64 || dslr_width > 8000 || dslr_height > 8000)
        bad("dslr size", "out of range (64..8000 each)");
    prob("dslr-fraction", dslr_fraction);
    prob("gauze-prob", gauze_prob);
    prob("blood-prob", blood_prob);
    if (sulcal_blood_prob) prob("sulcal-blood-prob", *sulcal_blood_prob);
    if (blood_film_prob) prob("blood-film-prob", *blood_film_prob);
    prob("lamp-spot-prob", lamp_spot_prob);
    prob("far-lamp-prob", far_lamp_prob);
    prob("skin-prep-prob", skin_prep_prob);
    prob("distortion-prob", distortion_prob);
    prob("png-fraction", png_fraction);
    range2("distance_mm", distance_mm, 100, 1000);
    range2("craniotomy_mm", craniotomy_mm, 20, 120);
    range2("fill_fraction", fill_fraction, 0.2, 1.2);
    range2("landmark_pixel_sd", landmark_pixel_sd, 0, 20);
    if (!(max_tilt_deg >= 0 && max_tilt_deg <= 60)) bad("max_tilt_deg", "must be in [0, 60]");
    if (!(landmark_world_sd_mm >= 0 && landmark_world_sd_mm <= 10)) bad("landmark_world_sd_mm", "must be in [0, 10]");
    if (landmarks_min < 4 || landmarks_max > 12 || landmarks_min > landmarks_max) bad("landmarks", "count range must lie within 4..12");
    if (targets_min < 5 || targets_max > 200 || targets_min > targets_max) bad("targets", "count range must lie within 5..200");
    if (fixed_camera) fixed_camera->validate("phantom fixed_camera");
    if (fixed_T_camera_from_world && !is_rigid(*fixed_T_camera_from_world)) bad("fixed_T_camera_from_world", "is not a rigid transform");
}

namespace {

constexpr double kPi = std::numbers::pi;
using Vec2 = Eigen::Vector2d;
using Vec3 = Eigen::Vector3d;
using Col = Eigen::Array3f;  // linear RGB

// ---------------------------------------------------------------- randomness
uint64_t splitmix64(uint64_t x) {
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

/// Portable draws (not std:: distributions, whose output is implementation-defined).
struct Rng {
    std::mt19937_64 g;
    explicit Rng(uint64_t s) : g(s) {}
    double uni() { return double(g() >> 11) * 0x1.0p-53; }
    double uni(double a, double b) { return a + (b - a) * uni(); }
    double uni(const std::array<double, 2>& r) { return uni(r[0], r[1]); }
    double normal() {
        const double u1 = std::max(uni(), 1e-300), u2 = uni();
        return std::sqrt(-2 * std::log(u1)) * std::cos(2 * kPi * u2);
    }
    int integer(int lo, int hi) { return std::min(hi, lo + int(uni() * (hi - lo + 1))); }
    bool chance(double p) { return uni() < p; }
    uint32_t u32() { return uint32_t(g() >> 32); }
};

inline uint32_t hash2(int x, int y, uint32_t s) {
    uint32_t h = s * 0x9E3779B1u ^ uint32_t(x) * 0x85EBCA77u ^ uint32_t(y) * 0xC2B2AE3Du;
    h ^= h >> 15;
    h *= 0x2C1B3C6Du;
    h ^= h >> 12;
    h *= 0x297A2D39u;
    h ^= h >> 15;
    return h;
}
inline float hashf(int x, int y, uint32_t s) { return float(hash2(x, y, s) & 0xFFFFFFu) / float(0xFFFFFF); }

/// Smooth value noise in [0, 1].
inline float vnoise(float x, float y, uint32_t s) {
    const float fx0 = std::floor(x), fy0 = std::floor(y);
    const int xi = int(fx0), yi = int(fy0);
    float fx = x - fx0, fy = y - fy0;
    fx = fx * fx * (3 - 2 * fx);
    fy = fy * fy * (3 - 2 * fy);
    const float a = hashf(xi, yi, s), b = hashf(xi + 1, yi, s), c = hashf(xi, yi + 1, s), d = hashf(xi + 1, yi + 1, s);
    return (a + (b - a) * fx) * (1 - fy) + (c + (d - c) * fx) * fy;
}
/// Fractal noise in about [0, 1], `oct` octaves starting at frequency 1.
inline float fbm(float x, float y, uint32_t s, int oct) {
    float sum = 0, amp = 0.5f, norm = 0;
    for (int o = 0; o < oct; ++o) {
        sum += amp * vnoise(x, y, s + uint32_t(o) * 1013u);
        norm += amp;
        x = x * 2.03f + 17.1f;
        y = y * 2.03f - 9.7f;
        amp *= 0.5f;
    }
    return sum / norm;
}

inline float smoothstep(float e0, float e1, float x) {
    const float t = std::clamp((x - e0) / (e1 - e0), 0.f, 1.f);
    return t * t * (3 - 2 * t);
}
inline float srgb_to_linear(float c) { return std::pow(std::clamp(c, 0.f, 1.f), 2.2f); }
inline Col rgb(double r, double g, double b) {
    return Col(srgb_to_linear(float(r / 255)), srgb_to_linear(float(g / 255)), srgb_to_linear(float(b / 255)));
}
inline Col mix(const Col& a, const Col& b, float t) { return a + (b - a) * t; }

/// What is seen through a layer of blood `h_mm` thick over `under` (light in and out again):
/// whole blood absorbs green and blue within a fraction of a millimetre and red far less, so a
/// thin film tints the tissue red and leaves its texture, and a thick layer shows only the
/// blood's own dark red `body`. Beer-Lambert per channel; the coefficients are rough, for looks.
inline Col through_blood(const Col& under, const Col& body, double h_mm) {
    const Col k_per_mm(2.f, 9.f, 7.f);
    const Col t = (-2.f * float(std::max(0.0, h_mm)) * k_per_mm).exp();
    return under * t + body * (1.f - t);
}

/// A colour jittered in brightness and per channel (multiplicative, linear space).
Col jitter(Rng& r, const Col& c, double bright, double chan) {
    const float k = float(1 + bright * (2 * r.uni() - 1));
    Col out = c * k;
    for (int i = 0; i < 3; ++i) out[i] *= float(1 + chan * (2 * r.uni() - 1));
    return out;
}

// ---------------------------------------------------------------- craniotomy geometry
/// The local head sphere (fitted to the smoothed brain around the craniotomy centre) and
/// polar coordinates on it: a point's (a, b) in mm is its angular position seen from the
/// sphere centre times the sphere radius, in the tangent basis (e1, e2) at the centre.
struct Crani {
    Vec3 c, n, e1, e2, O;  // centre on the smoothed brain, outward normal, tangents, sphere centre
    double Rc = 80;        // sphere radius (smoothed brain)
    // Bone cut radius r(theta) = base ellipse * (1 + harmonics).
    double R1 = 30, R2 = 25, phi = 0;
    std::array<double, 5> amp{}, phase{};
    std::array<double, 4> skin_amp{}, skin_phase{}, drape_amp{}, drape_phase{};
    double bone_w = 6, skin_w = 20, dura_w = 3;      // ring widths, mm
    double h_bone = 8, h_skin = 14;                 // heights above the brain sphere, mm
    // The sterile towels framing the field: towel k's hem is the line at towel_d[k] mm from the
    // centre, its outward normal at angle towel_psi[k]; towels later in the list lie on top.
    // Real drapes meet the scalp in straight edges, not in a smooth ring.
    int n_towels = 0;
    std::array<double, 5> towel_psi{}, towel_d{}, towel_tone{}, towel_weave_rad{}, towel_fold_mm{}, towel_fold_off{};
    double hem_mm = 4;  // the folded hem along a towel's edge
    // Burr holes at the rim of the bone flap (the flap is cut between them): angle, centre
    // distance and radius, mm.
    int n_burr = 0;
    std::array<double, 4> burr_th{}, burr_rho{}, burr_r{};
    // Scalp clips (Raney clips) along the skin edge: count, first angle, length and width, mm.
    int n_clips = 0;
    double clip_th0 = 0, clip_len = 9, clip_w = 4;
    Eigen::Array3f clip_col = Eigen::Array3f(0.05f, 0.15f, 0.6f);
    // The opened dura, folded back over the bone on one side: centre angle, half arc (rad) and
    // how far it reaches over the bone (mm); flap_w = 0 for none.
    double flap_th = 0, flap_half = 1, flap_w = 0;
    // A milky arachnoid bridging the sulci (0: clear), as over an older or inflamed brain.
    double veil = 0;
    // Blood besides the pools: subarachnoid blood filling the sulci over a patch (sah: its
    // strength, 0 for none) and a thin film of blood and irrigation over another (film_mm: its
    // thickness at the centre); centres and radii in (a, b) mm.
    double sah = 0, sah_r = 10, film_mm = 0, film_r = 10;
    Vec2 sah_c = Vec2::Zero(), film_c = Vec2::Zero();
    // The OR lamp's spot (spot_r_mm = 0: lit evenly, as by a flash): half-light radius on the
    // field, the light outside it as a fraction of the centre's, and its centre in (a, b) mm.
    // A surgical light is focused on the opening, so the drapes lie in its dimmer skirt.
    double spot_r_mm = 0, spot_floor = 1;
    Vec2 spot_c = Vec2::Zero();
    // Skin prep (povidone-iodine) staining the scalp around the opening: strength 0..1 (0: none).
    double prep = 0;
    // Clips are placed by hand: each one's angle (fraction of the spacing) and length vary.
    uint64_t clip_seed = 0;
    double clip_jitter = 0;
    // With the photographic finish (Look::finish) the clips are shaped as Raney clips, tapered
    // towards the jaws with rounded corners, and each is turned off the radius by up to
    // clip_tilt (rad); without it they are the plain bars drawn before, byte for byte.
    bool clip_shaped = false;
    double clip_tilt = 0;

    /// Whether (a, b), outside the bone cut, lies under the reflected dural flap; `edge_mm`: how
    /// far inside the flap's free edge.
    bool flap_at(const Vec2& ab, double* edge_mm) const {
        if (flap_w <= 0) return false;
        const double th = std::atan2(ab.y(), ab.x());
        const double dth = std::remainder(th - flap_th, 2 * kPi);
        if (std::abs(dth) >= flap_half) return false;
        const double q = dth / flap_half;
        const double reach = r_bone(th) + flap_w * std::sqrt(1 - q * q);
        if (ab.norm() >= reach) return false;
        if (edge_mm) *edge_mm = reach - ab.norm();
        return true;
    }

    Vec2 ab(const Vec3& p, double* height = nullptr) const {
        const Vec3 v = p - O;
        const double dist = v.norm();
        if (height) *height = dist - Rc;
        const Vec3 u = v / std::max(dist, 1e-9);
        const double cz = u.dot(n);
        const Vec3 w = u - cz * n;
        const double sw = w.norm();
        const double ang = std::atan2(sw, cz);
        if (sw < 1e-12) return Vec2::Zero();
        return Rc * ang / sw * Vec2(w.dot(e1), w.dot(e2));
    }
    double r_bone(double th) const {
        const double ct = std::cos(th - phi), st = std::sin(th - phi);
        double r = R1 * R2 / std::sqrt(R2 * R2 * ct * ct + R1 * R1 * st * st);
        double k = 1;
        for (size_t i = 0; i < amp.size(); ++i) k += amp[i] * std::cos(double(i + 2) * th + phase[i]);
        return r * k;
    }
    double r_skin(double th) const {
        double k = 1;
        for (size_t i = 0; i < skin_amp.size(); ++i) k += skin_amp[i] * std::cos(double(i + 1) * th + skin_phase[i]);
        return r_bone(th) + bone_w * k;
    }
    double r_drape(double th) const {
        if (n_towels > 0) return std::max(r_skin(th) + 1.5, r_towels(th));
        double k = 1;
        for (size_t i = 0; i < drape_amp.size(); ++i) k += drape_amp[i] * std::cos(double(i + 1) * th + drape_phase[i]);
        return r_skin(th) + skin_w * k;
    }
    /// Polar radius of the towels' window (the nearest hem crossed going out at angle th).
    double r_towels(double th) const {
        double r = 1e9;
        for (int k = 0; k < n_towels; ++k) {
            const double c = std::cos(th - towel_psi[size_t(k)]);
            if (c > 1e-3) r = std::min(r, towel_d[size_t(k)] / c);
        }
        return r;
    }
    /// The towel on top at (a, b) (-1: none) and how far inside it the point lies, mm.
    int towel_at(const Vec2& ab, double* inside_mm) const {
        for (int k = n_towels - 1; k >= 0; --k) {
            const double s = ab.x() * std::cos(towel_psi[size_t(k)]) + ab.y() * std::sin(towel_psi[size_t(k)]) - towel_d[size_t(k)];
            if (s > 0) {
                if (inside_mm) *inside_mm = s;
                return k;
            }
        }
        return -1;
    }
    /// Distance (mm, <= 0 inside) from (a, b) to the nearest burr hole's edge; +inf if none.
    double burr_edge(const Vec2& ab, double* radius = nullptr) const {
        double best = std::numeric_limits<double>::infinity();
        for (int k = 0; k < n_burr; ++k) {
            const Vec2 c = burr_rho[size_t(k)] * Vec2(std::cos(burr_th[size_t(k)]), std::sin(burr_th[size_t(k)]));
            const double d = (ab - c).norm() - burr_r[size_t(k)];
            if (d < best) {
                best = d;
                if (radius) *radius = burr_r[size_t(k)];
            }
        }
        return best;
    }
    /// Signed distance (mm, < 0 inside) from (a, b) to the nearest shaped clip's outline, and
    /// where in that clip it lies: `along` 0 at the jaws (the skin edge) to 1 at the spring,
    /// `across` -1..1, and the clip's axis (rad). +inf without clips.
    /// Where the clip of slot k (any integer; its draws are those of k modulo n_clips) sits: its
    /// angle on the skin's edge and its length (each offset by clip_jitter), its jaws' distance
    /// from the centre, and its turn off the radius (by up to clip_tilt).
    struct ClipPlace {
        double th, len, r0, tilt;
    };
    ClipPlace clip_place(double k) const {
        const int slot = ((int(k) % n_clips) + n_clips) % n_clips;
        const uint64_t h = splitmix64(clip_seed + uint64_t(slot));
        const double j1 = double(h >> 11) * 0x1.0p-53 - 0.5, j2 = double((h * 0x9E3779B97F4A7C15ull) >> 11) * 0x1.0p-53 - 0.5;
        const double j3 = double(splitmix64(h) >> 11) * 0x1.0p-53 - 0.5;
        ClipPlace c;
        c.th = clip_th0 + (k + clip_jitter * 0.6 * j1) * (2 * kPi / n_clips);
        c.len = clip_len * (1 + clip_jitter * 0.3 * j2);
        c.r0 = r_skin(c.th) - 1.0;
        c.tilt = 2 * clip_tilt * j3;
        return c;
    }
    /// The slot nearest angle th. A clip's offsets may move it off its slot, so callers try
    /// the slots on either side too.
    double clip_slot_near(double th) const { return std::round((th - clip_th0) / (2 * kPi / n_clips)); }
    double clip_sdf(const Vec2& ab, double* along01 = nullptr, double* across = nullptr, double* axis_rad = nullptr) const {
        double best = std::numeric_limits<double>::infinity();
        if (n_clips == 0) return best;
        const double k0 = clip_slot_near(std::atan2(ab.y(), ab.x()));
        for (double k = k0 - 1; k <= k0 + 1; ++k) {
            const ClipPlace cp = clip_place(k);
            const double thc = cp.th, len = cp.len, r0 = cp.r0, tilt = cp.tilt;
            const Vec2 dir(std::cos(thc + tilt), std::sin(thc + tilt)), side(-dir.y(), dir.x());
            const Vec2 q = ab - r0 * Vec2(std::cos(thc), std::sin(thc));
            const double along = q.dot(dir), t = std::clamp(along / len, 0.0, 1.0);
            // Narrower at the jaws than at the spring; the corners rounded (a rounded box).
            const double half_w = 0.5 * clip_w * (0.85 + 0.3 * t), rr = 0.3 * clip_w;
            const double px = std::abs(along - 0.5 * len) - (0.5 * len - rr), py = std::abs(q.dot(side)) - (half_w - rr);
            const double d = std::hypot(std::max(px, 0.0), std::max(py, 0.0)) + std::min(std::max(px, py), 0.0) - rr;
            if (d < best) {
                best = d;
                if (along01) *along01 = t;
                if (across) *across = std::clamp(q.dot(side) / half_w, -1.0, 1.0);
                if (axis_rad) *axis_rad = thc + tilt;
            }
        }
        return best;
    }
    /// Whether (a, b) on the skin lies under a scalp clip; `across` in [-1, 1] across its width.
    bool clip_at(const Vec2& ab, double* across) const {
        if (n_clips == 0) return false;
        if (clip_shaped) return clip_sdf(ab, nullptr, across) < 0;
        if (ab.norm() <= 0) return false;
        const double k0 = clip_slot_near(std::atan2(ab.y(), ab.x()));
        for (double k = k0 - 1; k <= k0 + 1; ++k) {
            const ClipPlace cp = clip_place(k);
            const double thc = cp.th, len = cp.len, r0 = cp.r0;
            const Vec2 dir(std::cos(thc), std::sin(thc)), side(-dir.y(), dir.x());
            const Vec2 q = ab - r0 * dir;
            const double along = q.dot(dir), acr = q.dot(side);
            if (along < 0 || along > len || std::abs(acr) > clip_w / 2) continue;
            if (across) *across = acr / (clip_w / 2);
            return true;
        }
        return false;
    }
    /// Nearest intersection of a ray with the sphere of radius Rc + h; false if missed.
    bool hit_sphere(const Vec3& C, const Vec3& d, double h, Vec3& q) const {
        const Vec3 m = C - O;
        const double R = Rc + h, b = m.dot(d), cc = m.squaredNorm() - R * R, disc = b * b - cc;
        if (disc < 0) return false;
        const double s = -b - std::sqrt(disc);
        if (s <= 0) return false;
        q = C + s * d;
        return true;
    }
};

// ---------------------------------------------------------------- vessels
struct VesselPath {
    std::vector<Vec2> pts;      // mm in (a, b)
    std::vector<double> radius; // mm
    int kind = 0;               // 0 vein, 1 artery, 2 small
};

/// A texture over the craniotomy in (a, b) mm: sulcal depth of the outermost surface,
/// the triangle seen along the sphere normal (to lift texture points to 3D), vessel layers.
struct Texture {
    double E = 60, texel = 0.12;  // half extent, mm per texel
    int N = 1000;
    RasterBuffers ortho;          // per texel: triangle + barycentrics
    cv::Mat sulc;                 // CV_32F sulcal depth, mm (0 where no surface)
    cv::Mat sulc_blur;            // smoothed, for vessel steering
    cv::Mat vein, artery, small;  // CV_32F alpha in [0, 1]
    cv::Mat vein_tube, artery_tube;  // CV_32F tube profile: 0 at a vessel's edge, 1 on its axis
    cv::Mat grad_x, grad_y;       // CV_32F height-map gradient (mm per mm)
    std::vector<Vec2> bifurcations_ab;

    Vec2 to_tex(const Vec2& ab) const { return (ab + Vec2(E, E)) / texel; }
    float sample(const cv::Mat& m, const Vec2& ab) const {
        const Vec2 t = to_tex(ab);
        const float x = float(t.x()), y = float(t.y());
        if (x < 0 || y < 0 || x > float(N - 1) || y > float(N - 1)) return 0.f;
        const int x0 = std::min(int(x), N - 2), y0 = std::min(int(y), N - 2);
        const float fx = x - float(x0), fy = y - float(y0);
        const float* r0 = m.ptr<float>(y0);
        const float* r1 = m.ptr<float>(y0 + 1);
        return (r0[x0] * (1 - fx) + r0[x0 + 1] * fx) * (1 - fy) + (r1[x0] * (1 - fx) + r1[x0 + 1] * fx) * fy;
    }
};

void trace_vessel(Texture& tx, Rng& rng, Vec2 p, Vec2 dir, double radius, int kind, int depth, double max_len_mm,
                  std::vector<VesselPath>& out) {
    VesselPath v;
    v.kind = kind;
    const double step = 0.4;
    const double steer = kind == 0 ? 0.6 : (kind == 1 ? 0.35 : 0.0);
    const double wiggle = kind == 2 ? 0.35 : (kind == 1 ? 0.12 : 0.08);
    double len = 0, r = radius;
    dir.normalize();
    double turn = 0;
    while (len < max_len_mm && p.norm() < tx.E * 0.98) {
        v.pts.push_back(p);
        v.radius.push_back(r);
        // Steer towards deeper sulci (veins mostly), with momentum and a smooth random turn.
        const Vec2 t = tx.to_tex(p);
        const int xi = std::clamp(int(t.x()), 2, tx.N - 3), yi = std::clamp(int(t.y()), 2, tx.N - 3);
        const float gx = tx.sulc_blur.at<float>(yi, xi + 2) - tx.sulc_blur.at<float>(yi, xi - 2);
        const float gy = tx.sulc_blur.at<float>(yi + 2, xi) - tx.sulc_blur.at<float>(yi - 2, xi);
        Vec2 g(gx, gy);
        if (g.norm() > 1e-6) g = g.normalized() * std::min(1.0, g.norm() * 0.5);
        turn = 0.85 * turn + wiggle * rng.normal() * 0.5;
        const double ct = std::cos(turn * 0.3), st = std::sin(turn * 0.3);
        dir = Vec2(ct * dir.x() - st * dir.y(), st * dir.x() + ct * dir.y());
        dir = (dir + steer * 0.25 * g).normalized();
        p += step * dir;
        len += step;
        r *= kind == 0 ? 0.9995 : 0.998;
        // Branches (tributaries of veins, arterial bifurcations).
        const double pb = kind == 0 ? 0.006 : (kind == 1 ? 0.012 : 0.0);
        if (depth < 3 && rng.chance(pb) && len > 3 && p.norm() < tx.E * 0.9) {
            const double side = rng.chance(0.5) ? 1 : -1;
            const double ang = side * rng.uni(0.5, 1.2);
            const Vec2 bd(std::cos(ang) * dir.x() - std::sin(ang) * dir.y(), std::sin(ang) * dir.x() + std::cos(ang) * dir.y());
            const double br = r * rng.uni(0.4, 0.75);
            if (br > 0.12) tx.bifurcations_ab.push_back(p);
            if (kind == 1) r *= 0.85;  // a bifurcating artery gets thinner
            trace_vessel(tx, rng, p, bd, br, kind, depth + 1, max_len_mm * rng.uni(0.3, 0.7), out);
        }
        if (r < 0.04) break;
    }
    if (v.pts.size() > 2) out.push_back(std::move(v));
}

void draw_vessels(Texture& tx, const std::vector<VesselPath>& vessels) {
    cv::Mat layers[3];
    for (auto& l : layers) l = cv::Mat::zeros(tx.N, tx.N, CV_8U);
    constexpr int shift = 4;
    const double sc = double(1 << shift);
    for (const auto& v : vessels) {
        cv::Mat& L = layers[v.kind];
        for (size_t i = 1; i < v.pts.size(); ++i) {
            const Vec2 a = tx.to_tex(v.pts[i - 1]), b = tx.to_tex(v.pts[i]);
            const int th = std::max(1, int(std::lround(2 * v.radius[i] / tx.texel)));
            const double alpha = v.kind == 2 ? std::clamp(v.radius[i] / 0.15, 0.3, 1.0) : 1.0;
            cv::line(L, cv::Point(int(a.x() * sc), int(a.y() * sc)), cv::Point(int(b.x() * sc), int(b.y() * sc)),
                     cv::Scalar(255 * alpha), th, cv::LINE_AA, shift);
        }
    }
    cv::Mat* dst[3] = {&tx.vein, &tx.artery, &tx.small};
    for (int k = 0; k < 3; ++k) {
        layers[k].convertTo(*dst[k], CV_32F, 1.0 / 255);
        cv::GaussianBlur(*dst[k], *dst[k], cv::Size(0, 0), 0.8);
    }
}

// ---------------------------------------------------------------- appearance
struct Look {
    Col cortex, sulcus, vein, artery, small_vessel, bone, bone_wall, dura, skin, skin_cut, drape, gauze, blood;
    Col iodine = rgb(150, 78, 30);  // dried povidone-iodine on skin
    Col light = Col(1, 1, 1), wb = Col(1, 1, 1);
    double ambient = 0.2, diffuse = 0.9, spec = 1.0, shininess = 60, exposure = 1.0;
    double bump_mm = 0.12, bump_scale_mm = 0.8, mottle = 0.12;
    double vignette = 0.3, blur_px = 0.6, noise_sd = 2.0;
    int jpeg_quality = 90;
    Vec3 light_offset_camera_mm = Vec3::Zero();
    double drape_weave_px = 3.0;
    int drape_kind = 0;
    uint32_t nseed = 1;
    // The photographic finish, drawn by add_finish() from a stream of the look's own seed, so
    // that adding it moved no other draw: the drapes' soft folds (wavelength, steepest slope,
    // direction), the lamp's reflection in a pool of blood (half the lamp's angular radius, as
    // the half-vector sees it), the lens' halation around glare and its lateral colour (red
    // scaled up and blue down about the centre by this fraction), a shaved scalp's stubble.
    bool finish = true;  // false: the appearance before the finish (PhantomParams::photo_finish)
    double fold_mm = 40, fold_slope = 0.6, fold_psi = 0;
    double lamp_half_deg = 4;
    double bloom = 0.3, chroma = 0.0005;
    bool stubble = true;
    // The rim of the opening, by hand (drawn after the above, so they kept their values): the
    // clips turned off the radius by up to clip_tilt_deg; the dura cut with scissors, its edge
    // ragged by dura_rag of its width; tack-up sutures (their count and colour) from its edge to
    // the bone; soft tissue (pericranium, muscle) left on the outer part of the bone, up to
    // tissue_frac of its width; cautery char along the bone's outer edge; trickles of blood
    // from the scalp's cut edge over the skin.
    double clip_tilt_deg = 0, dura_rag = 0, tissue_frac = 0, char_k = 0;
    int n_sutures = 0, n_trickles = 0;
    // The dura as a membrane held open (drawn after the rim's draws): meningeal vessels of
    // strength dura_vessels, greyer and bluer in places by up to dura_grey, folded towards the
    // tack-ups, its cut edge thickened and stained.
    double dura_vessels = 0, dura_grey = 0;
    Col suture = Col(0.02f, 0.02f, 0.03f);
    // Light scattered under the cortex's surface (drawn last of all, from its own stream): the
    // red channel's spread at the surface in mm (green and blue spread less: blood absorbs them)
    // and the share of the light that comes out away from where it went in. 0: none.
    double scatter_mm = 0, scatter_share = 0;
    // A pool of blood as a mirror (same stream, after the scatter): the OR lamp's half-width as
    // the half-vector sees it (a light head is some 60 cm across at about a metre, so its image
    // is large and soft, not a point), and the ripple of its surface, mm (isotropic, so the
    // lamp's image breaks into rounded glints rather than the blocks a lattice noise gives).
    double pool_lamp_half_deg = 0, pool_ripple_mm = 0;
};

Look random_look(Rng& r) {
    Look L;
    // Cortex: a mix of pink, pale-yellowish, red and greyish tissue (subjects and lighting vary).
    const Col pink = rgb(222, 158, 148), pale = rgb(230, 192, 168), red = rgb(208, 118, 108), grey = rgb(196, 164, 164);
    double w[4] = {r.uni(0.5, 1.5), r.uni(0, 1.0), r.uni(0, 1.0), r.uni(0, 0.6)};
    const double ws = w[0] + w[1] + w[2] + w[3];
    L.cortex = (pink * float(w[0]) + pale * float(w[1]) + red * float(w[2]) + grey * float(w[3])) / float(ws);
    L.cortex = jitter(r, L.cortex, 0.12, 0.06);
    L.sulcus = jitter(r, rgb(150, 62, 62), 0.2, 0.08);
    L.vein = jitter(r, r.chance(0.5) ? rgb(92, 24, 48) : rgb(118, 30, 40), 0.25, 0.1);
    L.artery = jitter(r, rgb(190, 52, 48), 0.15, 0.08);
    L.small_vessel = jitter(r, rgb(170, 60, 60), 0.15, 0.08);
    L.bone = jitter(r, rgb(226, 214, 184), 0.1, 0.04);
    L.bone_wall = jitter(r, rgb(176, 120, 96), 0.15, 0.08);
    L.dura = jitter(r, rgb(214, 196, 190), 0.1, 0.05);
    L.skin = jitter(r, rgb(214, 164, 138), 0.15, 0.06);
    L.skin_cut = jitter(r, rgb(130, 28, 24), 0.2, 0.08);
    L.drape_kind = r.integer(0, 2);
    const Col drapes[3] = {rgb(52, 118, 98), rgb(58, 98, 150), rgb(70, 135, 140)};
    L.drape = jitter(r, drapes[L.drape_kind], 0.2, 0.1);
    L.gauze = jitter(r, rgb(244, 244, 238), 0.05, 0.02);
    L.blood = jitter(r, rgb(105, 10, 14), 0.3, 0.1);
    // Light: near the camera (ring flash, headlamp or OR lamp), warm or cool.
    const double temp = r.uni(-1, 1);  // -1 cool, +1 warm
    L.wb = Col(float(1 + 0.10 * temp), 1.f, float(1 - 0.12 * temp));
    L.light = Col(1, 1, 1);
    L.ambient = r.uni(0.12, 0.3);
    L.diffuse = r.uni(0.75, 1.0);
    L.spec = r.uni(0.8, 2.5);
    L.shininess = r.uni(80, 400);
    L.exposure = r.uni(0.8, 1.25);
    L.bump_mm = r.uni(0.1, 0.3);
    L.bump_scale_mm = r.uni(0.4, 1.0);
    L.mottle = r.uni(0.05, 0.2);
    L.vignette = r.uni(0.1, 0.5);
    L.blur_px = r.uni(0.3, 1.1);
    L.noise_sd = r.uni(1.0, 4.5);
    L.jpeg_quality = r.integer(60, 95);
    L.light_offset_camera_mm = Vec3(r.uni(-120, 120), r.uni(-120, 120), r.uni(-40, 20));
    L.drape_weave_px = r.uni(2.0, 4.5);
    L.nseed = r.u32();
    return L;
}

void add_finish(Look& L, bool on, bool tissue_optics) {
    Rng r(splitmix64(uint64_t(L.nseed) * 0x94D049BB133111EBull + 0xF1215Bull));
    L.finish = on;
    L.fold_mm = r.uni(5, 15);
    L.fold_slope = r.uni(0.4, 1.0);
    L.fold_psi = r.uni(0, kPi);
    L.lamp_half_deg = r.uni(1.0, 3.0);
    L.bloom = r.uni(0.1, 0.5);
    L.chroma = r.uni(0, 0.0012);
    L.stubble = r.chance(0.7);
    L.clip_tilt_deg = r.uni(5, 20);
    L.dura_rag = r.uni(0.3, 0.8);
    L.n_sutures = r.integer(0, 4);
    L.suture = r.chance(0.5) ? Col(0.015f, 0.015f, 0.02f) : Col(0.02f, 0.03f, 0.12f);  // black nylon, blue prolene
    L.tissue_frac = r.uni(0.1, 0.6);
    L.char_k = r.uni(0.2, 0.8);
    L.n_trickles = r.integer(0, 4);
    L.dura_vessels = r.uni(0.4, 0.9);
    L.dura_grey = r.uni(0.1, 0.5);
    if (!on) {  // drawn all the same, then cleared
        L.fold_slope = L.bloom = L.chroma = 0, L.stubble = false;
        L.clip_tilt_deg = L.dura_rag = L.tissue_frac = L.char_k = 0, L.n_sutures = L.n_trickles = 0;
        L.dura_vessels = L.dura_grey = 0;
    }
    // The cortex scatters light under its surface (grey matter's reduced scattering length is
    // about 1 mm in the red, less in green and blue), so a photograph's shading is soft and
    // reddish where a surface model's is hard: lit crowns bleed into the sulci's edges. Its own
    // stream, after all the above, so none of their values moved.
    Rng s(splitmix64(uint64_t(L.nseed) * 0xBF58476D1CE4E5B9ull + 0x55CA7Eull));
    L.scatter_mm = s.uni(0.5, 1.3);
    L.scatter_share = s.uni(0.45, 0.8);
    L.pool_lamp_half_deg = s.uni(1.5, 4);
    L.pool_ripple_mm = s.uni(0.01, 0.04);
    if (!on || !tissue_optics) L.scatter_mm = L.scatter_share = L.pool_lamp_half_deg = L.pool_ripple_mm = 0;
}

enum Layer : uint8_t { kDrape = 0, kSkin, kSkinCut, kBone, kDura, kBoneWall, kCortex, kDark, kBurr, kClip, kDuraFlap };

// ---------------------------------------------------------------- helpers
/// Camera distortion coefficients for a consumer lens.
std::array<double, 5> random_distortion(Rng& r) {
    const double k1 = r.uni(-0.15, 0.08);
    return {k1, r.uni(-0.3, 0.3) * std::abs(k1), r.uni(-0.0015, 0.0015), r.uni(-0.0015, 0.0015), 0.0};
}

/// Least-squares radius of the sphere tangent at c with normal n through points `pts`.
double fit_sphere_radius(const std::vector<Vec3>& pts, const Vec3& c, const Vec3& n) {
    double best = 80, best_cost = 1e300;
    for (double R = 40; R <= 250; R += 2) {
        const Vec3 O = c - n * R;
        double cost = 0;
        for (const auto& p : pts) {
            const double e = (p - O).norm() - R;
            cost += e * e;
        }
        if (cost < best_cost) best_cost = cost, best = R;
    }
    return best;
}

/// Evenly spaced points (by arc length) along a closed contour.
std::vector<Vec2> resample_closed(const std::vector<cv::Point>& c, int n) {
    std::vector<double> acc(c.size() + 1, 0.0);
    for (size_t i = 0; i < c.size(); ++i) {
        const cv::Point d = c[(i + 1) % c.size()] - c[i];
        acc[i + 1] = acc[i] + std::hypot(double(d.x), double(d.y));
    }
    std::vector<Vec2> out;
    const double L = acc.back();
    size_t j = 0;
    for (int k = 0; k < n; ++k) {
        const double s = L * k / n;
        while (j + 1 < acc.size() - 1 && acc[j + 1] < s) ++j;
        const double seg = acc[j + 1] - acc[j];
        const double t = seg > 0 ? (s - acc[j]) / seg : 0;
        const cv::Point a = c[j], b = c[(j + 1) % c.size()];
        out.emplace_back(a.x + t * (b.x - a.x), a.y + t * (b.y - a.y));
    }
    return out;
}

std::string fmt(double v, int prec = 2) {
    std::ostringstream s;
    s.setf(std::ios::fixed);
    s.precision(prec);
    s << v;
    return s.str();
}

}  // namespace

// ================================================================ one case
PhantomCase generate_phantom_case(const PhantomSurface& S, const PhantomParams& P, int index) {
    P.validate();
    Rng rng(splitmix64(P.seed * 0x100000001B3ull + splitmix64(uint64_t(index) + 1)));
    PhantomCase out;
    std::ostringstream notes;

    // ---- image size: base (varied) or DSLR
    const bool dslr = rng.chance(P.dslr_fraction);
    int W = P.width, H = P.height;
    if (P.vary_size) {
        const double aspects[3] = {1.5, 4.0 / 3.0, 1.6};
        const double asp = aspects[rng.integer(0, 2)];
        W = int(std::lround(P.width * rng.uni(0.8, 1.2)));
        H = int(std::lround(W / asp));
    }
    if (dslr) W = P.dslr_width, H = P.dslr_height;
    if (P.fixed_camera) W = P.fixed_camera->width, H = P.fixed_camera->height;
    // Render at most ~1600 px wide, upscale after (a DSLR photo is rarely sharper than that).
    const double render_scale = std::min(1.0, 1600.0 / W);
    const int rw = std::max(32, int(std::lround(W * render_scale))), rh = std::max(32, int(std::lround(H * render_scale)));

    // ---- craniotomy centre on the upper / lateral convexity
    const size_t nv = S.mesh.vertices.size();
    std::vector<size_t> cand;
    for (size_t i = 0; i < nv; i += 7) {
        const Eigen::Vector3f& n = S.smooth_normals[i];
        const bool convex = n.z() > -0.1f && (std::abs(n.x()) > 0.45f || n.z() > 0.6f) && std::abs(n.y()) < 0.75f;
        if (convex && S.sulcal_depth_mm[i] < 1.0f && (S.smooth_vertices[i] - S.centroid_world_mm).dot(n) > 0) cand.push_back(i);
    }
    if (cand.empty()) throw InputError("brain surface", "no convex upper/lateral region found for a craniotomy");
    const size_t ci = cand[size_t(rng.integer(0, int(cand.size()) - 1))];
    Crani cr;
    cr.c = S.smooth_vertices[ci].cast<double>();
    const double diam = rng.uni(P.craniotomy_mm);
    {
        Vec3 nsum = Vec3::Zero();
        std::vector<Vec3> near;
        const Vec3 nc = S.smooth_normals[ci].cast<double>();
        for (size_t i = 0; i < nv; i += 3) {
            const Vec3 p = S.smooth_vertices[i].cast<double>();
            const double d = (p - cr.c).norm();
            if (d < 0.5 * diam + 12 && S.smooth_normals[i].cast<double>().dot(nc) > 0.5) {
                if (d < 20) nsum += S.smooth_normals[i].cast<double>();
                near.push_back(p);
            }
        }
        cr.n = nsum.norm() > 0 ? nsum.normalized() : nc.normalized();
        cr.Rc = fit_sphere_radius(near, cr.c, cr.n);
    }
    cr.e1 = cr.n.unitOrthogonal();
    cr.e2 = cr.n.cross(cr.e1);
    cr.O = cr.c - cr.n * cr.Rc;
    cr.R1 = diam / 2;
    cr.R2 = cr.R1 * rng.uni(0.7, 1.0);
    cr.phi = rng.uni(0, kPi);
    for (size_t i = 0; i < cr.amp.size(); ++i) cr.amp[i] = rng.normal() * 0.035 / double(i + 1), cr.phase[i] = rng.uni(0, 2 * kPi);
    for (size_t i = 0; i < cr.skin_amp.size(); ++i) {
        cr.skin_amp[i] = rng.normal() * 0.2;
        cr.skin_phase[i] = rng.uni(0, 2 * kPi);
        cr.drape_amp[i] = rng.normal() * 0.12;
        cr.drape_phase[i] = rng.uni(0, 2 * kPi);
    }
    cr.bone_w = rng.uni(3, 9);
    cr.skin_w = rng.uni(6, 35);
    cr.dura_w = rng.uni(1.5, 5);
    const double bone_above_rim = rng.uni(0.5, 3.0), scalp_mm = rng.uni(2, 5);
    {
        // The surgical field around the opening: towels, burr holes, scalp clips. Drawn from a
        // stream of their own so that poses, landmarks and the rest of a seed's case stay as they
        // were before these were added.
        Rng rx(splitmix64(P.seed * 0x2545F4914F6CDD1Dull + splitmix64(uint64_t(index) + 0x51EDull)));
        cr.n_towels = rx.integer(3, 5);
        const double base = rx.uni(0, 2 * kPi), margin = cr.skin_w * rx.uni(0.15, 0.5);
        for (int k = 0; k < cr.n_towels; ++k) {
            const size_t kk = size_t(k);
            cr.towel_psi[kk] = base + 2 * kPi * k / cr.n_towels + rx.uni(-0.25, 0.25);
            double reach = 0;  // the towel's hem clears the skin edge plus a margin everywhere
            for (int j = 0; j < 180; ++j) {
                const double th = 2 * kPi * j / 180;
                reach = std::max(reach, (cr.r_skin(th) + margin) * std::cos(th - cr.towel_psi[kk]));
            }
            cr.towel_d[kk] = reach + cr.skin_w * rx.uni(0, 0.6);
            cr.towel_tone[kk] = rx.uni(0.85, 1.15);
            cr.towel_weave_rad[kk] = rx.uni(0, kPi);
            cr.towel_fold_mm[kk] = rx.uni(45, 90);
            cr.towel_fold_off[kk] = rx.uni(0, 90);
        }
        cr.hem_mm = rx.uni(3, 6);
        cr.n_burr = rx.integer(1, 4);
        const double burr_base = rx.uni(0, 2 * kPi);
        for (int k = 0; k < cr.n_burr; ++k) {
            const size_t kk = size_t(k);
            cr.burr_th[kk] = burr_base + 2 * kPi * k / cr.n_burr + rx.uni(-0.3, 0.3);
            cr.burr_r[kk] = rx.uni(3.5, 7.0);  // 7-14 mm perforators
            cr.burr_rho[kk] = cr.r_bone(cr.burr_th[kk]) + cr.burr_r[kk] * rx.uni(0.0, 0.5);
        }
        if (rx.chance(0.6)) {
            const double perimeter = 2 * kPi * (cr.R1 + cr.R2) / 2 + 2 * kPi * cr.bone_w;
            cr.n_clips = std::max(4, int(std::lround(perimeter / rx.uni(12, 20))));
            cr.clip_th0 = rx.uni(0, 2 * kPi);
            cr.clip_len = rx.uni(8, 11);
            cr.clip_w = rx.uni(3.5, 5);
            const Eigen::Array3f cols[3] = {{0.06f, 0.16f, 0.42f}, {0.62f, 0.64f, 0.62f}, {0.06f, 0.06f, 0.07f}};
            cr.clip_col = cols[rx.integer(0, 2)] * float(rx.uni(0.85, 1.15));
        }
        if (rx.chance(0.7)) {
            cr.flap_th = rx.uni(0, 2 * kPi);
            cr.flap_half = rx.uni(0.5, 1.2);
            cr.flap_w = std::min(rx.uni(6, 20), cr.bone_w + 2);
        }
        if (rx.chance(0.4)) cr.veil = rx.uni(0.2, 0.6);
    }
    {
        // Blood in the sulci and as a film: a stream of their own too, so a seed's poses,
        // landmarks and ROI stay as they were before these were added.
        Rng rbd(splitmix64(P.seed * 0x9FB21C651E98DF25ull + splitmix64(uint64_t(index) + 0xB100Dull)));
        const double rc = 0.5 * (cr.R1 + cr.R2);
        // `-> Vec2`: a deduced return type was Eigen's product expression, which referred to the
        // Vec2 temporary after it died; the patches' centres were whatever the stack then held
        // (1e7 mm off on one VM, 0 on another), so the blood was drawn off the cortex or at its middle.
        auto inside = [&]() -> Vec2 {
            const double th = rbd.uni(0, 2 * kPi), rr = 0.7 * std::sqrt(rbd.uni());
            return Vec2(std::cos(th), std::sin(th)) * rr * cr.r_bone(th);
        };
        if (rbd.chance(P.sulcal_blood_prob.value_or(P.blood_prob))) {
            cr.sah = rbd.uni(0.5, 1.0);
            cr.sah_c = inside();
            cr.sah_r = rbd.uni(0.25, 0.6) * rc;
        }
        if (rbd.chance(P.blood_film_prob.value_or(P.blood_prob))) {
            cr.film_mm = rbd.uni(0.02, 0.12);
            cr.film_c = inside();
            cr.film_r = rbd.uni(0.3, 0.7) * rc;
        }
    }
    {
        // The lamp's spot, the skin prep and the clips' irregularity: a stream of their own too.
        Rng rlp(splitmix64(P.seed * 0xD6E8FEB86659FD93ull + splitmix64(uint64_t(index) + 0x1A3Dull)));
        // Every value is drawn whatever the chances, so that one option does not move another.
        const bool spot = rlp.chance(P.lamp_spot_prob), prep = rlp.chance(P.skin_prep_prob);
        // Focused on the opening: half light at 1.5-3 times its radius (30-120 mm), nearly flat
        // over the cortex, its centre off the opening's by up to a quarter of the radius.
        const double spot_r = cr.R1 * rlp.uni(1.5, 3.0), floor = rlp.uni(0.15, 0.5);
        const Vec2 spot_c = Vec2(rlp.uni(-0.25, 0.25), rlp.uni(-0.25, 0.25)) * cr.R1;
        const double prep_k = rlp.uni(0.35, 0.85);
        if (spot) cr.spot_r_mm = spot_r, cr.spot_floor = floor, cr.spot_c = spot_c;
        if (prep) cr.prep = prep_k;
        cr.clip_seed = rlp.u32();
        cr.clip_jitter = rlp.uni(0.3, 1.0);
    }

    // ---- pose: near the outward normal, tilted, random roll
    const double tilt = P.max_tilt_deg * std::sqrt(rng.uni()) * kPi / 180, az = rng.uni(0, 2 * kPi);
    const Vec3 view_dir = (std::cos(tilt) * cr.n + std::sin(tilt) * (std::cos(az) * cr.e1 + std::sin(az) * cr.e2)).normalized();
    const double dist = rng.uni(P.distance_mm);
    const Vec3 target = cr.c + (rng.uni(-0.15, 0.15) * cr.e1 + rng.uni(-0.15, 0.15) * cr.e2) * cr.R1 - cr.n * 4.0;
    const Vec3 eye = target + view_dir * dist;
    Vec3 up = view_dir.unitOrthogonal();
    const double roll = rng.uni(0, 2 * kPi);
    up = Eigen::AngleAxisd(roll, view_dir) * up;
    const Pose T = P.fixed_T_camera_from_world ? *P.fixed_T_camera_from_world : look_at(eye, target, up);
    out.T_camera_from_world = T;

    Intrinsics K;
    K.width = W;
    K.height = H;
    const double fill = rng.uni(P.fill_fraction);
    K.fx = fill * H * dist / (2 * cr.R1);
    K.fy = K.fx * rng.uni(0.998, 1.002);
    K.cx = (W - 1) * 0.5 + rng.uni(-0.02, 0.02) * W;
    K.cy = (H - 1) * 0.5 + rng.uni(-0.02, 0.02) * H;
    const bool distorted = rng.chance(P.distortion_prob);
    if (distorted) K.distortion = random_distortion(rng);
    if (P.fixed_camera) K = *P.fixed_camera;
    out.camera = K;
    const Intrinsics Kr = K.resized(rw, rh);

    Look L = random_look(rng);
    add_finish(L, P.photo_finish, P.tissue_optics);
    // The OR's light head far overhead instead of a light near the camera: 0.8-1.2 m from the
    // opening, up to 35 deg off the camera's axis, so its rays are nearly parallel across the
    // opening. A stream of its own, every value drawn whatever the chance, so a seed's cases are
    // the same without it.
    double far_lamp_mm = 0;
    {
        Rng rfl(splitmix64(P.seed * 0xA24BAED4963EE407ull + splitmix64(uint64_t(index) + 0xFA1Aull)));
        const bool far = rfl.chance(P.far_lamp_prob);
        const double d = rfl.uni(800, 1200), th = 35 * kPi / 180 * std::sqrt(rfl.uni()), ph = rfl.uni(0, 2 * kPi);
        if (far) {
            L.light_offset_camera_mm = Vec3(0, 0, dist) + d * Vec3(std::sin(th) * std::cos(ph), std::sin(th) * std::sin(ph), -std::cos(th));
            far_lamp_mm = d;
        }
    }
    cr.clip_shaped = L.finish;
    cr.clip_tilt = L.clip_tilt_deg * kPi / 180;
    out.jpeg = dslr || !rng.chance(P.png_fraction);
    out.jpeg_quality = dslr ? rng.integer(85, 96) : L.jpeg_quality;
    const bool apply_jpeg_artefacts = out.jpeg || rng.chance(0.5);

    // ---- rasterise the brain
    const RasterBuffers rb = rasterize(S.mesh, Kr, T);

    // ---- texture over the craniotomy (sulcal depth, vessels, bumps)
    Texture tx;
    double max_r = 0;
    for (int k = 0; k < 72; ++k) max_r = std::max(max_r, cr.r_bone(2 * kPi * k / 72));
    tx.E = max_r * 1.15 + 6;
    tx.texel = std::max(0.08, 2 * tx.E / 1100);
    tx.N = int(std::ceil(2 * tx.E / tx.texel));
    {
        std::vector<Eigen::Vector3f> uvz(nv);
        const float nan = std::numeric_limits<float>::quiet_NaN();
        for (size_t i = 0; i < nv; ++i) {
            const Vec3 p = S.mesh.vertices[i].cast<double>();
            if ((p - cr.O).normalized().dot(cr.n) < 0.3) {
                uvz[i] = Eigen::Vector3f(nan, nan, nan);
                continue;
            }
            double h = 0;
            const Vec2 t = tx.to_tex(cr.ab(p, &h));
            uvz[i] = Eigen::Vector3f(float(t.x()), float(t.y()), float(1000 - h));
        }
        tx.ortho = rasterize_screen(uvz, S.mesh.triangles, tx.N, tx.N, false);
    }
    {
        // The bone's outer surface sits a little above the brain at the craniotomy rim (the
        // brain fills the opening): mean height of the outermost surface along the rim.
        double hsum = 0;
        int hn = 0;
        for (int k = 0; k < 90; ++k) {
            const double th = 2 * kPi * k / 90, r = cr.r_bone(th);
            const Vec2 t = tx.to_tex(r * Vec2(std::cos(th), std::sin(th)));
            const int x = int(std::lround(t.x())), y = int(std::lround(t.y()));
            if (x < 0 || y < 0 || x >= tx.N || y >= tx.N) continue;
            const float z = tx.ortho.depth_mm[size_t(y) * tx.N + x];
            if (std::isfinite(z)) hsum += 1000.0 - z, ++hn;
        }
        cr.h_bone = (hn > 0 ? hsum / hn : 0.0) + bone_above_rim;
        cr.h_skin = cr.h_bone + scalp_mm;
    }
    tx.sulc = cv::Mat::zeros(tx.N, tx.N, CV_32F);
    for (int y = 0; y < tx.N; ++y)
        for (int x = 0; x < tx.N; ++x)
            tx.sulc.at<float>(y, x) = interpolate_at(tx.ortho, S.mesh.triangles, S.sulcal_depth_mm, x, y, 0.f);
    cv::GaussianBlur(tx.sulc, tx.sulc_blur, cv::Size(0, 0), 1.5 / tx.texel);

    std::vector<VesselPath> vessels;
    const int n_veins = rng.integer(1, 4), n_arteries = rng.integer(1, 5), n_small = rng.integer(30, 90);
    for (int k = 0; k < n_veins; ++k) {
        const double a0 = rng.uni(0, 2 * kPi);
        const Vec2 p0 = tx.E * 0.95 * Vec2(std::cos(a0), std::sin(a0));
        const Vec2 d0 = Eigen::Rotation2Dd(rng.uni(-0.6, 0.6)) * (-p0.normalized());
        trace_vessel(tx, rng, p0, d0, rng.uni(0.7, 1.9), 0, 0, 400, vessels);
    }
    for (int k = 0; k < n_arteries; ++k) {
        const double a0 = rng.uni(0, 2 * kPi);
        const Vec2 p0 = tx.E * rng.uni(0.3, 0.95) * Vec2(std::cos(a0), std::sin(a0));
        const Vec2 d0 = Eigen::Rotation2Dd(rng.uni(-1.2, 1.2)) * (-p0.normalized());
        trace_vessel(tx, rng, p0, d0, rng.uni(0.25, 0.65), 1, 0, rng.uni(20, 120), vessels);
    }
    for (int k = 0; k < n_small; ++k) {
        const Vec2 p0(rng.uni(-tx.E, tx.E) * 0.9, rng.uni(-tx.E, tx.E) * 0.9);
        const double a0 = rng.uni(0, 2 * kPi);
        trace_vessel(tx, rng, p0, Vec2(std::cos(a0), std::sin(a0)), rng.uni(0.05, 0.16), 2, 3, rng.uni(2, 14), vessels);
    }
    draw_vessels(tx, vessels);
    {
        // Height map (mm): vessels are raised tubes, pia is finely bumpy; its gradient tilts normals.
        cv::Mat height(tx.N, tx.N, CV_32F);
        const float bs = float(L.bump_scale_mm);
        for (int y = 0; y < tx.N; ++y) {
            float* hp = height.ptr<float>(y);
            const float* vp = tx.vein.ptr<float>(y);
            const float* ap = tx.artery.ptr<float>(y);
            const float* sp = tx.small.ptr<float>(y);
            for (int x = 0; x < tx.N; ++x) {
                const float a = float(x * tx.texel), b = float(y * tx.texel);
                hp[x] = float(L.bump_mm) * fbm(a / bs, b / bs, L.nseed + 11, 3) + 0.5f * vp[x] + 0.3f * ap[x] + 0.06f * sp[x];
            }
        }
        // Veins and arteries are round: a tube's height across them (from the distance to the
        // vessel's edge and the local radius) gives the rounded shading and the bright reflex
        // along the axis that a flat raised ribbon lacks.
        auto tube = [&](const cv::Mat& alpha, cv::Mat& profile) {
            cv::Mat inside, edge_mm, radius;
            cv::compare(alpha, 0.35, inside, cv::CMP_GT);
            cv::distanceTransform(inside, edge_mm, cv::DIST_L2, 3);
            edge_mm *= tx.texel;
            const int k = std::max(1, int(std::ceil(2.2 / tx.texel)));
            cv::dilate(edge_mm, radius, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * k + 1, 2 * k + 1)));
            profile = cv::Mat::zeros(alpha.size(), CV_32F);
            for (int y = 0; y < tx.N; ++y) {
                const float* d = edge_mm.ptr<float>(y);
                const float* r = radius.ptr<float>(y);
                float* pr = profile.ptr<float>(y);
                float* hp = height.ptr<float>(y);
                for (int x = 0; x < tx.N; ++x) {
                    if (d[x] <= 0 || r[x] <= 0) continue;
                    const float q = std::min(d[x] / r[x], 1.f);  // 0 at the edge, 1 on the axis
                    pr[x] = std::sqrt(std::max(0.f, q * (2 - q)));
                    hp[x] += 0.6f * r[x] * pr[x];
                }
            }
        };
        tube(tx.vein, tx.vein_tube);
        tube(tx.artery, tx.artery_tube);
        cv::Sobel(height, tx.grad_x, CV_32F, 1, 0, 3, 1.0 / (8 * tx.texel));
        cv::Sobel(height, tx.grad_y, CV_32F, 0, 1, 3, 1.0 / (8 * tx.texel));
    }

    // ---- per-pixel layers and shading
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    const Vec3 Cw = -R.transpose() * T.topRightCorner<3, 1>();
    const Vec3 light_w = Cw + R.transpose() * L.light_offset_camera_mm;
    const std::vector<Eigen::Vector3f> rays = pixel_rays(Kr);
    const size_t npx = size_t(rw) * rh;
    std::vector<uint8_t> layer(npx, kDrape);
    std::vector<Col> img(npx, Col::Zero());
    std::vector<Vec3> pworld(npx, Vec3::Zero());
    std::vector<float> depth_cam(npx, float(dist + 60));  // camera z of what each pixel shows, mm
    // With subsurface scatter the cortex's light and colour are kept apart until the light has
    // been spread (after the loop): its diffuse light (grey; the lamp is white), its albedo, its gloss.
    const bool scatter = L.scatter_mm > 0;
    std::vector<float> ctx_light(scatter ? npx : 0, 0.f);
    std::vector<Col> ctx_albedo(scatter ? npx : 0, Col::Zero()), ctx_gloss(scatter ? npx : 0, Col::Zero());
    const Vec3 light_dir_ref = (light_w - cr.c).normalized();
    const float ref_dist2 = float((light_w - cr.c).squaredNorm());
    const uint32_t ns = L.nseed;
    const double px_per_mm = Kr.fx / dist;
    // The rim made by hand (finish): noise along the opening's circumference, sampled on a circle
    // so that it closes on itself; `scale_mm`: its features' size along the rim.
    const double rim_r = 0.5 * (cr.R1 + cr.R2);
    auto rim_noise = [&](double th, double scale_mm, uint32_t seed, int oct) {
        const float k = float(rim_r / scale_mm);
        return fbm(k * float(std::cos(th)) + 50.f, k * float(std::sin(th)) + 50.f, seed, oct);
    };
    // The dura's cut edge at angle th, mm from the centre: an even band before the finish; with
    // it, wandering in width and notched by the scissors' strokes.
    auto dura_edge = [&](double th) {
        if (L.dura_rag <= 0) return cr.r_bone(th) + cr.dura_w;
        const double wob = rim_noise(th, 5, ns + 50, 3) - 0.5, teeth = rim_noise(th, 0.8, ns + 51, 1) - 0.5;
        return cr.r_bone(th) + cr.dura_w * std::max(0.2, 1 + L.dura_rag * (2.5 * wob + 0.8 * teeth));
    };
    // Tack-up sutures, each from the dura's edge out to a hole drilled in the bone, and the
    // blood's trickles from the scalp's edge: angles and sizes from a stream of the look's own.
    std::array<double, 4> sut_th{}, sut_mm{}, tr_th{}, tr_len{}, tr_w{};
    {
        Rng rs(splitmix64(uint64_t(ns) * 0xA24BAED4963EE407ull + 0x5D7ull));
        const double base = rs.uni(0, 2 * kPi), down = rs.uni(0, 2 * kPi);
        for (size_t k = 0; k < 4; ++k) {
            sut_th[k] = base + 2 * kPi * (double(k) + rs.uni(-0.3, 0.3)) / std::max(1, L.n_sutures);
            sut_mm[k] = rs.uni(2.5, 4.5);
            tr_th[k] = down + rs.uni(-0.7, 0.7);  // blood runs down one side of the head
            tr_len[k] = rs.uni(5, 18);
            tr_w[k] = rs.uni(1.0, 2.5);
        }
    }
    const double line_half_mm = std::max(0.15, 0.6 / px_per_mm);  // a thread: at least a pixel wide
    // How much of (a, b) on the bone or dura a suture covers (0..1).
    auto suture_ink = [&](const Vec2& ab) {
        float ink = 0;
        const double th = std::atan2(ab.y(), ab.x()), rho = ab.norm();
        for (int k = 0; k < L.n_sutures; ++k) {
            const size_t kk = size_t(k);
            const double r_in = dura_edge(sut_th[kk]) - 1.2, r_out = r_in + 1.2 + sut_mm[kk];
            const double along = rho - r_in, lat = rho * std::remainder(th - sut_th[kk], 2 * kPi);
            if (along < -1 || along > r_out - r_in + 1) continue;
            const double bow = 0.4 * std::sin(kPi * std::clamp(along / (r_out - r_in), 0.0, 1.0));
            if (along >= 0 && along <= r_out - r_in)
                ink = std::max(ink, 1.f - smoothstep(float(line_half_mm * 0.5), float(line_half_mm * 1.5), float(std::abs(lat - bow))));
            // The knot at the dura, the hole in the bone.
            ink = std::max(ink, 1.f - smoothstep(0.4f, 0.7f, float(std::hypot(along, lat))));
            ink = std::max(ink, 0.85f * (1.f - smoothstep(0.45f, 0.7f, float(std::hypot(along - (r_out - r_in), lat)))));
        }
        return ink;
    };
    // The drapes' soft folds: a ripple across fold_psi whose phase wanders and whose height comes
    // and goes (cloth lies flat in places), in render px. Lit by the lamp, each fold shows a lit
    // and a shaded flank; a brightness pattern alone reads as print on the cloth, not as cloth.
    // A second family, longer and across the first, breaks the ripple's regularity.
    auto fold_family = [&](float x, float y, float lam, float psi, uint32_t seed, float* crest) {
        const float cs = std::cos(psi), sn = std::sin(psi);
        const float a = (cs * x + sn * y) / lam, b = (-sn * x + cs * y) / lam;
        const float warp = 1.5f * fbm(a * 0.5f, b * 0.25f, seed, 2);
        const float gate = smoothstep(0.2f, 0.55f, fbm(a * 0.25f, b * 0.25f, seed + 1, 2));
        // Rounded crests, creased troughs: 1 - 2|sin| over half the wavelength.
        const float fs = 1.f - 2.f * std::abs(std::sin(float(kPi) * (a + warp)));
        if (crest) *crest = gate * fs;  // -1 in a full fold's trough, +1 on its crest
        return float(L.fold_slope) * gate * lam / (2 * float(kPi)) * fs;
    };
    const float fold_lam = float(L.fold_mm * px_per_mm), fold_psi = float(L.fold_psi);
    auto fold_height_px = [&](float x, float y, float* crest) {
        float c1 = 0, c2 = 0;
        const float h = fold_family(x, y, fold_lam, fold_psi, ns + 40, crest ? &c1 : nullptr) +
                        fold_family(x, y, 1.7f * fold_lam, fold_psi + 1.2f, ns + 45, crest ? &c2 : nullptr);
        if (crest) *crest = std::clamp(c1 + c2, -1.f, 1.f);
        return h;
    };

    tbb::parallel_for(0, rh, [&](int v) {
        for (int u = 0; u < rw; ++u) {
            const size_t i = size_t(v) * rw + u;
            const Vec3 d = (R.transpose() * rays[i].cast<double>()).normalized();
            auto shade = [&](const Col& albedo, const Vec3& nrm, const Vec3& p, double spec_k, double shin) -> Col {
                const Vec3 l = (light_w - p).normalized();
                const Vec3 vdir = (Cw - p).normalized();
                const double ndl = std::max(0.0, nrm.dot(l));
                const Vec3 h = (l + vdir).normalized();
                const double sp = spec_k * std::pow(std::max(0.0, nrm.dot(h)), shin);
                const float fall = std::clamp(ref_dist2 / float((light_w - p).squaredNorm()), 0.6f, 1.5f);
                return (albedo * float(L.ambient + L.diffuse * ndl) + L.light * float(sp)) * fall;
            };
            Vec3 qs, qb;
            uint8_t lay = kDrape;
            Vec2 ab_s(0, 0), ab_b(0, 0);
            const bool hs = cr.hit_sphere(Cw, d, cr.h_skin, qs);
            if (hs) ab_s = cr.ab(qs);
            const double th_s = std::atan2(ab_s.y(), ab_s.x()), rho_s = ab_s.norm();
            if (!hs || rho_s > cr.r_drape(th_s)) {
                lay = kDrape;
            } else if (rho_s > cr.r_skin(th_s)) {
                lay = rho_s < cr.r_skin(th_s) + 1.5 ? kSkinCut : kSkin;
                if (cr.clip_at(ab_s, nullptr)) lay = kClip;
            } else {
                const bool hb = cr.hit_sphere(Cw, d, cr.h_bone, qb);
                if (hb) ab_b = cr.ab(qb);
                const double th_b = std::atan2(ab_b.y(), ab_b.x()), rho_b = ab_b.norm();
                if (!hb || rho_b > cr.r_skin(th_b)) {
                    lay = cr.clip_at(ab_s, nullptr) ? kClip : kSkinCut;  // the cut scalp wall
                } else if (rho_b > cr.r_bone(th_b)) {
                    lay = cr.flap_at(ab_b, nullptr) ? kDuraFlap
                          : cr.burr_edge(ab_b) < 0  ? kBurr
                          : rho_b < dura_edge(th_b)             ? kDura
                                                                : kBone;
                } else if (rb.triangle[i] >= 0) {
                    const Vec3 p = interpolate_at(rb, S.mesh.triangles, S.mesh.vertices, u, v, Eigen::Vector3f(0, 0, 0)).cast<double>();
                    const Vec2 abc = cr.ab(p);
                    lay = abc.norm() <= cr.r_bone(std::atan2(abc.y(), abc.x())) + 0.5 ? kCortex : kBoneWall;
                    pworld[i] = p;
                } else {
                    lay = kDark;
                }
            }
            layer[i] = lay;
            {
                // What the pixel shows, for the depth of field: the brain, the bone sphere or the
                // skin sphere (the drapes lie a little beyond the skin they cover).
                const bool on_brain = lay == kCortex || lay == kBoneWall;
                const bool on_bone = lay == kBone || lay == kDura || lay == kBurr || lay == kDuraFlap;
                if (on_brain || on_bone || hs) {
                    const Vec3& q = on_brain ? pworld[i] : on_bone ? qb : qs;
                    depth_cam[i] = float((R * q + T.topRightCorner<3, 1>()).z()) + (lay == kDrape ? 15.f : 0.f);
                }
            }
            Col c;
            switch (lay) {
                case kCortex: {
                    const Vec3& p = pworld[i];
                    Vec3 nrm = interpolate_at(rb, S.mesh.triangles, S.normals, u, v, Eigen::Vector3f(0, 0, 1)).cast<double>().normalized();
                    const float sd = interpolate_at(rb, S.mesh.triangles, S.sulcal_depth_mm, u, v, 0.f);
                    const Vec2 ab = cr.ab(p);
                    const float va = tx.sample(tx.vein, ab), aa = tx.sample(tx.artery, ab), sa = tx.sample(tx.small, ab);
                    const float mot = fbm(float(ab.x() / 4), float(ab.y() / 4), ns + 3, 3);
                    Col alb = L.cortex * float(1 + L.mottle * (2 * mot - 1));
                    // The pia's capillary bed: a fine, reddish speckle at a fraction of a millimetre.
                    const float cap = fbm(float(ab.x() / 0.45), float(ab.y() / 0.45), ns + 13, 2);
                    alb = mix(alb, L.small_vessel, float(L.mottle) * 0.9f * smoothstep(0.45f, 0.8f, cap));
                    // Sulci: darker, redder (pia, CSF and small vessels in the groove).
                    alb = mix(alb, L.sulcus, 0.85f * smoothstep(0.6f, 3.5f, sd));
                    // The arachnoid spans the sulci: a pale, bluish veil that hazes them over.
                    if (cr.veil > 0) {
                        const float haze = float(cr.veil) * (0.6f + 0.4f * fbm(float(ab.x() / 3), float(ab.y() / 3), ns + 20, 2));
                        alb = mix(alb, mix(L.cortex, Col(0.85f, 0.86f, 0.92f), 0.5f), haze * smoothstep(0.4f, 2.5f, sd));
                    }
                    alb = mix(alb, L.small_vessel, 0.55f * sa);
                    // Blood is deepest on a vessel's axis: darker there, translucent at the edges.
                    const float vt = tx.sample(tx.vein_tube, ab), at = tx.sample(tx.artery_tube, ab);
                    alb = mix(alb, L.artery * (1.15f - 0.3f * at), (0.7f + 0.2f * at) * aa);
                    alb = mix(alb, L.vein * (1.2f - 0.35f * vt), (0.72f + 0.23f * vt) * va);
                    // Subarachnoid blood: it pools in the sulci (up to ~1 mm deep there) and
                    // stains the crowns only thinly; a patch with a ragged edge.
                    if (cr.sah > 0) {
                        const double q = (ab - cr.sah_c).norm() / cr.sah_r +
                                         0.6 * (fbm(float(ab.x() / 6), float(ab.y() / 6), ns + 30, 3) - 0.5);
                        const float w = float(cr.sah) * (1 - smoothstep(0.6f, 1.0f, float(q)));
                        if (w > 0) alb = through_blood(alb, L.blood, w * (0.04 + 1.0 * smoothstep(0.5f, 3.f, sd)));
                    }
                    // A film of blood and irrigation: the tissue shows through, tinted, and the
                    // film's surface is smooth and wet.
                    double film_h = 0;
                    if (cr.film_mm > 0) {
                        const double q = (ab - cr.film_c).norm() / cr.film_r +
                                         0.8 * (fbm(float(ab.x() / 8), float(ab.y() / 8), ns + 31, 3) - 0.5);
                        film_h = cr.film_mm * (1 - smoothstep(0.5f, 1.0f, float(q))) *
                                 (0.5 + fbm(float(ab.x() / 3), float(ab.y() / 3), ns + 32, 2));
                        if (film_h > 0) alb = through_blood(alb, L.blood, film_h);
                    }
                    const double film_smooth = std::clamp(film_h / 0.15, 0.0, 1.0);
                    // Bump: tilt the normal by the texture height gradient (a film fills it in).
                    const float gx = tx.sample(tx.grad_x, ab), gy = tx.sample(tx.grad_y, ab);
                    Vec3 t1 = cr.e1 - nrm * nrm.dot(cr.e1), t2 = cr.e2 - nrm * nrm.dot(cr.e2);
                    nrm = (nrm - (1 - 0.7 * film_smooth) * (double(gx) * t1 + double(gy) * t2)).normalized();
                    const double wet = L.spec * (1 - 0.5 * smoothstep(1.f, 4.f, sd)) * (1 + 0.5 * film_smooth);
                    // Deep sulci get little light.
                    const float deep = float(1 - 0.45 * smoothstep(2.f, 8.f, sd));
                    if (scatter) {
                        ctx_light[i] = shade(Col::Ones(), nrm, p, 0, L.shininess)[0] * deep;
                        ctx_gloss[i] = shade(Col::Zero(), nrm, p, wet, L.shininess) * deep;
                        ctx_albedo[i] = alb;
                        c = alb * ctx_light[i] + ctx_gloss[i];
                        break;
                    }
                    c = shade(alb, nrm, p, wet, L.shininess);
                    c *= deep;
                    break;
                }
                case kBone:
                case kDura: {
                    Vec3 nrm = (qb - cr.O).normalized();
                    const float t = fbm(float(ab_b.x() / 2), float(ab_b.y() / 2), ns + 5, 4);
                    Col alb = lay == kBone ? L.bone * (0.8f + 0.35f * t) : L.dura * (0.85f + 0.25f * t);
                    // The outer table's vascular pits, each a dark red point.
                    if (lay == kBone && L.finish)
                        alb = mix(alb, L.blood * 1.4f, 0.5f * smoothstep(0.82f, 0.95f, vnoise(float(ab_b.x() / 0.5), float(ab_b.y() / 0.5), ns + 44)));
                    // Blood stains on bone near the edge.
                    const float st = fbm(float(ab_b.x() / 5), float(ab_b.y() / 5), ns + 6, 3);
                    alb = mix(alb, L.blood * 1.6f, 0.8f * smoothstep(0.55f, 0.75f, st));
                    double spec_k = lay == kDura ? L.spec * 0.7 : 0.25, shin = lay == kDura ? 50 : 12;
                    if (lay == kDura && L.finish) {
                        // A membrane held open: folds running out towards the tack-ups and the
                        // bone (long radially, short around), greyer and bluer where it is thin,
                        // meningeal arteries in pairs of branching lines, and at its cut edge
                        // (towards the opening) thickened, curled in and stained with blood.
                        const double th = std::atan2(ab_b.y(), ab_b.x()), rho = ab_b.norm();
                        const Vec2 rad(std::cos(th), std::sin(th)), tan2(-rad.y(), rad.x());
                        const Vec3 rad3 = rad.x() * cr.e1 + rad.y() * cr.e2, tan3 = tan2.x() * cr.e1 + tan2.y() * cr.e2;
                        const float fold = fbm(float(rho / 4), float(th * rim_r / 1.2), ns + 61, 3) - 0.5f;
                        const double in_mm = rho - cr.r_bone(th);  // from the cut edge
                        const double curl = 1 - smoothstep(0.f, 1.f, float(in_mm));
                        nrm = (nrm + 0.7 * double(fold) * tan3 - 0.6 * curl * rad3).normalized();
                        // Its hue, not its lightness: the membrane is no darker for being thin.
                        const Col grey_blue = Col(0.55f, 0.58f, 0.66f) * (alb.sum() / 1.79f);
                        alb = mix(alb, grey_blue, float(L.dura_grey) * fbm(float(ab_b.x() / 7), float(ab_b.y() / 7), ns + 62, 2));
                        const float mv = 1.f - std::abs(2.f * fbm(float(ab_b.x() / 9), float(ab_b.y() / 9), ns + 63, 3) - 1.f);
                        const float mv2 = 1.f - std::abs(2.f * fbm(float(ab_b.x() / 4), float(ab_b.y() / 4), ns + 64, 2) - 1.f);
                        const float vessel = std::max(smoothstep(0.93f, 0.975f, mv), 0.7f * smoothstep(0.955f, 0.985f, mv2));
                        alb = mix(alb, L.artery * 0.6f, float(L.dura_vessels) * vessel);
                        alb *= 0.85f + 0.3f * (fold + 0.5f);  // the folds' flanks and troughs
                        const float stain = float(curl) * smoothstep(0.35f, 0.6f, fbm(float(ab_b.x() / 1.5), float(ab_b.y() / 1.5), ns + 65, 2));
                        alb = mix(alb * float(0.75 + 0.25 * (1 - curl)), L.blood * 1.3f, 0.7f * stain);
                    }
                    if (lay == kBone && L.finish) {
                        // Soft tissue left on the bone's outer part, as wide as the scraping left
                        // it: pericranium and muscle, wet, fibres running out from the opening;
                        // and char where the cautery stopped the bleeding at the scalp's edge.
                        const double th = std::atan2(ab_b.y(), ab_b.x()), rho = ab_b.norm();
                        const double in_mm = cr.r_skin(th) - rho;  // from the bone's outer edge
                        const double tw = cr.bone_w * L.tissue_frac * std::max(0.0, 1 + 3.0 * (rim_noise(th, 6, ns + 52, 3) - 0.5));
                        const float ragged = 0.8f * (fbm(float(ab_b.x() / 1.2), float(ab_b.y() / 1.2), ns + 53, 2) - 0.5f);
                        const float m = 1.f - smoothstep(float(tw) - 0.5f, float(tw) + 0.5f, float(in_mm) + ragged);
                        const float fibre = vnoise(float(rho / 2.5), float(th * rim_r / 0.3), ns + 54);
                        const Col tissue = mix(L.skin_cut * 1.5f, rgb(200, 128, 116), 0.35f + 0.4f * fibre);
                        alb = mix(alb, tissue, m);
                        const float ch = float(L.char_k) * smoothstep(0.55f, 0.8f, fbm(float(ab_b.x() / 1.5), float(ab_b.y() / 1.5), ns + 55, 3)) *
                                         (1.f - smoothstep(0.f, 3.f, float(in_mm)));
                        alb = mix(alb, rgb(48, 30, 22), ch);
                        spec_k = 0.25 + m * (L.spec * 0.6 - 0.25) * (1 - ch), shin = 12 + m * 28;
                    }
                    c = shade(alb, nrm, qb, spec_k, shin);
                    if (L.n_sutures > 0) {
                        const float ink = suture_ink(ab_b);
                        if (ink > 0) c = mix(c, shade(L.suture, nrm, qb, 0.6, 40), ink);
                    }
                    break;
                }
                case kBurr: {
                    // A perforator's hole through the bone: a bevelled wall, then the dura at the
                    // bottom, in the hole's shadow.
                    double rad = 5;
                    const double e = cr.burr_edge(ab_b, &rad);
                    const float q = std::clamp(float(-e / rad), 0.f, 1.f);  // 0 at the rim, 1 at the centre
                    const Vec3 sph = (qb - cr.O).normalized();
                    const float t = fbm(float(ab_b.x() / 1.5), float(ab_b.y() / 1.5), ns + 15, 3);
                    if (q < 0.3f) {
                        Vec2 to_c(0, 0);
                        for (int k = 0; k < cr.n_burr; ++k) {
                            const Vec2 cc = cr.burr_rho[size_t(k)] * Vec2(std::cos(cr.burr_th[size_t(k)]), std::sin(cr.burr_th[size_t(k)]));
                            if ((ab_b - cc).norm() <= cr.burr_r[size_t(k)]) to_c = (cc - ab_b).normalized();
                        }
                        const Vec3 nrm = (0.5 * sph + to_c.x() * cr.e1 + to_c.y() * cr.e2).normalized();
                        c = shade(L.bone_wall * (0.75f + 0.35f * t), nrm, qb, 0.2, 15) * (0.35f + 1.5f * q);
                    } else {
                        const Col floor = mix(L.dura, L.blood, 0.25f + 0.3f * t);
                        c = shade(floor, sph, qb, L.spec * 0.3, 40) * (0.12f + 0.25f * smoothstep(0.3f, 1.f, q));
                    }
                    break;
                }
                case kDuraFlap: {
                    // The opened dura folded back over the bone: a wrinkled, glossy sheet with
                    // meningeal vessels, its cut edge a darker line.
                    double edge = 5;
                    cr.flap_at(ab_b, &edge);
                    const Vec3 sph = (qb - cr.O).normalized();
                    const float w1 = fbm(float(ab_b.x() / 2.5), float(ab_b.y() / 2.5), ns + 16, 3);
                    const float w2 = fbm(float(ab_b.x() / 2.5) + 7.f, float(ab_b.y() / 2.5) - 3.f, ns + 16, 3);
                    const Vec3 nrm = (sph + 0.5 * double(w1 - 0.5f) * cr.e1 + 0.5 * double(w2 - 0.5f) * cr.e2).normalized();
                    // Reflected dura is greyer and bluer than the bone beside it.
                    const Col grey_blue(0.55f, 0.58f, 0.66f);
                    Col alb = mix(L.dura, grey_blue, 0.35f) * (0.75f + 0.3f * fbm(float(ab_b.x() / 6), float(ab_b.y() / 6), ns + 17, 3));
                    const float mv = 1.f - std::abs(2.f * fbm(float(ab_b.x() / 14), float(ab_b.y() / 14), ns + 18, 2) - 1.f);
                    alb = mix(alb, L.artery * 0.75f, 0.6f * smoothstep(0.965f, 0.99f, mv));
                    alb *= float(0.55 + 0.45 * smoothstep(0.f, 1.5f, float(edge)));
                    c = shade(alb, nrm, qb, L.spec * 0.8, 60);
                    break;
                }
                case kClip: {
                    // A plastic scalp clip: rounded across its width, glossy.
                    double acr = 0;
                    const Vec3 sph = (qs - cr.O).normalized();
                    if (cr.clip_shaped) {
                        // A Raney clip seen from above: its upper jaw domed across, the ends
                        // bevelled, a groove along the middle and grip ribs at the spring's end.
                        double al = 0, axis = 0;
                        const double sd = cr.clip_sdf(ab_s, &al, &acr, &axis);
                        const Vec2 dir(std::cos(axis), std::sin(axis));
                        const Vec3 along3 = dir.x() * cr.e1 + dir.y() * cr.e2, side = -dir.y() * cr.e1 + dir.x() * cr.e2;
                        const double bevel = 1 - smoothstep(0.f, 0.8f, float(-sd));  // 1 at the outline
                        const double end = al < 0.5 ? -1.0 : 1.0;
                        const float groove = (al > 0.08 && al < 0.92) ? 1.f - smoothstep(0.07f, 0.14f, float(std::abs(acr))) : 0.f;
                        const float rib = al > 0.68 && al < 0.94 ? smoothstep(0.6f, 0.9f, float(std::sin(al * cr.clip_len / 0.7 * 2 * kPi))) : 0.f;
                        const Vec3 nrm = (sph + 0.8 * acr * side + 0.9 * bevel * end * std::abs(2 * al - 1) * along3 -
                                          0.6 * groove * (acr < 0 ? -1.0 : 1.0) * side)
                                             .normalized();
                        c = shade(cr.clip_col * (1.f - 0.5f * groove) * (1.f - 0.3f * rib), nrm, qs, 0.9, 90) *
                            float(0.78 + 0.22 * (1 - acr * acr)) * float(1 - 0.35 * bevel);
                        break;
                    }
                    cr.clip_at(ab_s, &acr);
                    const Vec2 dir = ab_s.normalized();
                    const Vec3 side = -dir.y() * cr.e1 + dir.x() * cr.e2;
                    const Vec3 nrm = (sph + 0.9 * acr * side).normalized();
                    c = shade(cr.clip_col, nrm, qs, 0.9, 90) * float(0.75 + 0.25 * (1 - acr * acr));
                    break;
                }
                case kBoneWall: {
                    const Vec3 radial = (pworld[i] - cr.c);
                    const Vec3 nrm = (-(radial - cr.n * radial.dot(cr.n)).normalized() + 0.3 * cr.n).normalized();
                    const float t = fbm(float(u * 0.08), float(v * 0.08), ns + 7, 3);
                    c = shade(L.bone_wall * (0.7f + 0.4f * t), nrm, pworld[i], 0.3, 20) * 0.75f;
                    break;
                }
                case kSkin:
                case kSkinCut: {
                    const Vec3 nrm = (qs - cr.O).normalized();
                    const float t = fbm(float(ab_s.x() / 3), float(ab_s.y() / 3), ns + 8, 4);
                    const double edge = hs ? rho_s - cr.r_skin(th_s) : 0;
                    Col alb = L.skin * (0.85f + 0.3f * t);
                    // Pores, and on a shaved scalp the stubble's dark points (about 1 mm apart).
                    if (L.finish) alb *= 1.f - 0.12f * smoothstep(0.7f, 0.9f, vnoise(float(ab_s.x() / 0.3), float(ab_s.y() / 0.3), ns + 42));
                    if (L.stubble) alb *= 1.f - 0.3f * smoothstep(0.86f, 0.96f, vnoise(float(ab_s.x() / 0.45), float(ab_s.y() / 0.45), ns + 43));
                    if (cr.prep > 0) {
                        // Iodine prep dries unevenly: blotches, streaks along the sponge's strokes.
                        const float blot = fbm(float(ab_s.x() / 14), float(ab_s.y() / 14), ns + 31, 3);
                        const float streak = fbm(float(ab_s.x() / 40), float(ab_s.y() / 6), ns + 32, 2);
                        const float m = float(cr.prep) * smoothstep(0.3f, 0.65f, 0.7f * blot + 0.3f * streak);
                        alb = mix(alb, L.iodine * (0.7f + 0.6f * t), m);
                    }
                    // The cut edge's redness reaches into the skin: 5 mm before the finish; with
                    // it as far as the bleeding and the cautery went, 1.5 to 8 mm along the rim.
                    const float edge_w = L.finish ? float(5 * std::max(0.3, 1 + 3.0 * (rim_noise(th_s, 7, ns + 56, 3) - 0.5))) : 5.f;
                    alb = mix(alb, L.skin_cut, float(1 - smoothstep(0.f, edge_w, float(edge))));
                    const double spec_k = L.spec * 0.4;
                    if (L.n_trickles > 0 && (lay == kSkin || (L.finish && edge > 0))) {
                        // Blood run from the edge over the skin: narrowing as it goes, a bead at its end.
                        for (int k = 0; k < L.n_trickles; ++k) {
                            const size_t kk = size_t(k);
                            const double along = rho_s - cr.r_skin(tr_th[kk]);  // from the cut edge
                            if (along > tr_len[kk] + 2) continue;
                            const double wig = 1.2 * (fbm(float(along / 5), float(k) * 7.f, ns + 57, 2) - 0.5) * along / 6;
                            const double lat = rho_s * std::remainder(th_s - tr_th[kk], 2 * kPi) - wig;
                            const double f = std::clamp(along / tr_len[kk], 0.0, 1.0);
                            const double hw = tr_w[kk] * (1 - 0.5 * f) + 0.1 * tr_w[kk] * (1 - smoothstep(0.f, 1.5f, float(std::abs(along - tr_len[kk]))));
                            // A rounded end: past its length, the distance from the end's centre.
                            const double off = along > tr_len[kk] ? std::hypot(along - tr_len[kk], lat) : std::abs(lat);
                            const float m = 1.f - smoothstep(float(hw) - 0.3f, float(hw) + 0.3f, float(off));
                            if (m > 0) {
                                // Thin, so the skin shows through; thickest at the edge and in the bead.
                                // Drying, it is no glossier than the skin.
                                const double h = 0.1 + 0.35 * (1 - f) * (1 - std::abs(lat) / std::max(hw, 0.1)) + 0.2 * (1 - smoothstep(0.f, 1.5f, float(std::abs(along - tr_len[kk]))));
                                alb = mix(alb, through_blood(alb, L.blood, h), m);
                            }
                        }
                    }
                    // With the finish the cut edge's dark margin on the skin is ragged, 0.6 to 2.4 mm.
                    const bool margin = !(L.finish && edge > 1.5 * std::max(0.4, 1 + 2.4 * (rim_noise(th_s, 2.5, ns + 60, 2) - 0.5)));
                    if (lay == kSkinCut && margin) {
                        const float t2 = fbm(float(u * 0.15), float(v * 0.15), ns + 12, 3);
                        alb = L.skin_cut * (0.35f + 0.5f * t2);
                        if (L.finish && hs) {
                            // The scalp's cut wall in layers where it is not covered in blood: the
                            // skin, the pale dermis, the yellow fat with its vessels, the white galea.
                            // Depth into the wall from where the ray crosses the cut, between its
                            // hits on the skin's sphere and the bone's.
                            Vec3 qw;
                            double depth_mm = 0.5 * (cr.h_skin - cr.h_bone);
                            if (cr.hit_sphere(Cw, d, cr.h_bone, qw)) {
                                const double rho_w = cr.ab(qw).norm(), rs = rho_s;
                                const double f = std::clamp((cr.r_skin(th_s) - rs) / std::max(rho_w - rs, 1e-6), 0.0, 1.0);
                                depth_mm = f * (cr.h_skin - cr.h_bone);
                            }
                            const float dz = float(depth_mm);
                            const Col dermis = rgb(226, 186, 170), fat = rgb(222, 186, 110), galea = rgb(230, 226, 214);
                            Col wall = dz < 0.3f ? L.skin * 0.8f : dz < 1.4f ? dermis : fat * (0.8f + 0.4f * t2);
                            wall = mix(wall, galea, smoothstep(0.6f, 0.15f, float(cr.h_skin - cr.h_bone) - dz));
                            const float wiped = smoothstep(0.52f, 0.72f, rim_noise(th_s, 4, ns + 59, 3));
                            alb = mix(alb, through_blood(wall, L.blood, 0.04 + 0.12 * (1 - t2)), wiped);
                            // Clots, and char from the cautery.
                            const float clot = smoothstep(0.6f, 0.8f, fbm(float(ab_s.x() / 1.2), float(ab_s.y() / 1.2), ns + 58, 3));
                            alb = mix(alb, L.blood * 0.5f, clot);
                            alb = mix(alb, rgb(48, 30, 22), float(L.char_k) * 0.6f * smoothstep(0.6f, 0.85f, fbm(float(ab_s.x() / 2), float(ab_s.y() / 2), ns + 55, 3)));
                        }
                    }
                    c = shade(alb, nrm, hs ? qs : cr.c, spec_k, 30);
                    // The clips' contact shadow on the scalp.
                    if (cr.clip_shaped && hs && lay == kSkin && cr.n_clips > 0) c *= float(0.5 + 0.5 * smoothstep(0.f, 1.5f, float(cr.clip_sdf(ab_s))));
                    // The towels' edge lies on the skin: a contact shadow along it.
                    if (hs && cr.n_towels > 0) c *= float(0.55 + 0.45 * smoothstep(0.f, 2.5f, float(cr.r_drape(th_s) - rho_s)));
                    break;
                }
                case kDark: {
                    // Where the brain has fallen away from the bone: the dura lining the skull, deep
                    // and in shadow, with some blood; mottled, not a flat black.
                    const float su = float(u / render_scale), sv = float(v / render_scale);
                    const float t = fbm(su / 45.f, sv / 45.f, ns + 19, 2);
                    c = mix(L.dura * 0.06f, L.blood * 0.25f, 0.8f * smoothstep(0.4f, 0.75f, t)) * (0.7f + 0.6f * t);
                    break;
                }
                default: {  // drapes: towels with hems, cloth weave, folds and creases, in image space
                    float su = float(u / render_scale), sv = float(v / render_scale);
                    const float fold = fbm(su / 180.f, sv / 180.f, ns + 9, 3);
                    // Which towel is on top here, found on the skin sphere (or, off it, on the
                    // tangent plane at the field's height).
                    Vec2 ab_d = ab_s;
                    if (!hs) {
                        const Vec3 p0 = cr.O + cr.n * (cr.Rc + cr.h_skin);
                        const double den = d.dot(cr.n);
                        if (std::abs(den) > 1e-6) {
                            const Vec3 q = Cw + d * ((p0 - Cw).dot(cr.n) / den);
                            ab_d = Vec2((q - p0).dot(cr.e1), (q - p0).dot(cr.e2));
                        }
                    }
                    double inside = 99;
                    const int tk = cr.towel_at(ab_d, &inside);
                    float tone = 1, shadow = 1, hem = 1, crease = 0;
                    if (tk >= 0) {
                        const size_t kk = size_t(tk);
                        tone = float(cr.towel_tone[kk]);
                        const float ca = float(std::cos(cr.towel_weave_rad[kk])), sa = float(std::sin(cr.towel_weave_rad[kk]));
                        const float ru = ca * su - sa * sv, rv = sa * su + ca * sv;
                        su = ru, sv = rv;
                        // The hem: a doubled band along the edge, a dark line where it folds under.
                        const float in = float(inside), hm = float(cr.hem_mm);
                        hem = 1.f + 0.07f * (1.f - smoothstep(hm - 0.5f, hm + 0.5f, in)) -
                              0.3f * (1.f - smoothstep(0.f, 0.6f, std::abs(in - hm))) - 0.35f * (1.f - smoothstep(0.f, 0.8f, in));
                        // The creases of the towel's pack: straight lines along and across the hem.
                        const double fm = cr.towel_fold_mm[kk];
                        const double along = -ab_d.x() * std::sin(cr.towel_psi[kk]) + ab_d.y() * std::cos(cr.towel_psi[kk]);
                        const double fs = inside / fm + 0.37, ft = (along + cr.towel_fold_off[kk]) / fm;
                        const double to_fold_mm = fm * std::min(std::abs(fs - std::round(fs)), std::abs(ft - std::round(ft)));
                        crease = 1.f - smoothstep(0.f, 0.9f, float(to_fold_mm));
                        // A towel lying on this one shades it along its edge.
                        for (int j = tk + 1; j < cr.n_towels; ++j) {
                            const size_t jj = size_t(j);
                            const double sj = ab_d.x() * std::cos(cr.towel_psi[jj]) + ab_d.y() * std::sin(cr.towel_psi[jj]) - cr.towel_d[jj];
                            if (sj > -3 && sj <= 0) shadow = std::min(shadow, float(0.6 + 0.4 * smoothstep(0.f, 3.f, float(-sj))));
                        }
                    }
                    const float weave = 0.5f + 0.5f * std::sin(su * 2 * float(kPi) / float(L.drape_weave_px)) *
                                                    std::sin(sv * 2 * float(kPi) / float(L.drape_weave_px));
                    const float fine = vnoise(su * 0.7f, sv * 0.7f, ns + 10);
                    if (!L.finish) {
                        c = L.drape * (0.45f + 0.9f * fold) * (0.88f + 0.12f * weave) * (0.94f + 0.12f * fine) * float(L.exposure) *
                            (tone * hem * shadow * (1.f - 0.25f * crease));
                        break;
                    }
                    // The folds' relief, lit: Lambert against the lamp, relative to the cloth
                    // lying flat, and the troughs a little occluded.
                    float crest = 0;
                    const float fu = float(u), fv = float(v);
                    fold_height_px(fu, fv, &crest);
                    const float hx = 0.5f * (fold_height_px(fu + 1, fv, nullptr) - fold_height_px(fu - 1, fv, nullptr));
                    const float hy = 0.5f * (fold_height_px(fu, fv + 1, nullptr) - fold_height_px(fu, fv - 1, nullptr));
                    const Eigen::Vector3f nrm_c = Eigen::Vector3f(-hx, -hy, -1.f).normalized();  // camera frame, towards the camera
                    const Eigen::Vector3f p_cam = rays[i] * depth_cam[i];
                    const Eigen::Vector3f l_cam = (L.light_offset_camera_mm.cast<float>() - p_cam).normalized();
                    const float flat = std::max(0.2f, -l_cam.z());
                    const float relief = (0.3f + 0.7f * std::max(0.f, nrm_c.dot(l_cam)) / flat) * (1.f - 0.2f * (1.f - crest));
                    c = L.drape * (0.65f + 0.5f * fold) * relief * (0.88f + 0.12f * weave) * (0.94f + 0.12f * fine) *
                        float(L.exposure) * (tone * hem * shadow * (1.f - 0.25f * crease));
                    break;
                }
            }
            img[i] = c;
        }
    });
    (void)light_dir_ref;

    // ---- light scattered under the cortex's surface
    // Screen-space, as film and games render skin: each channel's diffuse light is spread by a
    // near and a wide lobe (a Gaussian of the channel's width in mm at the cortex), over cortex
    // pixels only (a normalised convolution, so the bone's light does not leak in), then the
    // albedo and the gloss (which is reflected at the surface, so not spread) are put back on.
    if (scatter) {
        cv::Mat light(rh, rw, CV_32F), mask(rh, rw, CV_32F);
        for (size_t i = 0; i < npx; ++i) {
            const bool on = layer[i] == kCortex;
            mask.ptr<float>()[i] = on ? 1.f : 0.f;
            light.ptr<float>()[i] = on ? ctx_light[i] : 0.f;
        }
        // Red spreads furthest; blood absorbs green and blue within a fraction of it.
        const double width[3] = {1.0, 0.45, 0.3};
        cv::Mat spread[3];
        for (int ch = 0; ch < 3; ++ch) {
            const double sigma_px = std::max(0.3, L.scatter_mm * width[ch] * px_per_mm);
            cv::Mat num, den;
            cv::GaussianBlur(light, num, cv::Size(0, 0), sigma_px, sigma_px, cv::BORDER_REPLICATE);
            cv::GaussianBlur(mask, den, cv::Size(0, 0), sigma_px, sigma_px, cv::BORDER_REPLICATE);
            spread[ch] = num / cv::max(den, 1e-3f);
        }
        const float share[3] = {float(L.scatter_share), float(L.scatter_share * 0.8), float(L.scatter_share * 0.7)};
        tbb::parallel_for(size_t(0), npx, [&](size_t i) {
            if (layer[i] != kCortex) return;
            Col lit;
            for (int ch = 0; ch < 3; ++ch)
                lit[ch] = (1 - share[ch]) * ctx_light[i] + share[ch] * spread[ch].ptr<float>()[i];
            img[i] = ctx_albedo[i] * lit + ctx_gloss[i];
        });
    }

    // ---- visible cortex mask (render size)
    cv::Mat cortex(rh, rw, CV_8U, cv::Scalar(0));
    for (size_t i = 0; i < npx; ++i)
        if (layer[i] == kCortex) cortex.data[i] = 255;
    {
        // Keep the largest connected region only.
        cv::Mat lab, stats, cents;
        const int nl = cv::connectedComponentsWithStats(cortex, lab, stats, cents, 8, CV_32S);
        int best = -1, best_area = 0;
        for (int l = 1; l < nl; ++l)
            if (stats.at<int>(l, cv::CC_STAT_AREA) > best_area) best_area = stats.at<int>(l, cv::CC_STAT_AREA), best = l;
        if (best < 0 || best_area < int(npx / 200))
            throw InputError("phantom case " + std::to_string(index), "too little cortex visible (internal: bad pose)");
        cv::compare(lab, best, cortex, cv::CMP_EQ);
    }

    // ---- gauze (cottonoid patties) and blood over part of the cortex
    cv::Mat occl(rh, rw, CV_8U, cv::Scalar(0));
    std::vector<cv::Point> cortex_contour;
    {
        std::vector<std::vector<cv::Point>> cs;
        cv::findContours(cortex.clone(), cs, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
        for (auto& c : cs)
            if (c.size() > cortex_contour.size()) cortex_contour = c;
    }
    cv::Moments mo = cv::moments(cortex, true);
    const Vec2 cortex_c(mo.m10 / mo.m00, mo.m01 / mo.m00);
    const bool has_gauze = rng.chance(P.gauze_prob), has_blood = rng.chance(P.blood_prob);
    int n_gauze = 0, n_blood = 0;
    if (has_gauze && !cortex_contour.empty()) {
        n_gauze = rng.integer(1, 2);
        for (int g = 0; g < n_gauze; ++g) {
            const cv::Point e = cortex_contour[size_t(rng.integer(0, int(cortex_contour.size()) - 1))];
            const Vec2 edge(e.x, e.y), inward = (cortex_c - edge).normalized();
            const double wmm = rng.uni(10, 15), lmm = rng.uni(18, 38);
            const double wpx = wmm * px_per_mm, lpx = lmm * px_per_mm;
            const Vec2 gc = edge + inward * wpx * rng.uni(0.1, 0.6);
            const double ang = std::atan2(inward.y(), inward.x()) + kPi / 2 + rng.uni(-0.5, 0.5);
            const Vec2 ax(std::cos(ang), std::sin(ang)), ay(-std::sin(ang), std::cos(ang));
            const float soak = float(rng.uni(0, 0.8));
            const int x0 = std::max(0, int(gc.x() - lpx)), x1 = std::min(rw - 1, int(gc.x() + lpx));
            const int y0 = std::max(0, int(gc.y() - lpx)), y1 = std::min(rh - 1, int(gc.y() + lpx));
            const uint32_t gs = ns + 100 + uint32_t(g);
            for (int v = y0; v <= y1; ++v)
                for (int u = x0; u <= x1; ++u) {
                    const Vec2 q = Vec2(u, v) - gc;
                    const double s = q.dot(ax) / (lpx / 2), t = q.dot(ay) / (wpx / 2);
                    const double fray = 0.06 * (vnoise(float(u * 0.3), float(v * 0.3), gs) - 0.5);
                    const double m = std::max(std::abs(s), std::abs(t)) + fray;
                    const size_t i = size_t(v) * rw + u;
                    if (m < 1.0) {
                        // Cotton: fibrous, slightly uneven, partly blood-soaked, matte.
                        const double f = 0.35 * px_per_mm;  // fibre scale ~0.35 mm
                        const float fib = vnoise(float(q.dot(ax) / f), float(q.dot(ay) / (4 * f)), gs + 1);
                        const float fib2 = vnoise(float(q.dot(ax) / (4 * f)), float(q.dot(ay) / f), gs + 2);
                        const float lump = fbm(float(u / (3 * px_per_mm)), float(v / (3 * px_per_mm)), gs + 3, 3);
                        Col alb = L.gauze * (0.78f + 0.06f * fib + 0.06f * fib2 + 0.2f * lump);
                        const float b = fbm(float(u / (6 * px_per_mm)), float(v / (6 * px_per_mm)), gs + 4, 3);
                        const float wet = smoothstep(1.05f - soak, 1.25f - soak, b + 0.25f * float(t));
                        alb = mix(alb, mix(L.blood * 2.5f, L.blood, wet), wet);
                        const float edge_shade = float(1 - 0.25 * smoothstep(0.8f, 1.0f, float(m)));
                        img[i] = alb * float(L.ambient + L.diffuse * 0.85) * edge_shade;
                        occl.data[i] = 255;
                    } else if (m < 1.12) {
                        img[i] *= float(0.55 + 0.45 * (m - 1.0) / 0.12);  // contact shadow
                    }
                }
            // The x-ray thread of the patty.
            const Vec2 a = gc + ax * lpx * 0.5, b = a + (ax * 0.6 - inward * 0.8).normalized() * lpx * rng.uni(0.4, 1.2);
            cv::Mat thread(rh, rw, CV_8U, cv::Scalar(0));
            cv::line(thread, cv::Point(int(a.x()), int(a.y())), cv::Point(int(b.x()), int(b.y())), cv::Scalar(255),
                     std::max(1, int(0.5 * px_per_mm)), cv::LINE_AA);
            const Col thread_col = rgb(40, 50, 90);
            for (size_t i = 0; i < npx; ++i)
                if (thread.data[i]) img[i] = mix(img[i], thread_col, float(thread.data[i]) / 255.f);
        }
    }
    if (has_blood && !cortex_contour.empty()) {
        n_blood = rng.integer(1, 3);
        for (int bI = 0; bI < n_blood; ++bI) {
            const cv::Point e = cortex_contour[size_t(rng.integer(0, int(cortex_contour.size()) - 1))];
            const Vec2 edge(e.x, e.y), inward = (cortex_c - edge).normalized();
            const double rpx = rng.uni(3, 11) * px_per_mm;
            const Vec2 bc = edge + inward * rpx * rng.uni(0.0, 1.2);
            const uint32_t bs = ns + 200 + uint32_t(bI);
            const int x0 = std::max(0, int(bc.x() - 2 * rpx)), x1 = std::min(rw - 1, int(bc.x() + 2 * rpx));
            const int y0 = std::max(0, int(bc.y() - 2 * rpx)), y1 = std::min(rh - 1, int(bc.y() + 2 * rpx));
            const float thin = float(rng.uni(0.2, 0.8));
            // Depth at the centre, mm: a shallow smear to a deep pool.
            const double deep_mm = 0.3 + 2.5 * (1 - thin);
            const float ppm = float(px_per_mm);
            // The pool's edge (m = 1) is ragged; its depth rises from nothing there (a meniscus)
            // as sqrt(1 - m), and clots and ripples roughen its surface a little.
            auto pool_m = [&](int uu, int vv) {
                return (Vec2(uu, vv) - bc).norm() / rpx + 0.7 * (fbm(float(uu / rpx * 1.5), float(vv / rpx * 1.5), bs, 3) - 0.5);
            };
            auto pool_depth_mm = [&](double m) { return deep_mm * std::sqrt(std::max(0.0, 1 - m)); };
            auto pool_h_mm = [&](int uu, int vv) {
                const double m = pool_m(uu, vv);
                return pool_depth_mm(m) +
                       0.015 * std::min(1.0, 4 * std::max(0.0, 1 - m)) * fbm(float(uu / (1.2 * ppm)), float(vv / (1.2 * ppm)), bs + 4, 2);
            };
            const double lamp_deg = L.pool_lamp_half_deg > 0 ? L.pool_lamp_half_deg : L.lamp_half_deg;
            const double cos_lamp = std::cos(lamp_deg * kPi / 180), cos_soft = std::cos(2.0 * lamp_deg * kPi / 180);
            // With the finish, the surface's height over the pool's box (one pixel of margin):
            // the meniscus dome plus a ripple of smoothed white noise, isotropic.
            cv::Mat pool_h;
            if (L.finish && L.pool_ripple_mm > 0 && x1 >= x0 && y1 >= y0) {
                cv::Mat ripple(y1 - y0 + 3, x1 - x0 + 3, CV_32F);
                cv::RNG noise(uint64_t(bs) * 0x9E3779B97F4A7C15ull + 0x9001ull);
                noise.fill(ripple, cv::RNG::NORMAL, 0.0, 1.0);
                const double sig = std::max(0.8, 0.5 * px_per_mm);
                cv::GaussianBlur(ripple, ripple, cv::Size(0, 0), sig, sig, cv::BORDER_REFLECT);
                cv::Scalar mean, sd;
                cv::meanStdDev(ripple, mean, sd);
                ripple = (ripple - mean[0]) * (L.pool_ripple_mm / std::max(sd[0], 1e-9));
                pool_h = cv::Mat(ripple.size(), CV_32F);
                for (int y = 0; y < pool_h.rows; ++y)
                    for (int x = 0; x < pool_h.cols; ++x) {
                        const double m = pool_m(x0 - 1 + x, y0 - 1 + y);
                        pool_h.at<float>(y, x) = float(pool_depth_mm(m) + std::min(1.0, 4 * std::max(0.0, 1 - m)) * ripple.at<float>(y, x));
                    }
            }
            for (int v = y0; v <= y1; ++v)
                for (int u = x0; u <= x1; ++u) {
                    const size_t i = size_t(v) * rw + u;
                    const double m = pool_m(u, v);
                    if (m < 1.0 && layer[i] != kDrape) {
                        // The rim is a red stain over the tissue and the middle the blood's own
                        // colour, darker where it clots.
                        const double h = pool_depth_mm(m);
                        const float clot = fbm(float(u / (1.2f * ppm)), float(v / (1.2f * ppm)), bs + 2, 3);
                        const Col body = L.blood * (0.55f + 0.7f * clot) * float(L.ambient + L.diffuse);
                        Col col = through_blood(img[i], body, h);
                        if (!L.finish) {
                            // Before the finish: flecks of glare, and a glint along the meniscus.
                            const float fleck = fbm(float(u / (2.5 * ppm)), float(v / (2.5 * ppm)), bs + 1, 2);
                            col += L.light * float(1.2 * smoothstep(0.84f, 0.9f, fleck) * L.spec * 0.6 * (1 - smoothstep(0.85f, 1.f, float(m))));
                            const float men = smoothstep(0.84f, 0.88f, float(m)) * (1 - smoothstep(0.9f, 0.94f, float(m)));
                            const float glint = smoothstep(0.62f, 0.8f, fbm(float(u / (1.5 * ppm)), float(v / (1.5 * ppm)), bs + 3, 2));
                            col += L.light * float(0.2 * L.spec * men * glint);
                        } else {
                            // Its smooth surface mirrors the lamp: where the surface's normal is the
                            // half-vector between lamp and camera, a soft-edged image of the lamp (on
                            // the dome's flank, or a glint along the meniscus on the lamp's side).
                            double sx, sy;
                            if (!pool_h.empty()) {
                                const int x = u - x0 + 1, y = v - y0 + 1;
                                sx = 0.5 * double(pool_h.at<float>(y, x + 1) - pool_h.at<float>(y, x - 1)) * px_per_mm;
                                sy = 0.5 * double(pool_h.at<float>(y + 1, x) - pool_h.at<float>(y - 1, x)) * px_per_mm;
                            } else {
                                sx = 0.5 * (pool_h_mm(u + 1, v) - pool_h_mm(u - 1, v)) * px_per_mm;
                                sy = 0.5 * (pool_h_mm(u, v + 1) - pool_h_mm(u, v - 1)) * px_per_mm;
                            }
                            const Vec3 n_cam = Vec3(-sx, -sy, -1).normalized();
                            const Vec3 p_cam = rays[i].cast<double>() * double(depth_cam[i]);
                            const Vec3 half = ((L.light_offset_camera_mm - p_cam).normalized() - p_cam.normalized()).normalized();
                            const float mirror = smoothstep(float(cos_soft), float(cos_lamp), float(n_cam.dot(half)));
                            col += L.light * float(0.9 * L.spec * mirror * mirror * smoothstep(0.f, 0.08f, float(h)));
                        }
                        img[i] = col;
                        if (m < 0.95) occl.data[i] = 255;
                    }
                }
        }
    }

    // ---- ROI: a little inside the visible cortex
    std::vector<Vec2> roi_render;
    cv::Mat cortex_inner;
    {
        const int er = std::max(2, int(std::lround(0.012 * rw)));
        cv::erode(cortex, cortex_inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * er + 1, 2 * er + 1)));
        std::vector<std::vector<cv::Point>> cs;
        cv::findContours(cortex_inner.clone(), cs, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
        const std::vector<cv::Point>* best = nullptr;
        for (auto& c : cs)
            if (!best || cv::contourArea(c) > cv::contourArea(*best)) best = &c;
        if (!best || best->size() < 20) throw InputError("phantom case " + std::to_string(index), "no ROI (internal)");
        // Smooth the contour so that the spline is not jagged, then pick control points.
        cv::Mat roi_fill(rh, rw, CV_8U, cv::Scalar(0));
        cv::drawContours(roi_fill, std::vector<std::vector<cv::Point>>{*best}, 0, cv::Scalar(255), cv::FILLED);
        cortex_inner = roi_fill;
        std::vector<cv::Point> approx;
        const int npts = rng.integer(10, 16);
        roi_render = resample_closed(*best, npts);
        // Pull the control points slightly inwards: the spline overshoots between them.
        cv::Moments m = cv::moments(roi_fill, true);
        const Vec2 cc(m.m10 / m.m00, m.m01 / m.m00);
        for (auto& p : roi_render) p += (cc - p).normalized() * std::min(3.0, 0.15 * (cc - p).norm());
    }
    const double to_final = double(W) / rw;
    auto final_px = [&](const Vec2& pr) { return Vec2((pr.x() + 0.5) * to_final - 0.5, (pr.y() + 0.5) * double(H) / rh - 0.5); };
    for (const auto& p : roi_render) out.roi_points.push_back(final_px(p));

    // Pixels well inside the ROI, for targets and landmarks.
    cv::Mat inner;
    {
        const int er = std::max(2, int(std::lround(0.02 * rw)));
        cv::erode(cortex_inner, inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * er + 1, 2 * er + 1)));
    }
    std::vector<int> inner_px;
    for (size_t i = 0; i < npx; ++i)
        if (inner.data[i] && layer[i] == kCortex && rb.triangle[i] >= 0) inner_px.push_back(int(i));
    if (inner_px.size() < 50) throw InputError("phantom case " + std::to_string(index), "cortex region too small (internal)");

    // ---- targets: visible cortex points spread over the ROI
    {
        const int nt = rng.integer(P.targets_min, P.targets_max);
        std::vector<Vec2> chosen_px;
        const double min_sep = std::sqrt(double(inner_px.size()) / nt) * 0.5;
        for (int tries = 0; tries < 4000 && int(out.targets_world_mm.size()) < nt; ++tries) {
            const int i = inner_px[size_t(rng.integer(0, int(inner_px.size()) - 1))];
            const Vec2 q(i % rw, i / rw);
            bool ok = true;
            for (const auto& c : chosen_px)
                if ((c - q).norm() < min_sep * (tries < 2000 ? 1.0 : 0.3)) ok = false;
            if (!ok) continue;
            chosen_px.push_back(q);
            out.targets_world_mm.push_back(pworld[size_t(i)]);
        }
    }

    // ---- landmarks: vessel bifurcations and sulcal points, visible and unoccluded
    {
        std::vector<std::pair<Vec3, Vec2>> cands;  // world, render pixel
        auto visible_px = [&](const Vec3& p, Vec2& px) {
            const auto q = project(Kr, T, p);
            if (!q) return false;
            const int u = int(std::lround(q->x())), v = int(std::lround(q->y()));
            if (u < 0 || v < 0 || u >= rw || v >= rh) return false;
            const size_t i = size_t(v) * rw + u;
            if (!inner.data[i] || occl.data[i] || layer[i] != kCortex) return false;
            const double zc = (T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>()).z();
            if (std::abs(zc - rb.depth_mm[i]) > 1.0) return false;
            px = *q;
            return true;
        };
        for (const auto& ab : tx.bifurcations_ab) {
            const Vec2 t = tx.to_tex(ab);
            const int x = int(std::lround(t.x())), y = int(std::lround(t.y()));
            if (x < 0 || y < 0 || x >= tx.N || y >= tx.N || tx.ortho.triangle[size_t(y) * tx.N + x] < 0) continue;
            const Vec3 p = interpolate_at(tx.ortho, S.mesh.triangles, S.mesh.vertices, x, y, Eigen::Vector3f(0, 0, 0)).cast<double>();
            Vec2 px;
            if (visible_px(p, px)) cands.emplace_back(p, px);
        }
        const size_t n_bif = cands.size();
        for (int tries = 0; tries < 3000 && cands.size() < n_bif + 60; ++tries) {
            const int i = inner_px[size_t(rng.integer(0, int(inner_px.size()) - 1))];
            const int u = i % rw, v = i / rw;
            const float sd = interpolate_at(rb, S.mesh.triangles, S.sulcal_depth_mm, u, v, 0.f);
            if (sd < 1.0f || sd > 3.5f) continue;  // the visible lip of a sulcus
            Vec2 px;
            if (visible_px(pworld[size_t(i)], px)) cands.emplace_back(pworld[size_t(i)], px);
        }
        if (cands.size() < 4) {  // fall back to any visible cortex point
            for (int tries = 0; tries < 2000 && cands.size() < 40; ++tries) {
                const int i = inner_px[size_t(rng.integer(0, int(inner_px.size()) - 1))];
                Vec2 px;
                if (visible_px(pworld[size_t(i)], px)) cands.emplace_back(pworld[size_t(i)], px);
            }
        }
        // Farthest-point sampling in the image, starting from a random candidate; bifurcations
        // are favoured by a bonus.
        const int nl = std::min<int>(rng.integer(P.landmarks_min, P.landmarks_max), int(cands.size()));
        std::vector<size_t> pick;
        if (!cands.empty()) pick.push_back(size_t(rng.integer(0, int(cands.size()) - 1)));
        while (int(pick.size()) < nl) {
            double best = -1;
            size_t bi = 0;
            for (size_t k = 0; k < cands.size(); ++k) {
                double dmin = 1e300;
                for (size_t q : pick) dmin = std::min(dmin, (cands[k].second - cands[q].second).norm());
                const double score = dmin * (k < n_bif ? 1.3 : 1.0);
                if (score > best) best = score, bi = k;
            }
            pick.push_back(bi);
        }
        const double px_sd = rng.uni(P.landmark_pixel_sd) * W / 750.0;
        for (size_t k = 0; k < pick.size(); ++k) {
            const auto& [p, pr] = cands[pick[k]];
            PhantomLandmark lm;
            lm.label = "L" + std::to_string(k + 1);
            lm.true_world_mm = p;
            lm.world_mm = p + P.landmark_world_sd_mm * Vec3(rng.normal(), rng.normal(), rng.normal());
            const auto q = project(K, T, p);
            lm.pixel = *q + px_sd * Vec2(rng.normal(), rng.normal());
            lm.pixel.x() = std::clamp(lm.pixel.x(), 0.0, double(W - 1));
            lm.pixel.y() = std::clamp(lm.pixel.y(), 0.0, double(H - 1));
            out.landmarks.push_back(lm);
        }
        if (out.landmarks.size() < 4) throw InputError("phantom case " + std::to_string(index), "fewer than 4 landmarks visible (internal)");
        notes << "landmark_pixel_sd=" << fmt(px_sd) << " bifurcation_candidates=" << n_bif << "; ";
    }

    // ---- post: white balance, exposure, vignetting, sRGB, blur, upscale, noise, JPEG
    cv::Mat photo(rh, rw, CV_32FC3);
    {
        const double cxn = Kr.cx, cyn = Kr.cy, rn = std::hypot(rw * 0.5, rh * 0.5);
        // The spot's centre and half-light radius in the picture (the field is nearly facing
        // the camera; its tilt and the lens' distortion are left out of the spot's shape).
        Vec2 spot_px(cxn, cyn);
        double spot_r_px = 1;
        if (cr.spot_r_mm > 0) {
            const Vec3 p = cr.c + cr.spot_c.x() * cr.e1 + cr.spot_c.y() * cr.e2;
            const Vec3 q = T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>();
            if (q.z() > 1) spot_px = Vec2(Kr.fx * q.x() / q.z() + Kr.cx, Kr.fy * q.y() / q.z() + Kr.cy);
            spot_r_px = std::max(1.0, cr.spot_r_mm * Kr.fx / std::max(1.0, q.z()));
        }
        for (int v = 0; v < rh; ++v) {
            cv::Vec3f* row = photo.ptr<cv::Vec3f>(v);
            for (int u = 0; u < rw; ++u) {
                const size_t i = size_t(v) * rw + u;
                const double r2 = (std::pow(u - cxn, 2) + std::pow(v - cyn, 2)) / (rn * rn);
                float vig = float(1 - L.vignette * r2);
                if (cr.spot_r_mm > 0) {
                    // The lamp's spot, flat-topped as a surgical light's field is.
                    const double d = std::hypot(u - spot_px.x(), v - spot_px.y()) / spot_r_px;
                    vig *= float(cr.spot_floor + (1 - cr.spot_floor) * std::exp(-0.6931 * d * d * d));
                }
                const Col c = img[i] * L.wb * float(L.exposure) * vig;  // linear light, glare above 1
                row[u] = cv::Vec3f(c[2], c[1], c[0]);                    // BGR
            }
        }
    }
    {
        // Depth of field, in linear light before the sensor clips: each pixel blurred by its circle
        // of confusion, fx * aperture * |z - z_focus| / (z * z_focus) (thin lens, focus far beyond
        // the focal length). Focused on the visible cortex's median depth, and stopped down until
        // 90 % of it is blurred by at most 1.5 px (the photographer keeps the cortex sharp; the
        // scalp and drapes soften). The aperture (3-10 mm before stopping down) comes from the
        // look's seed, so the other draws stay as they were.
        std::vector<double> zc;
        for (size_t i = 0; i < npx; ++i)
            if (layer[i] == kCortex) zc.push_back(depth_cam[i]);
        double z_focus = (R * cr.c + T.topRightCorner<3, 1>()).z();
        double aperture_mm = 3.0 + 7.0 * double(splitmix64(L.nseed) >> 11) / double(1ull << 53);
        if (!zc.empty()) {
            std::nth_element(zc.begin(), zc.begin() + long(zc.size() / 2), zc.end());
            z_focus = zc[zc.size() / 2];
            std::vector<double> coc_per_mm;  // CoC in px per mm of aperture
            for (double z : zc) coc_per_mm.push_back(Kr.fx * std::abs(z - z_focus) / (z * z_focus));
            const size_t k90 = coc_per_mm.size() * 9 / 10;
            std::nth_element(coc_per_mm.begin(), coc_per_mm.begin() + long(k90), coc_per_mm.end());
            if (coc_per_mm[k90] > 1e-9) aperture_mm = std::min(aperture_mm, 1.5 / coc_per_mm[k90]);
        }
        const std::array<double, 5> sigmas{0, 1, 2, 4, 8};  // px at render size
        std::array<cv::Mat, 5> levels;
        levels[0] = photo;
        for (size_t k = 1; k < sigmas.size(); ++k) cv::GaussianBlur(photo, levels[k], cv::Size(0, 0), sigmas[k]);
        cv::Mat focused(rh, rw, CV_32FC3);
        for (int v = 0; v < rh; ++v)
            for (int u = 0; u < rw; ++u) {
                const size_t i = size_t(v) * rw + u;
                const double z = std::max(1.0, double(depth_cam[i]));
                const double coc_px = Kr.fx * aperture_mm * std::abs(z - z_focus) / (z * z_focus);
                const double sg = std::min(coc_px / 2, sigmas.back());  // a blur disc's sd is about half its diameter
                size_t k = 0;
                while (k + 2 < sigmas.size() && sg > sigmas[k + 1]) ++k;
                const float w = float(std::clamp((sg - sigmas[k]) / (sigmas[k + 1] - sigmas[k]), 0.0, 1.0));
                focused.at<cv::Vec3f>(v, u) = levels[k].at<cv::Vec3f>(v, u) * (1 - w) + levels[k + 1].at<cv::Vec3f>(v, u) * w;
            }
        photo = focused;
        notes << "aperture_mm=" << fmt(aperture_mm, 1) << " ";
    }
    if (L.bloom > 0) {
        // Halation: light above the sensor's white point spreads in the lens and the sensor's
        // stack, a tight halo and a wide veil around glare (a rendering stops at the clip).
        cv::Mat excess, near_halo, wide_halo;
        cv::subtract(photo, cv::Scalar::all(0.9), excess);
        excess = cv::max(excess, 0.0);
        cv::GaussianBlur(excess, near_halo, cv::Size(0, 0), 0.005 * rw);
        cv::GaussianBlur(excess, wide_halo, cv::Size(0, 0), 0.03 * rw);
        photo += (near_halo * 3.0 + wide_halo * 1.5) * L.bloom;
    }
    // The sensor clips after the lens has blurred: glare stays saturated where it is bright.
    for (int v = 0; v < rh; ++v) {
        cv::Vec3f* row = photo.ptr<cv::Vec3f>(v);
        for (int u = 0; u < rw; ++u)
            for (int k = 0; k < 3; ++k) row[u][k] = 255.f * std::pow(std::clamp(row[u][k], 0.f, 1.f), 1 / 2.2f);
    }
    if (L.chroma > 0) {
        // Lateral colour: the lens images red a little larger than blue, so edges far from the
        // centre carry coloured fringes (about a pixel at the corners).
        std::vector<cv::Mat> ch;
        cv::split(photo, ch);  // BGR
        for (const auto& [k, scale] : {std::pair{0, 1 - L.chroma}, std::pair{2, 1 + L.chroma}}) {
            const cv::Matx23d A(scale, 0, Kr.cx * (1 - scale), 0, scale, Kr.cy * (1 - scale));
            cv::warpAffine(ch[size_t(k)], ch[size_t(k)], A, ch[size_t(k)].size(), cv::INTER_LINEAR, cv::BORDER_REFLECT);
        }
        cv::merge(ch, photo);
    }
    cv::GaussianBlur(photo, photo, cv::Size(0, 0), L.blur_px);
    if (rw != W || rh != H) cv::resize(photo, photo, cv::Size(W, H), 0, 0, cv::INTER_CUBIC);
    {
        cv::Mat noise(H, W, CV_32FC3);
        cv::RNG cvr(uint64_t(rng.u32()) << 16 | 7);
        cvr.fill(noise, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(L.noise_sd * (dslr ? 1.5 : 1.0)));
        photo += noise;
    }
    photo.convertTo(out.photo_bgr, CV_8UC3);  // saturates
    if (apply_jpeg_artefacts && !out.jpeg) {
        std::vector<uchar> buf;
        cv::imencode(".jpg", out.photo_bgr, buf, {cv::IMWRITE_JPEG_QUALITY, L.jpeg_quality});
        out.photo_bgr = cv::imdecode(buf, cv::IMREAD_COLOR);
    }

    notes << "size=" << W << "x" << H << (dslr ? " dslr" : "") << " render=" << rw << "x" << rh
          << " distance_mm=" << fmt(dist, 1) << " tilt_deg=" << fmt(tilt * 180 / kPi, 1) << " roll_deg=" << fmt(roll * 180 / kPi, 1)
          << " craniotomy_mm=" << fmt(diam, 1) << " head_radius_mm=" << fmt(cr.Rc, 0) << " distortion=" << (distorted ? "yes" : "no")
          << " gauze=" << n_gauze << " blood=" << n_blood << " veins=" << n_veins << " arteries=" << n_arteries
          << " towels=" << cr.n_towels << " burr_holes=" << cr.n_burr << " clips=" << cr.n_clips
          << " dural_flap=" << (cr.flap_w > 0 ? "yes" : "no") << " arachnoid_veil=" << fmt(cr.veil)
          << " sulcal_blood=" << fmt(cr.sah) << " blood_film_mm=" << fmt(cr.film_mm)
          << " far_lamp_mm=" << fmt(far_lamp_mm, 0) << " lamp_spot_mm=" << fmt(cr.spot_r_mm, 0) << " spot_floor=" << fmt(cr.spot_floor) << " skin_prep=" << fmt(cr.prep)
          << " shininess=" << fmt(L.shininess, 0) << " spec=" << fmt(L.spec) << " exposure=" << fmt(L.exposure)
          << " noise_sd=" << fmt(L.noise_sd) << " photo_finish=" << (L.finish ? "yes" : "no")
          << " drape_fold_slope=" << fmt(L.fold_slope) << " drape_fold_mm=" << fmt(L.fold_mm, 0) << " halation=" << fmt(L.bloom)
          << " lateral_colour=" << fmt(L.chroma * 1e3) << "e-3" << " stubble=" << (L.stubble ? "yes" : "no")
          << " clip_tilt_deg=" << fmt(L.clip_tilt_deg, 1) << " dura_rag=" << fmt(L.dura_rag) << " sutures=" << L.n_sutures
          << " bone_tissue=" << fmt(L.tissue_frac) << " char=" << fmt(L.char_k) << " blood_trickles=" << L.n_trickles
          << " dura_vessels=" << fmt(L.dura_vessels) << " dura_grey=" << fmt(L.dura_grey)
          << " scatter_mm=" << fmt(L.scatter_mm) << " scatter_share=" << fmt(L.scatter_share)
          << " pool_lamp_half_deg=" << fmt(L.pool_lamp_half_deg, 1) << " pool_ripple_mm=" << fmt(L.pool_ripple_mm, 3)
          << " jpeg_quality=" << (out.jpeg ? out.jpeg_quality : (apply_jpeg_artefacts ? L.jpeg_quality : 0));
    out.notes = notes.str();
    return out;
}

}  // namespace cf
