// cortexfuse render: a volume, a pose, intrinsics, a transfer function -> PNG.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <iostream>
#include <sstream>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/render/renderer_factory.hpp"

namespace fs = std::filesystem;

namespace cf::cli {

namespace {
struct RenderCmd {
    std::string volume, mask, pose_file, camera_file, tf = "skin", out, depth_out, view = "left", size = "375x250";
    std::string renderer = "cpu";
    double distance_mm = 400, focal_px = 0, sample_mm = 1.0;
    bool grey = false, no_shading = false;
};

std::pair<int, int> parse_size(const std::string& s) {
    int w = 0, h = 0;
    char x = 0;
    std::istringstream in(s);
    if (!(in >> w >> x >> h) || x != 'x' || w < 8 || h < 8 || w > 8192 || h > 8192)
        throw InputError("--size " + s, "expected WIDTHxHEIGHT, each 8..8192");
    return {w, h};
}
}  // namespace

TransferFunction transfer_function_arg(const std::string& name_or_file) {
    if (fs::exists(name_or_file)) return load_transfer_function(name_or_file);
    return preset_transfer_function(name_or_file);
}

void add_render(CLI::App& app) {
    auto o = std::make_shared<RenderCmd>();
    auto* sub = app.add_subcommand("render", "Ray-cast a volume to a PNG");
    sub->add_option("volume", o->volume, "Volume (NIfTI, NRRD, MHA or a DICOM folder)")->required();
    sub->add_option("--out", o->out, "PNG to write")->required();
    sub->add_option("--tf", o->tf, "Transfer function: a preset name or a JSON file")->capture_default_str();
    sub->add_option("--mask", o->mask, "Brain mask: render only inside it");
    sub->add_option("--pose", o->pose_file, "JSON with T_camera_from_world (else --view)");
    sub->add_option("--camera", o->camera_file, "JSON with a \"camera\" object (case.json works; else --size/--focal-px)");
    sub->add_option("--view", o->view, "left, right, anterior, posterior, superior, inferior")->capture_default_str();
    sub->add_option("--distance-mm", o->distance_mm, "Camera distance from the volume centre for --view")->capture_default_str();
    sub->add_option("--size", o->size, "Image size WxH without --camera")->capture_default_str();
    sub->add_option("--focal-px", o->focal_px, "Focal length in pixels without --camera (default: fits the head)");
    sub->add_option("--sample-mm", o->sample_mm, "Sample distance along rays")->capture_default_str();
    sub->add_option("--depth-out", o->depth_out, "Also write the depth of the first opaque hit (16-bit PNG, 0.1 mm units)");
    sub->add_flag("--grey", o->grey, "Write the grey image instead of RGB");
    sub->add_flag("--no-shading", o->no_shading, "Turn Lambert shading off");
    sub->add_option("--renderer", o->renderer, "Ray caster: cpu, gl (EGL/OpenGL, off-screen) or auto (gl if it works, else cpu)")
        ->capture_default_str();
    sub->callback([o] {
        run_guarded("render", [&] {
            const RendererKind kind = parse_renderer_kind(o->renderer);
            const Volume v = load_volume(o->volume);
            LabelVolume mask;
            if (!o->mask.empty()) mask = load_mask(o->mask, v.geom);
            Intrinsics K;
            if (!o->camera_file.empty()) {
                K = parse_camera(read_json_file(o->camera_file), o->camera_file);
            } else {
                const auto [w, h] = parse_size(o->size);
                K.width = w;
                K.height = h;
                K.fx = K.fy = o->focal_px > 0 ? o->focal_px : 0.5 * w * o->distance_mm / 110.0;
                K.cx = (w - 1) * 0.5;
                K.cy = (h - 1) * 0.5;
            }
            const Pose T = !o->pose_file.empty() ? parse_pose(read_json_file(o->pose_file), o->pose_file)
                                                 : standard_view(o->view, v.geom.center_world_mm(), o->distance_mm);
            auto r = make_renderer(kind, v, transfer_function_arg(o->tf), o->mask.empty() ? nullptr : &mask);
            RenderOptions ro;
            ro.sample_distance_mm = o->sample_mm;
            ro.shading = !o->no_shading;
            RenderImage img;
            r->render(K, T, ro, img);
            cv::Mat out;
            if (o->grey) {
                cv::Mat(K.height, K.width, CV_32F, img.grey.data()).convertTo(out, CV_8U, 255.0);
            } else {
                cv::cvtColor(cv::Mat(K.height, K.width, CV_8UC3, img.rgb.data()), out, cv::COLOR_RGB2BGR);
            }
            if (!cv::imwrite(o->out, out)) throw InputError(o->out, "cannot write PNG");
            if (!o->depth_out.empty()) {
                cv::Mat d;
                cv::Mat(K.height, K.width, CV_32F, img.depth_mm.data()).convertTo(d, CV_16U, 10.0);
                if (!cv::imwrite(o->depth_out, d)) throw InputError(o->depth_out, "cannot write PNG");
            }
            return 0;
        });
    });
}

}  // namespace cf::cli
