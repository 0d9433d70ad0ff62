// `cortexfuse overlay CASE RESULT --plan PLAN --out DIR` run as a user runs it, on a planned
// phantom case built here (2 mm copy of the shipped head): the fused PNGs show the plan's CT
// and fMRI (GL fusion scene), and with GL unavailable the CPU draws the T1 alone and says so
// in one line. The plan folder is written by the test (CT-like and fMRI volumes on the T1
// grid, as `cortexfuse plan` leaves them), so the test needs no co-registration run.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "../../cli/process.hpp"
#include "../../remove_dir_guard.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/plan.hpp"
#include "cortexfuse/core/roi.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/render/gl_renderer.hpp"

namespace fs = std::filesystem;
using cf::test::run_process;

namespace {

struct Planned {
    fs::path dir, case_dir, result, plan, other_plan;
    // Bad inputs: a plan of another patient's T1 on the same grid, a case whose brain mask is
    // empty, a surface 300 mm away, a mesh with no triangles, a pose looking away from the
    // brain, a plan whose fMRI map is empty.
    fs::path other_patient_plan, empty_mask_case, far_mesh, no_triangles_mesh, away_result, empty_fmri_plan;
    Eigen::Vector2d fmri_px;  // where the fMRI blob is seen in the camera's fused picture
    double view_scale = 1.0;
};

void write_json(const fs::path& p, const nlohmann::json& j) { std::ofstream(p) << j.dump(1); }

nlohmann::json read_json_file_here(const fs::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}

const Planned& planned() {
    static const Planned w = [] {
        Planned r;
        r.dir = fs::temp_directory_path() / ("cf_overlay_plan_cli_" + std::to_string(::getpid()));
        fs::remove_all(r.dir);
        fs::create_directories(r.dir);
        const cf::Volume t1_full = cf::load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
        const cf::LabelVolume m_full = cf::load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
        const cf::VolumeGeometry g = cf::isotropic_grid(t1_full.geom, 2.0);
        const cf::Volume t1 = cf::resample(t1_full, g);
        const cf::LabelVolume mask = cf::resample_nearest(m_full, g);
        cf::save_volume(t1, r.dir / "t1.nii.gz");
        cf::save_mask(mask, r.dir / "brain_mask.nii.gz");
        const cf::PhantomSurface surface = cf::build_phantom_surface(t1, mask);
        cf::PhantomParams p;
        p.seed = 5;
        p.width = 240;
        p.height = 160;
        p.vary_size = false;
        p.dslr_fraction = 0;
        p.distortion_prob = 0;
        p.gauze_prob = 0;
        p.blood_prob = 0;
        const cf::PhantomCase pc = cf::generate_phantom_case(surface, p, 0);
        r.case_dir = r.dir / "case";
        cf::write_phantom_case(pc, r.case_dir, "../t1.nii.gz", "../brain_mask.nii.gz");
        r.result = r.dir / "result.json";
        write_json(r.result, {{"T_camera_from_world", cf::pose_to_json(pc.T_camera_from_world)}});

        // The plan: its mask and surface, a CT-like volume (bone outside the brain where the
        // T1 is bright, soft tissue inside) and an fMRI t-map with one blob under the ROI.
        r.plan = r.dir / "plan";
        fs::create_directories(r.plan);
        cf::save_mask(mask, r.plan / "brain_mask.nii.gz");
        cf::SurfaceMesh mesh;
        mesh.vertices = surface.mesh.vertices;
        mesh.triangles = surface.mesh.triangles;
        mesh.normals = surface.normals;
        cf::save_mesh(mesh, r.plan / "brain_surface.ply");
        cf::Volume ct = t1;
        const auto st = cf::intensity_stats(t1);
        for (size_t i = 0; i < ct.voxels.size(); ++i)
            ct.voxels[i] = mask.voxels[i] ? 40.f : (t1.voxels[i] > st.p50 ? 900.f : -1000.f);
        cf::save_volume(ct, r.plan / "ct_on_t1.nii.gz");
        Eigen::Vector2d c = Eigen::Vector2d::Zero();
        for (const auto& q : pc.roi_points) c += q;
        c /= double(pc.roi_points.size());
        const auto hit = cf::cast_back(mesh, pc.camera, pc.T_camera_from_world, c);
        if (!hit) throw std::runtime_error("test setup: the ROI centre does not hit the surface");
        r.fmri_px = c;
        cf::Volume fmri = t1;
        const Eigen::Affine3d w_from_i = g.world_from_index();
        for (int k = 0; k < g.dims[2]; ++k)
            for (int j = 0; j < g.dims[1]; ++j)
                for (int i = 0; i < g.dims[0]; ++i) {
                    const double d = ((w_from_i * Eigen::Vector3d(i, j, k)) - hit->p_world_mm).norm();
                    fmri.voxels[g.linear(i, j, k)] = d < 10.0 ? 8.f : 0.f;
                }
        cf::save_volume(fmri, r.plan / "fmri_on_t1.nii.gz");
        write_json(r.plan / "fmri_transfer_function.json", cf::to_json(cf::preset_transfer_function("fmri_hot")));

        // plan.json keeps the T1's fingerprint, as `cortexfuse plan` writes it.
        write_json(r.plan / "plan.json", {{"format", "cortexfuse-plan/1"},
                                          {"t1_fingerprint", cf::volume_fingerprint(cf::load_volume(r.dir / "t1.nii.gz"))}});

        // Another patient's plan on an identical grid: same grid, other voxels.
        r.other_patient_plan = r.dir / "other_patient_plan";
        fs::create_directories(r.other_patient_plan);
        cf::save_mask(mask, r.other_patient_plan / "brain_mask.nii.gz");
        cf::Volume other_t1 = t1;
        for (size_t i = 0; i < other_t1.voxels.size(); i += 7) other_t1.voxels[i] *= 0.9f;
        write_json(r.other_patient_plan / "plan.json",
                   {{"format", "cortexfuse-plan/1"}, {"t1_fingerprint", cf::volume_fingerprint(other_t1)}});
        // A case whose brain mask is empty.
        r.empty_mask_case = r.dir / "case_empty_mask";
        fs::copy(r.case_dir, r.empty_mask_case, fs::copy_options::recursive);
        cf::LabelVolume empty = mask;
        std::fill(empty.voxels.begin(), empty.voxels.end(), uint8_t(0));
        cf::save_mask(empty, r.dir / "empty_mask.nii.gz");
        {
            nlohmann::json cj = read_json_file_here(r.empty_mask_case / "case.json");
            cj["brain_mask"] = "../empty_mask.nii.gz";
            write_json(r.empty_mask_case / "case.json", cj);
        }
        // The plan's surface moved 300 mm: it lies on no brain of this case.
        {
            cf::SurfaceMesh far = mesh;
            for (auto& v : far.vertices) v.x() += 300.f;
            r.far_mesh = r.dir / "far_surface.ply";
            cf::save_mesh(far, r.far_mesh);
        }
        // A mesh with vertices and no triangles (ASCII PLY).
        r.no_triangles_mesh = r.dir / "no_triangles.ply";
        std::ofstream(r.no_triangles_mesh) << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                              "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
                                              "end_header\n0 0 0\n1 0 0\n0 1 0\n";
        // The camera turned 180 degrees about its vertical axis: it looks away from the brain.
        {
            cf::Pose away = cf::Pose::Identity();
            away.topLeftCorner<3, 3>() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY()).toRotationMatrix();
            r.away_result = r.dir / "result_away.json";
            write_json(r.away_result, {{"T_camera_from_world", cf::pose_to_json(away * pc.T_camera_from_world)}});
        }
        // A plan whose fMRI map holds no active voxel.
        r.empty_fmri_plan = r.dir / "empty_fmri_plan";
        fs::create_directories(r.empty_fmri_plan);
        cf::save_mask(mask, r.empty_fmri_plan / "brain_mask.nii.gz");
        cf::Volume zero = t1;
        std::fill(zero.voxels.begin(), zero.voxels.end(), 0.f);
        cf::save_volume(zero, r.empty_fmri_plan / "fmri_on_t1.nii.gz");

        // A plan of another T1 (a 3 mm grid): must be refused.
        r.other_plan = r.dir / "other_plan";
        fs::create_directories(r.other_plan);
        cf::save_mask(cf::resample_nearest(m_full, cf::isotropic_grid(t1_full.geom, 3.0)), r.other_plan / "brain_mask.nii.gz");
        return r;
    }();
    // The folder goes when the test program ends.
    static const cf::test::RemoveDirGuard remove_at_exit{w.dir};
    return w;
}

cf::test::ProcessResult overlay(const std::vector<std::string>& extra, const fs::path& out) {
    std::vector<std::string> a{CF_CORTEXFUSE_EXE, "overlay", planned().case_dir.string(), planned().result.string(),
                               "--out", out.string(), "--yaw", "30", "--pitch", "20"};
    a.insert(a.end(), extra.begin(), extra.end());
    return run_process(a, 280.0);
}

nlohmann::json read_json(const fs::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}

/// Pixels of the fMRI map's colours (dark red to yellow: blue far below red). The T1's
/// cortex is pink (blue about 0.6-0.7 of red), the CT's bone white-beige, the photo grey.
int hot_pixels(const cv::Mat& bgr) {
    int n = 0;
    for (int y = 0; y < bgr.rows; ++y)
        for (int x = 0; x < bgr.cols; ++x) {
            const auto& p = bgr.at<cv::Vec3b>(y, x);
            if (p[2] > 120 && p[0] < 0.35 * p[2]) ++n;
        }
    return n;
}

double mean_abs_diff(const cv::Mat& a, const cv::Mat& b) {
    cv::Mat d;
    cv::absdiff(a, b, d);
    const cv::Scalar s = cv::mean(d);
    return (s[0] + s[1] + s[2]) / 3.0;
}

class GlEnv {
public:
    explicit GlEnv(bool disable) {
        if (const char* e = std::getenv("CF_GL_DISABLE")) saved_ = e, had_ = true;
        if (disable) ::setenv("CF_GL_DISABLE", "1", 1);
        else ::unsetenv("CF_GL_DISABLE");
    }
    ~GlEnv() {
        if (had_) ::setenv("CF_GL_DISABLE", saved_.c_str(), 1);
        else ::unsetenv("CF_GL_DISABLE");
    }

private:
    std::string saved_;
    bool had_ = false;
};

bool gl_available(std::string& why) {
    GlEnv env(false);
    try {
        cf::probe_gl();
        return true;
    } catch (const std::exception& e) {
        why = e.what();
        return false;
    }
}

}  // namespace

TEST(OverlayPlanCli, FusedPicturesAreMultimodalWithGl) {
    std::string why;
    if (!gl_available(why)) GTEST_SKIP() << "no GL context: " << why;
    const auto& w = planned();
    GlEnv env(false);
    const fs::path t1_out = w.dir / "t1_only", mm_out = w.dir / "multimodal";
    const auto a = overlay({"--mesh", (w.plan / "brain_surface.ply").string()}, t1_out);
    ASSERT_EQ(a.exit_code, 0) << a.err;
    const auto b = overlay({"--plan", w.plan.string()}, mm_out);
    ASSERT_EQ(b.exit_code, 0) << b.err;
    const auto j = read_json(mm_out / "overlay.json");
    EXPECT_EQ(j["modalities"], nlohmann::json({"t1", "ct", "fmri"}));
    EXPECT_EQ(j["mesh"], (w.plan / "brain_surface.ply").string()) << "the plan's surface is used without --mesh";
    EXPECT_EQ(read_json(t1_out / "overlay.json")["modalities"], nlohmann::json({"t1"}));
    // From the camera and from both free viewpoints the pictures change (the CT's bone around
    // the craniotomy, the fMRI map).
    for (const char* f : {"fused_camera.png", "fused_yaw30.png", "fused_pitch20.png"}) {
        const cv::Mat t = cv::imread((t1_out / f).string()), m = cv::imread((mm_out / f).string());
        ASSERT_FALSE(t.empty()) << f;
        ASSERT_FALSE(m.empty()) << f;
        ASSERT_EQ(t.size(), m.size()) << f;
        EXPECT_GT(mean_abs_diff(t, m), 5.0) << f;
    }
    // The activation is where it was put: its colours near the ROI centre from the camera,
    // none there in the T1-only picture.
    {
        const cv::Mat t = cv::imread((t1_out / "fused_camera.png").string());
        const cv::Mat m = cv::imread((mm_out / "fused_camera.png").string());
        const double s = double(m.cols) / 240.0;
        const cv::Rect box = cv::Rect(int(w.fmri_px.x() * s) - 25, int(w.fmri_px.y() * s) - 25, 50, 50) &
                             cv::Rect(0, 0, m.cols, m.rows);
        EXPECT_GT(hot_pixels(m(box)), 100);
        EXPECT_LT(hot_pixels(t(box)), 10);
    }
    // Weight 0 leaves a modality out; without the CT the fMRI map shows from a free viewpoint.
    const auto c = overlay({"--plan", w.plan.string(), "--fmri-weight", "0"}, w.dir / "no_fmri");
    ASSERT_EQ(c.exit_code, 0) << c.err;
    EXPECT_EQ(read_json(w.dir / "no_fmri" / "overlay.json")["modalities"], nlohmann::json({"t1", "ct"}));
    const auto d = overlay({"--plan", w.plan.string(), "--ct-weight", "0"}, w.dir / "no_ct");
    ASSERT_EQ(d.exit_code, 0) << d.err;
    EXPECT_EQ(read_json(w.dir / "no_ct" / "overlay.json")["modalities"], nlohmann::json({"t1", "fmri"}));
    const cv::Mat t = cv::imread((t1_out / "fused_yaw30.png").string());
    const cv::Mat f = cv::imread((w.dir / "no_ct" / "fused_yaw30.png").string());
    ASSERT_FALSE(f.empty());
    EXPECT_GT(hot_pixels(f), hot_pixels(t) + 100);
}

TEST(OverlayPlanCli, CpuFallbackDrawsTheT1AloneAndSaysSo) {
    const auto& w = planned();
    GlEnv env(true);
    const fs::path t1_out = w.dir / "cpu_t1", fb_out = w.dir / "cpu_fallback";
    const auto a = overlay({"--mesh", (w.plan / "brain_surface.ply").string()}, t1_out);
    ASSERT_EQ(a.exit_code, 0) << a.err;
    const auto b = overlay({"--plan", w.plan.string()}, fb_out);
    ASSERT_EQ(b.exit_code, 0) << b.err;
    EXPECT_NE(b.err.find("only the T1 is drawn (ct, fmri of the plan left out"), std::string::npos) << b.err;
    const auto j = read_json(fb_out / "overlay.json");
    EXPECT_EQ(j["modalities"], nlohmann::json({"t1"}));
    // The same picture as without the plan: the CPU ray caster of the T1 alone.
    for (const char* f : {"fused_camera.png", "fused_yaw30.png"}) {
        const cv::Mat t = cv::imread((t1_out / f).string()), m = cv::imread((fb_out / f).string());
        ASSERT_FALSE(t.empty()) << f;
        ASSERT_FALSE(m.empty()) << f;
        EXPECT_EQ(mean_abs_diff(t, m), 0.0) << f;
    }
    // --renderer gl does not fall back: a clear error.
    const auto c = overlay({"--plan", w.plan.string(), "--renderer", "gl"}, w.dir / "gl_forced");
    EXPECT_NE(c.exit_code, 0);
    EXPECT_NE(c.err.find("OpenGL"), std::string::npos) << c.err;
}

TEST(OverlayPlanCli, PlanOfAnotherT1IsRefused) {
    const auto& w = planned();
    const auto r = overlay({"--plan", w.other_plan.string()}, w.dir / "other");
    EXPECT_NE(r.exit_code, 0);
    EXPECT_NE(r.err.find("another T1"), std::string::npos) << r.err;
    EXPECT_NE(r.err.find(w.other_plan.string()), std::string::npos) << r.err;
    const auto n = overlay({"--plan", (w.dir / "no_such_plan").string()}, w.dir / "none");
    EXPECT_NE(n.exit_code, 0);
    EXPECT_NE(n.err.find("not a folder"), std::string::npos) << n.err;
}

// Bad input: one line on stderr naming the input and the problem, a non-zero exit, and
// nothing written (a new output folder is not even left behind; an existing one keeps only
// what it held).
TEST(OverlayPlanCli, BadInputsStopWithOneLineNamingTheInputAndWriteNothing) {
    const auto& w = planned();
    struct Bad {
        std::string what;
        std::vector<std::string> argv;  // full overlay argv after "overlay"
        std::string input, problem;
    };
    const std::string cse = w.case_dir.string(), res = w.result.string();
    const std::vector<Bad> bad{
        {"another patient's plan", {cse, res, "--plan", w.other_patient_plan.string()}, w.other_patient_plan.string(),
         "the plan was made from another T1 (its voxels differ"},
        {"a plan of another grid", {cse, res, "--plan", w.other_plan.string()}, w.other_plan.string(), "another T1"},
        {"absurd overlap", {cse, res, "--mesh", w.far_mesh.string()}, w.far_mesh.string(), "absurd overlap with the case's brain"},
        {"empty brain mask", {w.empty_mask_case.string(), res}, (w.empty_mask_case / ".." / "empty_mask.nii.gz").string(),
         "the brain mask is empty"},
        {"no triangles", {cse, res, "--mesh", w.no_triangles_mesh.string()}, w.no_triangles_mesh.string(), "no triangles"},
        {"pose away from the brain", {cse, w.away_result.string(), "--mesh", (w.plan / "brain_surface.ply").string()},
         w.away_result.string(), "the camera points away from the brain"},
        {"empty fMRI map", {cse, res, "--plan", w.empty_fmri_plan.string()}, (w.empty_fmri_plan / "fmri_on_t1.nii.gz").string(),
         "empty: no active voxel"},
    };
    for (size_t i = 0; i < bad.size(); ++i) {
        const auto& b = bad[i];
        for (bool existing : {false, true}) {
            const fs::path out = w.dir / ("bad_" + std::to_string(i) + (existing ? "_existing" : ""));
            if (existing) {
                fs::create_directories(out);
                std::ofstream(out / "keep.txt") << "kept";
            }
            std::vector<std::string> a{CF_CORTEXFUSE_EXE, "overlay"};
            a.insert(a.end(), b.argv.begin(), b.argv.end());
            a.insert(a.end(), {"--out", out.string()});
            const auto r = run_process(a, 120.0);
            EXPECT_NE(r.exit_code, 0) << b.what;
            EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << b.what << ": " << r.err;
            EXPECT_NE(r.err.find(b.input + ": "), std::string::npos) << b.what << ": " << r.err;
            EXPECT_NE(r.err.find(b.problem), std::string::npos) << b.what << ": " << r.err;
            if (existing) {
                size_t n = 0;
                for (const auto& e : fs::directory_iterator(out)) {
                    ++n;
                    EXPECT_EQ(e.path().filename(), "keep.txt") << b.what;
                }
                EXPECT_EQ(n, 1u) << b.what;
            } else {
                EXPECT_FALSE(fs::exists(out)) << b.what << ": the failed run left " << out;
            }
        }
    }
}
