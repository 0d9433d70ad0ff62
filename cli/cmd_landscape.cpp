// cortexfuse landscape: the similarity along each pose parameter about the true (or landmark)
// pose of a case, as a picture: where the optimiser's target really is.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <optional>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/landmarks.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/render/renderer_factory.hpp"

namespace cf::cli {

namespace {
struct LandscapeCmd {
    std::string case_dir, out, params_file, about = "truth", renderer = "cpu", pose_file, inputs_out;
    double fwhm_mm = 4, range_mm = 10, range_deg = 10;
    int width_px = 190, steps = 41;
};
/// Three panels side by side, each at least 400 px wide: filtered photo, filtered rendering,
/// and the two overlaid, with the pixels the similarity does not count dimmed in all three.
void write_inputs(const Registration::SimilarityInputs& in, const std::string& path) {
    const double scale = std::max(1.0, std::ceil(400.0 / in.photo.cols));
    const cv::Size size(int(in.photo.cols * scale), int(in.photo.rows * scale));
    auto grey8 = [&](const cv::Mat& f) {
        cv::Mat g;
        f.convertTo(g, CV_8U, 255.0);  // the filters leave [0, 1] over the usable pixels
        return g;
    };
    const cv::Mat photo = grey8(in.photo), rendered = grey8(in.rendered);
    cv::Mat overlay;
    cv::merge(std::vector<cv::Mat>{photo, rendered, photo}, overlay);  // BGR: magenta photo, green rendering
    std::vector<cv::Mat> panels;
    for (const cv::Mat& m : {photo, rendered, overlay}) {
        cv::Mat bgr;
        if (m.channels() == 1) cv::cvtColor(m, bgr, cv::COLOR_GRAY2BGR);
        else bgr = m.clone();
        bgr.setTo(cv::Scalar(60, 30, 30), in.usable == 0);  // dark blue-grey: not counted
        cv::resize(bgr, bgr, size, 0, 0, cv::INTER_NEAREST);
        panels.push_back(bgr);
    }
    cv::Mat row;
    cv::hconcat(panels, row);
    cv::Mat img(row.rows + 26, row.cols, CV_8UC3, cv::Scalar(255, 255, 255));
    row.copyTo(img(cv::Rect(0, 26, row.cols, row.rows)));
    char label[160];
    std::snprintf(label, sizeof label, "photo | rendering | overlay (photo magenta, rendering green); similarity %.4f; %dx%d px",
                  in.similarity, in.photo.cols, in.photo.rows);
    cv::putText(img, label, {8, 18}, cv::FONT_HERSHEY_SIMPLEX, 0.5, cv::Scalar(0, 0, 0));
    if (!cv::imwrite(path, img)) throw InputError(path, "cannot write PNG");
}
}  // namespace

void add_landscape(CLI::App& app) {
    auto o = std::make_shared<LandscapeCmd>();
    auto* sub = app.add_subcommand("landscape", "Plot the similarity along each pose parameter about a case's pose");
    sub->add_option("case_dir", o->case_dir, "Case folder")->required();
    sub->add_option("--out", o->out, "PNG to write")->required();
    sub->add_option("--about", o->about, "truth (needs truth.json) or landmarks")->capture_default_str();
    sub->add_option("--pose", o->pose_file,
                    "JSON with T_camera_from_world (a register result, say) to sweep about instead of --about; "
                    "a result's estimated light (light_position_camera_mm, else light_direction_camera) is used too");
    sub->add_option("--params", o->params_file, "Registration parameters (JSON)");
    sub->add_option("--fwhm-mm", o->fwhm_mm, "Blur FWHM at the cortex")->capture_default_str();
    sub->add_option("--width-px", o->width_px, "Working image width")->capture_default_str();
    sub->add_option("--range-mm", o->range_mm, "Translation range +-")->capture_default_str();
    sub->add_option("--range-deg", o->range_deg, "Rotation range +-")->capture_default_str();
    sub->add_option("--steps", o->steps, "Samples per parameter")->capture_default_str();
    sub->add_option("--inputs", o->inputs_out,
                    "Also write a PNG of what the similarity compares at the pose: the filtered photo, the "
                    "filtered rendering, both overlaid (photo magenta, rendering green), unusable pixels dimmed");
    sub->add_option("--renderer", o->renderer, "Ray caster for the similarity: cpu, gl (EGL/OpenGL) or auto")
        ->capture_default_str();
    sub->callback([o] {
        run_guarded("landscape", [&] {
            LoadedCase c = load_case(o->case_dir);
            RegistrationParams params = RegistrationParams::defaults();
            if (!o->params_file.empty()) params = registration_params_from_json(read_json_file(o->params_file), o->params_file);
            params.renderer_factory = renderer_factory(parse_renderer_kind(o->renderer));
            Pose T;
            // The headlight, unless the pose file carries a result's estimated light.
            std::optional<Eigen::Vector3d> light_direction, light_position_mm;
            std::string light = "headlight";
            if (!o->pose_file.empty()) {
                const nlohmann::json pj = read_json_file(o->pose_file);
                T = parse_pose(pj, o->pose_file);
                auto vec3 = [&](const char* key) -> std::optional<Eigen::Vector3d> {
                    if (!pj.contains(key)) return std::nullopt;
                    const auto& a = pj.at(key);
                    if (!a.is_array() || a.size() != 3 || !a[0].is_number() || !a[1].is_number() || !a[2].is_number())
                        throw InputError(o->pose_file, std::string(key) + " must be an array of 3 numbers");
                    const Eigen::Vector3d v(a[0].get<double>(), a[1].get<double>(), a[2].get<double>());
                    if (!v.allFinite()) throw InputError(o->pose_file, std::string(key) + " must be finite");
                    return v;
                };
                light_position_mm = vec3("light_position_camera_mm");
                light_direction = vec3("light_direction_camera");
                // (0, 0, -1) is how a result without an estimate reports the headlight.
                if (light_direction && (*light_direction - Eigen::Vector3d(0, 0, -1)).norm() < 1e-12) light_direction.reset();
                if (light_position_mm) light = "point";
                else if (light_direction) light = "distant";
            } else if (o->about == "truth") {
                if (!c.spec.truth) throw InputError(o->case_dir + "/truth.json", "missing (use --about landmarks)");
                T = c.spec.truth->T_camera_from_world;
            } else if (o->about == "landmarks") {
                T = fit_pose_pnp(c.spec.landmarks, c.spec.camera).T_camera_from_world;
            } else {
                throw InputError("--about " + o->about, "expected truth or landmarks");
            }
            Registration reg(c.volume, c.mask, params);
            StageParams st;
            st.fwhm_mm = o->fwhm_mm;
            st.render_width_px = o->width_px;
            if (!o->inputs_out.empty()) write_inputs(reg.similarity_inputs(c.photo, T, T, st, light_direction, light_position_mm), o->inputs_out);
            const SimilaritySweep sw = reg.sweep(c.photo, T, st, o->range_mm, o->range_deg, o->steps, light_direction, light_position_mm);
            // 3 x 2 panels.
            const int pw = 300, ph = 216, pb = 46, W = pw * 3, H = ph * 2 + 30;  // pb: below the frame
            cv::Mat img(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
            const char* names[6] = {"rx deg", "ry deg", "rz deg", "tx mm", "ty mm", "tz mm"};
            const char* keys[6] = {"rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm"};
            nlohmann::json j = {{"about", o->pose_file.empty() ? o->about : "pose"}, {"fwhm_mm", o->fwhm_mm}, {"width_px", o->width_px},
                                {"metric", params.metric}, {"light", light}};
            for (int p = 0; p < 6; ++p) {
                const auto& xs = sw.offsets[size_t(p)];
                const auto& ys = sw.similarity[size_t(p)];
                const auto [mn, mx] = std::minmax_element(ys.begin(), ys.end());
                const int ox = (p % 3) * pw, oy = 30 + (p / 3) * ph;
                cv::rectangle(img, {ox + 30, oy + 10}, {ox + pw - 10, oy + ph - pb}, cv::Scalar(200, 200, 200));
                auto X = [&](size_t i) { return ox + 30 + int((pw - 40) * double(i) / double(xs.size() - 1)); };
                auto Y = [&](double v) { return oy + ph - pb - int((ph - pb - 10) * (v - *mn) / std::max(*mx - *mn, 1e-9)); };
                // The sample nearest the pose itself (the middle one for an odd --steps).
                size_t at = 0;
                for (size_t i = 1; i < xs.size(); ++i)
                    if (std::abs(xs[i]) < std::abs(xs[at])) at = i;
                cv::line(img, {X(at), oy + 10}, {X(at), oy + ph - pb}, cv::Scalar(0, 0, 220), 1);
                for (size_t i = 1; i < xs.size(); ++i) cv::line(img, {X(i - 1), Y(ys[i - 1])}, {X(i), Y(ys[i])}, cv::Scalar(120, 60, 0), 2);
                const size_t best = size_t(std::max_element(ys.begin(), ys.end()) - ys.begin());
                cv::circle(img, {X(best), Y(ys[best])}, 4, cv::Scalar(0, 150, 0), cv::FILLED);
                char label[96];
                std::snprintf(label, sizeof label, "%s  peak at %+.1f", names[p], xs[best]);
                cv::putText(img, label, {ox + 35, oy + ph - pb + 18}, cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0));
                // The curve's values, so that two cases' landscapes can be compared: each panel is
                // scaled to its own range, and how far the peak stands above the ripple is what
                // says how much the photo shows about that parameter.
                char range[64];
                std::snprintf(range, sizeof range, "%s %.4f .. %.4f", params.metric.c_str(), *mn, *mx);
                cv::putText(img, range, {ox + 35, oy + ph - pb + 34}, cv::FONT_HERSHEY_SIMPLEX, 0.35, cv::Scalar(90, 90, 90));
                // How far the peak stands above the ripple (twenty-first session: tx and ty
                // averaged, about the truth, 0.08-0.34 on every MNI152 case and 0.54-0.93 on the
                // informative heads); the engine's prominence gate takes the same measure.
                const double prominence = peak_prominence(xs, ys);
                j["peak_offsets"].push_back(xs[best]);
                j["axes"][keys[p]] = {{"peak_offset", xs[best]},
                                      {"similarity_peak", *mx},
                                      {"similarity_at_pose", ys[at]},
                                      {"similarity_min", *mn},
                                      {"peak_prominence", prominence},
                                      {"offsets", xs},
                                      {"similarity", ys}};
            }
            const std::string about = o->pose_file.empty() ? "the " + o->about + " pose" : o->pose_file;
            cv::putText(img, params.metric + " about " + about + " (red line), " + light + "; green: peak", {10, 20},
                        cv::FONT_HERSHEY_SIMPLEX, 0.5, cv::Scalar(0, 0, 0));
            if (!cv::imwrite(o->out, img)) throw InputError(o->out, "cannot write PNG");
            std::cout << j.dump() << "\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
