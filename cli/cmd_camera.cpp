// cortexfuse camera: list cameras, take a photo, list and download files on a camera.
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "cortexfuse/core/install_paths.hpp"
#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/drivers/camera.hpp"
#include "cortexfuse/drivers/sim/tracked_camera.hpp"
#include "cortexfuse/drivers/sim/tracker_sim.hpp"

namespace cf::cli {

namespace {

struct CameraOpts {
    std::string backend = "gphoto2", device, out, truth, file, pose;
    std::string sim_size = "750x500";
    // The simulated camera on the tracker simulator's camera tool (docs/camera.md).
    std::string sim_pose = "orbit", sim_trajectory, sim_hand_eye;
    std::uint64_t sim_tracker_seed = 1;
    camera::SimCameraConfig sim;
};

camera::SimCameraConfig sim_config(const CameraOpts& o) {
    camera::SimCameraConfig c = o.sim;
    const auto x = o.sim_size.find_first_of("xX");
    try {
        if (x == std::string::npos) throw std::invalid_argument("x");
        c.width = std::stoi(o.sim_size.substr(0, x));
        c.height = std::stoi(o.sim_size.substr(x + 1));
    } catch (const std::exception&) {
        throw InputError("camera --sim-size", "expected WxH, got \"" + o.sim_size + "\"");
    }
    return c;
}

std::unique_ptr<camera::Camera> open_camera(const CameraOpts& o) {
    auto backend = camera::make_backend(o.backend, sim_config(o));
    std::string id = o.device;
    if (id.empty()) {
        const auto cams = backend->list();
        if (cams.empty()) throw camera::CameraError(o.backend, "no camera found (is it plugged in and switched on?)");
        id = cams[0].id;
    }
    return backend->open(id);
}

/// Writes the photo: the delivered bytes as they are when the extension fits (.jpg for a
/// JPEG, the raw extension for raw), otherwise the decoded image in the format the extension
/// names (.png, .tif, ...). Atomic: temporary file + rename.
void write_photo(const camera::Photo& p, const std::filesystem::path& out) {
    std::string ext = out.extension().string();
    for (auto& ch : ext) ch = char(std::tolower(static_cast<unsigned char>(ch)));
    std::string src = std::filesystem::path(p.name).extension().string();
    for (auto& ch : src) ch = char(std::tolower(static_cast<unsigned char>(ch)));
    const bool jpeg_both = (ext == ".jpg" || ext == ".jpeg") && p.mime == "image/jpeg";
    if (jpeg_both || (!ext.empty() && ext == src)) {
        write_file_atomic(out, std::string(p.bytes.begin(), p.bytes.end()));
        return;
    }
    std::vector<uint8_t> buf;
    bool ok = false;
    try {
        ok = cv::imencode(ext, p.bgr, buf);
    } catch (const cv::Exception&) {
        ok = false;
    }
    if (!ok) throw InputError(out.string(), "cannot encode a photo as \"" + ext + "\" (use .jpg, .png or .tif)");
    write_file_atomic(out, std::string(buf.begin(), buf.end()));
}

}  // namespace

void add_camera(CLI::App& app) {
    auto o = std::make_shared<CameraOpts>();
    o->sim.volume_path = cf::bundled_data_dir(CF_DATA_DIR).string() + "/t1_head_mne_ecog.nii.gz";
    o->sim.mask_path = cf::bundled_data_dir(CF_DATA_DIR).string() + "/brainmask_mne_ecog_binary.nii.gz";
    auto* cmd = app.add_subcommand("camera", "Cameras: list, capture, files, download (gphoto2, v4l2, sim)");
    cmd->require_subcommand(1);
    auto backend_opt = [o](CLI::App* c) {
        c->add_option("--backend", o->backend, "gphoto2 (DSLR over USB), v4l2 (video device) or sim")
            ->capture_default_str()
            ->check(CLI::IsMember({"gphoto2", "v4l2", "sim"}));
        c->add_option("--device", o->device, "camera id from `camera list` (usb:001,004, disk:/folder, /dev/video0, sim:0)");
        c->add_option("--sim-seed", o->sim.seed, "sim: scene seed")->capture_default_str();
        c->add_option("--sim-size", o->sim_size, "sim: sensor size WxH")->capture_default_str();
        c->add_option("--sim-delay-ms", o->sim.capture_delay_ms, "sim: capture latency, ms")->capture_default_str();
        c->add_option("--sim-volume", o->sim.volume_path, "sim: T1 volume of the scene")->capture_default_str();
        c->add_option("--sim-mask", o->sim.mask_path, "sim: brain mask of the volume")->capture_default_str();
    };

    auto* list = cmd->add_subcommand("list", "Cameras present (one JSON object per line)");
    list->add_option("--backend", o->backend, "gphoto2, v4l2, sim or all")->check(CLI::IsMember({"gphoto2", "v4l2", "sim", "all"}));
    list->callback([o] {
        run_guarded("camera list", [o]() -> int {
            const std::vector<std::string> names =
                o->backend == "all" ? std::vector<std::string>{"gphoto2", "v4l2"} : std::vector<std::string>{o->backend};
            for (const auto& n : names)
                for (const auto& c : camera::make_backend(n, o->sim)->list())
                    std::cout << nlohmann::json{{"backend", c.backend}, {"id", c.id}, {"model", c.model},
                                                {"can_capture", c.can_capture}, {"can_stream", c.can_stream}}
                                     .dump()
                              << "\n";
            return 0;
        });
    });

    auto* capture = cmd->add_subcommand("capture", "Take one photo and write it");
    backend_opt(capture);
    capture->add_option("--out", o->out, "photo file: .jpg (as delivered), a raw extension, .png or .tif")->required();
    capture->add_option("--truth", o->truth, "sim: also write the true pose and camera as JSON here");
    capture->add_option("--pose", o->pose, "sim: photograph from this pose (JSON {\"T_camera_from_world\": 4x4})");
    capture->add_option("--sim-pose", o->sim_pose,
                        "sim: orbit (scripted, round the craniotomy) or tracker (from the pose an in-process tracker simulator "
                        "reports for its camera tool CF-CAMERA, composed with --sim-hand-eye and the scene's patient registration)")
        ->check(CLI::IsMember({"orbit", "tracker"}))
        ->capture_default_str();
    capture->add_option("--sim-tracker-seed", o->sim_tracker_seed, "sim, --sim-pose tracker: the tracker simulator's seed")
        ->capture_default_str();
    capture->add_option("--sim-trajectory", o->sim_trajectory,
                        "sim, --sim-pose tracker: tracker simulator trajectory file (`<t_s> <part> tx ty tz qw qx qy qz`, e.g. CF-CAMERA)");
    capture->add_option("--sim-hand-eye", o->sim_hand_eye,
                        "sim, --sim-pose tracker: T_optics_from_tool 'tx ty tz qw qx qy qz' (mm); default: plate on top, lens 45 mm ahead, 30 mm below");
    capture->callback([o] {
        run_guarded("camera capture", [o]() -> int {
            std::optional<Pose> pose;
            if (!o->pose.empty()) {
                if (o->backend != "sim") throw InputError("camera capture --pose", "only the simulated camera can be placed");
                pose = parse_pose(read_json_file(o->pose), o->pose);  // checked before the scene is built
            }
            const bool tracked = o->sim_pose == "tracker";
            if (tracked && o->backend != "sim")
                throw InputError("camera capture --sim-pose", "tracker applies to the simulated camera only (--backend sim)");
            if (tracked && pose) throw InputError("camera capture --sim-pose", "tracker and --pose both place the camera: give one");
            sim::TrackedCameraRig rig;
            std::unique_ptr<sim::TrackerSimulator> tracker;
            if (tracked) {  // checked before the scene is built
                if (!o->sim_hand_eye.empty()) rig.T_optics_from_tool = sim::parse_pose7(o->sim_hand_eye, "camera capture --sim-hand-eye");
                try {
                    sim::TrackerSimConfig tc;
                    tc.camera_tool = true;
                    tc.seed = o->sim_tracker_seed;
                    tc.trajectory_file = o->sim_trajectory;
                    tracker = std::make_unique<sim::TrackerSimulator>(tc);
                } catch (const std::invalid_argument& e) {
                    throw InputError("camera capture --sim-trajectory", e.what());
                }
            }
            auto cam = open_camera(*o);
            if (pose) dynamic_cast<camera::SimCamera&>(*cam).set_pose(pose);
            std::uint32_t frame = 0;
            if (tracked) {
                auto& sc = dynamic_cast<camera::SimCamera&>(*cam);
                try {
                    sim::register_rig_to_view(rig, *tracker, Eigen::Isometry3d(sc.home_pose()));
                    tracker->start();
                    frame = tracker->current_frame();
                    sc.set_pose_source(sim::tracked_camera_pose_source(*tracker, rig));
                } catch (const std::exception& e) {
                    throw InputError("camera capture --sim-pose tracker", e.what());
                }
            }
            const camera::Photo p = cam->capture();
            nlohmann::json truth;  // built before anything is written
            if (!o->truth.empty()) {
                if (!p.T_camera_from_world || !p.intrinsics)
                    throw InputError("camera capture --truth", "only the simulated camera knows its true pose");
                truth = {{"T_camera_from_world", pose_to_json(*p.T_camera_from_world)}, {"camera", camera_to_json(*p.intrinsics)}};
                truth["pose_source"] = tracked ? "tracker" : (pose ? "pose" : "orbit");
                if (tracked) {  // the scene's transforms, frames in the names (docs/camera.md)
                    truth["T_optics_from_tool"] = pose_to_json(rig.T_optics_from_tool.matrix());
                    truth["T_reference_from_image"] = pose_to_json(rig.T_reference_from_image.matrix());
                    truth["tracker_frame_at_capture_start"] = frame;
                }
            }
            write_photo(p, o->out);
            if (!o->truth.empty()) write_file_atomic(o->truth, truth.dump(2) + "\n");
            std::fprintf(stderr, "cortexfuse camera capture: %dx%d %s from %s in %.0f ms -> %s\n", p.bgr.cols, p.bgr.rows,
                         p.mime.c_str(), cam->info().id.c_str(), p.capture_ms, o->out.c_str());
            return 0;
        });
    });

    auto* files = cmd->add_subcommand("files", "List the image files stored on a camera");
    backend_opt(files);
    files->callback([o] {
        run_guarded("camera files", [o]() -> int {
            for (const auto& f : open_camera(*o)->list_files()) std::cout << f << "\n";
            return 0;
        });
    });

    auto* download = cmd->add_subcommand("download", "Download one file from a camera");
    backend_opt(download);
    download->add_option("FILE", o->file, "path on the camera, as `camera files` lists it")->required();
    download->add_option("--out", o->out, "where to write it")->required();
    download->callback([o] {
        run_guarded("camera download", [o]() -> int {
            const camera::Photo p = open_camera(*o)->download(o->file);
            write_photo(p, o->out);
            std::fprintf(stderr, "cortexfuse camera download: %s (%zu bytes, %dx%d%s) -> %s\n", o->file.c_str(), p.bytes.size(),
                         p.bgr.cols, p.bgr.rows, p.raw ? ", raw" : "", o->out.c_str());
            return 0;
        });
    });
}

}  // namespace cf::cli
