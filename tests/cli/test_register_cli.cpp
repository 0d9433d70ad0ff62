// `cortexfuse register` on valid cases: photos of any size (a DSLR-size JPEG registers as well as
// its small version, on the full bundled head) and the landmark initialisation it is asked for.
#include <gtest/gtest.h>

#include <filesystem>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "../sanitized.hpp"
#include "base_case.hpp"
#include "cli_files.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/evaluation.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"
#include "process.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf;

namespace {

using test::fresh_dir;
using test::pose_of;
using test::read_json;
using test::write_json;

// Pixel coordinates under an image resize by `s` (OpenCV pixel centres).
double scale_px(double u, double s) { return (u + 0.5) * s - 0.5; }

/// Makes a DSLR-size copy of `src`: the photo upscaled by `s` and saved as JPEG, the camera's
/// intrinsics, the landmark pixels and the ROI scaled with it.
void make_scaled_case(const fs::path& src, const fs::path& dst, double s) {
    fs::copy(src, dst, fs::copy_options::recursive);
    json cj = read_json(dst / "case.json");
    const Intrinsics K = parse_camera(cj, "case.json");
    const Intrinsics K2 = K.resized(int(std::lround(K.width * s)), int(std::lround(K.height * s)));
    const cv::Mat photo = cv::imread((dst / cj.at("photo").get<std::string>()).string(), cv::IMREAD_COLOR);
    ASSERT_FALSE(photo.empty());
    cv::Mat big;
    cv::resize(photo, big, cv::Size(K2.width, K2.height), 0, 0, cv::INTER_CUBIC);
    fs::remove(dst / cj.at("photo").get<std::string>());
    ASSERT_TRUE(cv::imwrite((dst / "photo.jpg").string(), big, {cv::IMWRITE_JPEG_QUALITY, 95}));
    cj["photo"] = "photo.jpg";
    cj["camera"] = camera_to_json(K2);
    write_json(dst / "case.json", cj);
    json lj = read_json(dst / "landmarks.json");
    for (auto& l : lj.at("landmarks"))
        l["pixel"] = {scale_px(l["pixel"][0].get<double>(), s), scale_px(l["pixel"][1].get<double>(), s)};
    write_json(dst / "landmarks.json", lj);
    json rj = read_json(dst / "roi.json");
    for (auto& p : rj.at("points")) p = {scale_px(p[0].get<double>(), s), scale_px(p[1].get<double>(), s)};
    write_json(dst / "roi.json", rj);
}

test::ProcessResult run_register(const fs::path& case_dir, const fs::path& out, std::vector<std::string> extra = {}) {
    std::vector<std::string> argv{test::cortexfuse_exe(), "register", case_dir.string(), "--out", out.string()};
    argv.insert(argv.end(), extra.begin(), extra.end());
    return test::run_process(argv, 300.0);
}

Eigen::Vector3d targets_centroid(const fs::path& case_dir) {
    const json t = read_json(case_dir / "truth.json");
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const auto& p : t.at("targets_world_mm")) c += Eigen::Vector3d(p[0].get<double>(), p[1].get<double>(), p[2].get<double>());
    return c / double(t.at("targets_world_mm").size());
}

}  // namespace

// The seed took 3000x2000 photos and worked at 375x250: a DSLR-size JPEG of a scene must register
// as well as the small photo of it (it is downsampled internally, intrinsics scaled). On the full
// 1 mm bundled head, since the 64^3 test volume does not hold a pose: there, started at the truth
// with one short stage, both versions drifted 4.8 deg. Accuracy is compared against the truth
// (MRE on the phantom's mesh), not pose against pose: depth is weakly seen by a single photo, so
// two runs may end millimetres apart along the view and both be right on the surface.
TEST(RegisterCli, DslrSizeJpegRegistersAsWellAsItsSmallVersionOnTheFullHead) {
    if (test::kSanitized) GTEST_SKIP() << "two registrations on the 1 mm head take minutes under the sanitizers";
    const fs::path data(CF_DATA_DIR);
    const Volume t1 = load_volume(data / "t1_head_mne_ecog.nii.gz");
    const LabelVolume mask = load_mask(data / "brainmask_mne_ecog_binary.nii.gz");
    const PhantomSurface surface = build_phantom_surface(t1, mask);
    PhantomParams p;
    p.seed = 3;  // a case whose landmarks alone miss by 2.9 mm: the photo has to do the work
    p.width = 750;
    p.height = 500;
    p.vary_size = false;
    p.dslr_fraction = 0;
    p.png_fraction = 1;  // the small photo lossless: the JPEG is the DSLR copy's
    const fs::path work = fresh_dir("dslr");
    write_phantom_case(generate_phantom_case(surface, p, 0), work / "small", (data / "t1_head_mne_ecog.nii.gz").string(),
                       (data / "brainmask_mne_ecog_binary.nii.gz").string());
    make_scaled_case(work / "small", work / "dslr", 3000.0 / 750.0);

    std::map<std::string, PoseErrors> err;
    std::map<std::string, json> result;
    for (const std::string v : {"small", "dslr"}) {
        const auto r = run_register(work / v, work / (v + ".json"));
        ASSERT_EQ(r.exit_code, 0) << v << ": " << r.err;
        result[v] = read_json(work / (v + ".json"));
        const CaseSpec spec = read_case(work / v);
        ASSERT_TRUE(spec.truth.has_value());
        err[v] = pose_errors(*spec.truth, spec.camera, pose_of(result[v].at("T_camera_from_world")), surface.mesh);
        err[v + " landmarks"] =
            pose_errors(*spec.truth, spec.camera, pose_of(result[v].at("initial_T_camera_from_world")), surface.mesh);
    }
    for (const auto& [v, e] : err) std::cout << "MRE " << v << ": " << e.mre_mm << " mm\n";
    EXPECT_EQ(cv::imread((work / "dslr" / "photo.jpg").string()).cols, 3000);
    // The same landmark start (pixels scaled with the intrinsics) ...
    const Eigen::Vector3d pivot = targets_centroid(work / "small");
    const PoseDelta d0 = pose_delta(pose_of(result["small"].at("initial_T_camera_from_world")),
                                    pose_of(result["dslr"].at("initial_T_camera_from_world")), pivot);
    EXPECT_LT(d0.angle_deg, 0.05);
    EXPECT_LT(d0.translation_mm, 0.1);
    // ... and both registered well inside the seed's 3 mm radius, far better than the landmarks
    // alone, so the DSLR photo's pixels were used, not only its landmarks; the DSLR copy no worse
    // than the small photo by more than the spread of repeated runs. Measured (18th session,
    // MRE small / DSLR / landmarks alone, mm): seed 3 0.20 / 0.17 / 2.87; for comparison seeds
    // 1, 2, 4, 5, 6, 7, 2026: 0.51/0.57/0.48, 0.71/0.76/1.28, 0.57/0.49/0.99, 0.84/0.89/1.54,
    // 0.65/0.64/1.22, 1.79/0.99/0.70, 1.02/1.03/1.00.
    for (const std::string v : {"small", "dslr"}) {
        EXPECT_LT(err[v].mre_mm, 1.5) << v;
        EXPECT_LT(err[v].mre_mm, err[v + " landmarks"].mre_mm - 1.0) << v;
    }
    EXPECT_LT(err["dslr"].mre_mm, err["small"].mre_mm + 1.0)
        << "small " << err["small"].mre_mm << " mm, dslr " << err["dslr"].mre_mm << " mm";
    fs::remove_all(work);
}

// --init picks the landmark alignment: PnP (RANSAC from 6 pairs) or the seed's orthographic
// variant; the result records the method and its reprojection RMS in pixels.
TEST(RegisterCli, InitMethodIsSelectableAndReported) {
    const fs::path base = test::base_cases() / "small";
    const fs::path work = fresh_dir("init");
    const Pose T_true = pose_of(read_json(base / "truth.json").at("T_camera_from_world"));
    const Eigen::Vector3d pivot = targets_centroid(base);
    // Only the initialisation is of interest here: one tiny stage.
    write_json(work / "params.json", {{"search_stages", json::array()},
                                      {"final_stages", {{{"name", "one"}, {"max_evaluations", 5}, {"render_width_px", 96}}}}});
    std::map<std::string, PoseDelta> err;
    std::map<std::string, double> rms;
    for (const std::string m : {"pnp", "ortho"}) {
        const auto r = run_register(base, work / (m + ".json"), {"--init", m, "--params", (work / "params.json").string()});
        ASSERT_EQ(r.exit_code, 0) << r.err;
        const json j = read_json(work / (m + ".json"));
        const json& fit = j.at("landmark_fit");
        EXPECT_EQ(fit.at("method").get<std::string>().rfind(m == "pnp" ? "pnp" : "orthographic", 0), 0u) << fit;
        rms[m] = fit.at("rms_px").get<double>();
        // The one fit asked for is the start: the landmarks' other fits are not added as moves.
        EXPECT_EQ(j.at("parameters").at("initial_pose_landmark_moves"), false) << m;
        EXPECT_GE(fit.at("inliers").size(), 4u);
        err[m] = pose_delta(pose_of(j.at("initial_T_camera_from_world")), T_true, pivot);
    }
    // Known-pose accuracy of both fits is tested in tests/core/inputs (exact landmarks). Here the
    // phantom's 6 near-planar landmarks with picking noise leave PnP a mirror ambiguity (which is
    // why `--init auto` also starts from the mirrored pose), so only the reporting is checked:
    // PnP minimises exactly what the RMS measures, so the orthographic fit cannot beat it.
    EXPECT_LT(rms["pnp"], 4.0);
    EXPECT_GE(rms["ortho"], rms["pnp"] - 1e-6);
    (void)err;
    (void)T_true;
    const auto bad = run_register(base, work / "x.json", {"--init", "affine"});
    EXPECT_NE(bad.exit_code, 0);
    EXPECT_FALSE(fs::exists(work / "x.json"));
    fs::remove_all(work);
}
