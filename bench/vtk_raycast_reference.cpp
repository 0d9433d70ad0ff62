// vtk_raycast_reference: VTK's volume ray casters on exactly the frames that
// `cortexfuse bench render` times, for a like-for-like ratio in one run
// (bench/render_vs_vtk.sh).
//
// Matched to our CPU ray caster (core/src/raycast_cpu.cpp):
//  - the same volume, quantised the same way: intensities over the robust range (inside the
//    mask) mapped to 0..4095 as unsigned short, 0 outside the mask; the transfer function's
//    piecewise-linear points put on that scale, so both look up the same table values;
//  - opacity per mm (ScalarOpacityUnitDistance 1 mm), the same sample distance, no image
//    subsampling, no automatic sample adjustment, no jitter;
//  - Lambert shading from a headlight (ambient 0.2, diffuse 0.8, no specular);
//  - the same pinhole camera (view angle from fy, principal point at the image centre) along
//    the same camera path (cortexfuse::bench::bench_pose), the same thread count
//    (SetNumberOfThreads for the fixed-point mapper, LP_NUM_THREADS for Mesa llvmpipe);
//  - time per frame = Render() + reading the image back into memory.
//
// The volume is given to VTK in "index times spacing" coordinates (origin 0, no direction)
// and the camera is moved into that frame, so oblique volumes need neither the image data's
// direction matrix (which not every VTK mapper honours) nor resampling. A direction with
// determinant -1 (a mirrored grid) is made proper by flipping the i axis of the data.
//
// Debian's VTK renders through X only: run under xvfb-run -a -s "-screen 0 1920x1080x24".
#include <vtkCamera.h>
#include <vtkColorTransferFunction.h>
#include <vtkFixedPointVolumeRayCastMapper.h>
#include <vtkGPUVolumeRayCastMapper.h>
#include <vtkImageData.h>
#include <vtkNew.h>
#include <vtkPiecewiseFunction.h>
#include <vtkPointData.h>
#include <vtkRenderWindow.h>
#include <vtkRenderer.h>
#include <vtkSmartPointer.h>
#include <vtkUnsignedCharArray.h>
#include <vtkUnsignedShortArray.h>
#include <vtkVolume.h>
#include <vtkVolumeProperty.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <thread>

#include "cortexfuse/bench/bench.hpp"
#include "cortexfuse/core/error.hpp"

namespace {

using Clock = std::chrono::steady_clock;

struct Options {
    std::string volume = std::string(CF_DATA_DIR) + "/t1_head_mne_ecog.nii.gz";
    std::string mask, size = "375x250", tf = "skin", mapper = "fixedpoint", save_frame;
    int frames = 30, warmup = 5, threads = 0;
    double sample_mm = 1.0;
    bool json = false, no_shading = false;
};

// The volume quantised as our ray caster does it, in VTK's index-times-spacing frame.
struct VtkVolume {
    vtkSmartPointer<vtkImageData> image;
    Eigen::Matrix4d world_from_vtk = Eigen::Matrix4d::Identity();
};

VtkVolume make_vtk_volume(const cf::Volume& v, const cf::LabelVolume* mask, double lo, double hi) {
    const auto& g = v.geom;
    const auto& d = g.dims;
    const bool flip = g.direction.determinant() < 0;  // VTK's camera cannot mirror: flip i instead
    auto img = vtkSmartPointer<vtkImageData>::New();
    img->SetDimensions(d[0], d[1], d[2]);
    img->SetSpacing(g.spacing_mm.x(), g.spacing_mm.y(), g.spacing_mm.z());
    img->SetOrigin(0, 0, 0);
    vtkNew<vtkUnsignedShortArray> arr;
    arr->SetNumberOfComponents(1);
    arr->SetNumberOfTuples(vtkIdType(g.voxel_count()));
    arr->SetName("q");
    unsigned short* out = arr->GetPointer(0);
    const double s = (cf::bench::kQuantLevels - 1) / (hi - lo);
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j)
            for (int i = 0; i < d[0]; ++i) {
                const size_t src = g.linear(i, j, k);
                const size_t dst = g.linear(flip ? d[0] - 1 - i : i, j, k);
                // The same arithmetic as CpuRenderer's constructor (truncation included).
                double x = (double(v.voxels[src]) - lo) * s;
                if (mask && !mask->voxels[src]) x = 0;
                out[dst] = static_cast<unsigned short>(std::clamp(x, 0.0, double(cf::bench::kQuantLevels - 1)));
            }
    img->GetPointData()->SetScalars(arr);
    VtkVolume r;
    r.image = img;
    // p_world = D * (p_vtk / spacing) * spacing + origin; with the flip, i -> (n-1) - i.
    Eigen::Matrix3d D = g.direction;
    Eigen::Vector3d o = g.origin_mm;
    if (flip) {
        o += D.col(0) * g.spacing_mm.x() * double(d[0] - 1);
        D.col(0) = -D.col(0);
    }
    r.world_from_vtk.topLeftCorner<3, 3>() = D;
    r.world_from_vtk.topRightCorner<3, 1>() = o;
    return r;
}

// Transfer-function x (normalized or absolute units) -> quantised units.
double to_q(const cf::TransferFunction& tf, double x, double lo, double hi) {
    const double units = tf.normalized ? lo + x * (hi - lo) : x;
    return (units - lo) * (cf::bench::kQuantLevels - 1) / (hi - lo);
}

void set_camera(vtkCamera* cam, const cf::Intrinsics& K, const cf::Pose& T_camera_from_world,
                const Eigen::Matrix4d& world_from_vtk) {
    const Eigen::Matrix4d T = T_camera_from_world * world_from_vtk;  // camera from VTK frame
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    const Eigen::Vector3d c = -R.transpose() * T.topRightCorner<3, 1>();  // camera centre
    const Eigen::Vector3d z = R.row(2).transpose(), y = R.row(1).transpose();
    // Our pinhole looks along +z with +y down; VTK's up is -y. The focal point sits at the
    // volume's distance so that VTK's clipping and LOD heuristics see a sensible scene.
    const double dist = cf::bench::kBenchDistanceMm;
    cam->SetPosition(c.x(), c.y(), c.z());
    cam->SetFocalPoint(c.x() + dist * z.x(), c.y() + dist * z.y(), c.z() + dist * z.z());
    cam->SetViewUp(-y.x(), -y.y(), -y.z());
    cam->SetViewAngle(2.0 * std::atan(0.5 * K.height / K.fy) * 180.0 / M_PI);
    cam->SetClippingRange(std::max(1.0, dist - 300.0), dist + 300.0);
}

int run(const Options& o) {
    const auto [w, h] = cf::bench::parse_size(o.size);
    if (o.frames < 1) throw cf::InputError("--frames " + std::to_string(o.frames), "must be at least 1");
    if (o.warmup < 0) throw cf::InputError("--warmup " + std::to_string(o.warmup), "must be 0 or more");
    if (o.threads < 0) throw cf::InputError("--threads " + std::to_string(o.threads), "must be 0 (all cores) or more");
    if (!(o.sample_mm >= 0.05 && o.sample_mm <= 10))
        throw cf::InputError("--sample-mm " + std::to_string(o.sample_mm), "must lie in 0.05..10 mm");
    if (o.mapper != "fixedpoint" && o.mapper != "gpu")
        throw cf::InputError("--mapper " + o.mapper, "unknown mapper (known: fixedpoint, gpu)");
    const int threads = o.threads > 0 ? o.threads : int(std::max(1u, std::thread::hardware_concurrency()));
    // Mesa llvmpipe reads its thread count when the context is made (the GPU mapper's "GPU").
    if (o.mapper == "gpu") setenv("LP_NUM_THREADS", std::to_string(threads).c_str(), 0);
    const cf::TransferFunction tf = cf::bench::transfer_function_arg(o.tf);
    tf.validate(o.tf);

    const cf::Volume v = cf::load_volume(o.volume);
    std::optional<cf::LabelVolume> mask;
    if (!o.mask.empty()) {
        mask = cf::load_mask(o.mask);
        if (!mask->geom.same_grid(v.geom)) mask = cf::resample_nearest(*mask, v.geom);
    }
    const auto t_prep = Clock::now();
    const auto range = cf::bench::bench_quantised_range(v, mask ? &*mask : nullptr);
    const double lo = range[0], hi = range[1];
    const VtkVolume vv = make_vtk_volume(v, mask ? &*mask : nullptr, lo, hi);

    vtkNew<vtkColorTransferFunction> colour;
    for (const auto& p : tf.colour) colour->AddRGBPoint(to_q(tf, p[0], lo, hi), p[1], p[2], p[3]);
    vtkNew<vtkPiecewiseFunction> opacity;
    for (const auto& p : tf.opacity) opacity->AddPoint(to_q(tf, p[0], lo, hi), p[1]);
    vtkNew<vtkVolumeProperty> prop;
    prop->SetColor(colour);
    prop->SetScalarOpacity(opacity);
    prop->SetScalarOpacityUnitDistance(1.0);  // opacity per mm, as ours
    if (!tf.gradient_opacity.empty()) {
        // Ours: x in normalized units per mm; VTK: scalar units per world unit (approximate match).
        vtkNew<vtkPiecewiseFunction> gop;
        const double scale = tf.normalized ? (cf::bench::kQuantLevels - 1) : (cf::bench::kQuantLevels - 1) / (hi - lo);
        for (const auto& p : tf.gradient_opacity) gop->AddPoint(p[0] * scale, p[1]);
        prop->SetGradientOpacity(gop);
    }
    prop->SetInterpolationTypeToLinear();
    prop->SetShade(o.no_shading ? 0 : 1);
    prop->SetAmbient(0.2);
    prop->SetDiffuse(0.8);
    prop->SetSpecular(0.0);

    vtkSmartPointer<vtkVolumeMapper> mapper;
    if (o.mapper == "fixedpoint") {
        auto m = vtkSmartPointer<vtkFixedPointVolumeRayCastMapper>::New();
        m->SetNumberOfThreads(threads);
        m->SetSampleDistance(float(o.sample_mm));
        m->SetInteractiveSampleDistance(float(o.sample_mm));
        m->SetImageSampleDistance(1.0f);
        m->SetMinimumImageSampleDistance(1.0f);
        m->SetMaximumImageSampleDistance(1.0f);
        m->SetAutoAdjustSampleDistances(0);
        m->SetLockSampleDistanceToInputSpacing(0);
        m->SetIntermixIntersectingGeometry(0);
        mapper = m;
    } else {
        auto m = vtkSmartPointer<vtkGPUVolumeRayCastMapper>::New();
        m->SetSampleDistance(float(o.sample_mm));
        m->SetImageSampleDistance(1.0f);
        m->SetMinimumImageSampleDistance(1.0f);
        m->SetMaximumImageSampleDistance(1.0f);
        m->SetAutoAdjustSampleDistances(0);
        m->SetLockSampleDistanceToInputSpacing(0);
        m->SetUseJittering(0);
        mapper = m;
    }
    mapper->SetInputData(vv.image);
    mapper->SetBlendModeToComposite();
    vtkNew<vtkVolume> volume;
    volume->SetMapper(mapper);
    volume->SetProperty(prop);

    vtkNew<vtkRenderer> ren;
    ren->SetBackground(0, 0, 0);
    ren->AddVolume(volume);
    ren->SetAutomaticLightCreation(1);  // one headlight, as ours
    vtkNew<vtkRenderWindow> win;
    win->SetOffScreenRendering(1);
    win->SetSize(w, h);
    win->SetMultiSamples(0);
    win->AddRenderer(ren);
    win->Render();  // makes the context
    if (o.mapper == "gpu") {
        auto* gm = vtkGPUVolumeRayCastMapper::SafeDownCast(mapper);
        if (!gm->IsRenderSupported(win, prop))
            throw cf::InputError("--mapper gpu", "vtkGPUVolumeRayCastMapper cannot render in this OpenGL context");
    }
    const double prepare_ms = std::chrono::duration<double, std::milli>(Clock::now() - t_prep).count();

    const cf::Intrinsics K = cf::bench::bench_intrinsics(w, h);
    vtkNew<vtkUnsignedCharArray> pixels;
    std::vector<double> ms;
    double nonblack = 0;
    for (int i = 0; i < o.warmup + o.frames; ++i) {
        set_camera(ren->GetActiveCamera(), K, cf::bench::bench_pose(v.geom, i), vv.world_from_vtk);
        const auto t0 = Clock::now();
        win->Render();
        // After Render() the finished frame is in the displayed (front) buffer.
        win->GetPixelData(0, 0, w - 1, h - 1, 1, pixels);
        const double dt = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
        if (i < o.warmup) continue;
        ms.push_back(dt);
        if (i == o.warmup) {
            // VTK's rows run bottom-up; ours top-down.
            cv::Mat rgb(h, w, CV_8UC3, pixels->GetPointer(0));
            cv::Mat bgr;
            cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
            cv::flip(bgr, bgr, 0);
            cv::Mat grey;
            cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
            nonblack = double(cv::countNonZero(grey > 8)) / double(grey.total());
            if (!o.save_frame.empty() && !cv::imwrite(o.save_frame, bgr))
                throw cf::InputError(o.save_frame, "cannot write PNG");
        }
    }
    const auto s = cf::bench::stats(ms);
    nlohmann::json j = {{"mode", "render"},
                        {"renderer", o.mapper == "fixedpoint" ? "vtkFixedPointVolumeRayCastMapper" : "vtkGPUVolumeRayCastMapper"},
                        {"mapper", o.mapper},
                        {"volume", o.volume},
                        {"dims", v.geom.dims},
                        {"mask", o.mask},
                        {"size", o.size},
                        {"tf", o.tf},
                        {"shading", !o.no_shading},
                        {"sample_mm", o.sample_mm},
                        {"threads", threads},
                        {"frames", o.frames},
                        {"warmup", o.warmup},
                        {"prepare_ms", prepare_ms},
                        {"nonblack_fraction", nonblack},
                        {"ms_per_frame_median", s.median},
                        {"ms_per_frame_p90", s.p90},
                        {"ms_per_frame_min", s.min},
                        {"ms_per_frame_mean", s.mean},
                        {"peak_rss_mb", cf::bench::peak_rss_mb()}};
    std::cout << (o.json ? j.dump() : j.dump(2)) << "\n";
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    Options o;
    CLI::App app{"VTK volume ray casting on the frames `cortexfuse bench render` times (run under xvfb-run)"};
    app.add_option("--volume", o.volume, "Volume (NIfTI, NRRD, MHA or a DICOM folder)")->capture_default_str();
    app.add_option("--mask", o.mask, "Render only inside this mask");
    app.add_option("--size", o.size, "Image size WxH")->capture_default_str();
    app.add_option("--tf", o.tf, "Transfer function: a preset name or a JSON file")->capture_default_str();
    app.add_option("--mapper", o.mapper, "fixedpoint (vtkFixedPointVolumeRayCastMapper) or gpu (vtkGPUVolumeRayCastMapper)")
        ->capture_default_str();
    app.add_option("--frames", o.frames, "Timed frames")->capture_default_str();
    app.add_option("--warmup", o.warmup, "Untimed frames first")->capture_default_str();
    app.add_option("--threads", o.threads, "Threads (0: all cores)")->capture_default_str();
    app.add_option("--sample-mm", o.sample_mm, "Sample distance along rays, mm")->capture_default_str();
    app.add_flag("--no-shading", o.no_shading, "Turn shading off");
    app.add_option("--save-frame", o.save_frame, "Write the first timed frame as PNG");
    app.add_flag("--json", o.json, "One line of JSON");
    CLI11_PARSE(app, argc, argv);
    try {
        return run(o);
    } catch (const std::exception& e) {
        std::cerr << "vtk_raycast_reference: error: " << e.what() << "\n";
        return 1;
    }
}
