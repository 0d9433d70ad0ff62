// cortexfuse overlay: the photo texture-mapped onto the brain surface with a registration
// result; textured mesh (OBJ+MTL+PNG, GLB) and fused pictures.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <unistd.h>
#include <filesystem>
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/fusion.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/plan.hpp"
#include "cortexfuse/core/rasterizer.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/skull_strip.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/render/gl_renderer.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include "progress_bar.hpp"

namespace fs = std::filesystem;

namespace cf::cli {
namespace {

/// A mesh that does not lie on the case's brain (another patient's or another space's
/// surface, a wrong unit): fewer than half of its vertices inside the brain mask's bounding
/// box grown by 10 mm. Throws InputError naming the mesh.
void check_mesh_on_brain(const SurfaceMesh& mesh, const std::string& what, const LabelVolume& mask) {
    const auto& d = mask.geom.dims;
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e18), hi = -lo;
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j)
            for (int i = 0; i < d[0]; ++i)
                if (mask.at(i, j, k)) lo = lo.cwiseMin(Eigen::Vector3d(i, j, k)), hi = hi.cwiseMax(Eigen::Vector3d(i, j, k));
    const Eigen::Vector3d grow = mask.geom.spacing_mm.cwiseInverse() * 10.0;
    lo -= grow, hi += grow;
    const Eigen::Affine3d I = mask.geom.index_from_world();
    size_t in = 0;
    for (const auto& v : mesh.vertices) {
        const Eigen::Vector3d q = I * v.cast<double>();
        in += (q.array() >= lo.array()).all() && (q.array() <= hi.array()).all();
    }
    const double f = mesh.vertices.empty() ? 0.0 : double(in) / double(mesh.vertices.size());
    if (f < 0.5) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "%.1f", f * 100);
        throw InputError(what, std::string("absurd overlap with the case's brain: only ") + buf +
                                   " % of its vertices lie within 10 mm of the brain mask's box (another patient's or "
                                   "another space's surface?)");
    }
}

/// The output folder is written through a staging folder inside it; the files are moved into
/// place only when everything has been made, so a failed run leaves nothing (and removes the
/// folder when it made it).
struct StagedOutput {
    fs::path final_dir, stage;
    bool made_dir = false, done = false;
    explicit StagedOutput(const fs::path& dir) : final_dir(dir) {
        made_dir = !fs::exists(dir);
        fs::create_directories(dir);
        stage = dir / (".overlay.partial." + std::to_string(::getpid()));
        fs::remove_all(stage);
        fs::create_directories(stage);
    }
    void commit() {
        for (const auto& e : fs::directory_iterator(stage)) fs::rename(e.path(), final_dir / e.path().filename());
        done = true;
    }
    ~StagedOutput() {
        std::error_code ec;
        fs::remove_all(stage, ec);
        if (!done && made_dir) fs::remove(final_dir, ec);  // only if empty
    }
};

}  // namespace

void add_overlay(CLI::App& app) {
    struct Opts {
        std::string case_dir, result, out, mesh, tf = "cortex_t1", plan, renderer = "auto";
        double opacity = 0.5, ct_weight = 0.6, fmri_weight = 1.0;
        int view_width = 800, max_triangles = 200000;
        std::vector<double> yaws{-35, 35}, pitches{25};
        std::vector<std::string> cast;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("overlay", "Texture-map the photo onto the brain surface with a registration result; "
                                              "textured OBJ/GLB and fused PNGs");
    cmd->add_option("CASE_DIR", o->case_dir, "case folder (docs/case-format.md)")->required();
    cmd->add_option("RESULT", o->result, "registration result (RESULT.json with T_camera_from_world)")->required();
    cmd->add_option("--out", o->out, "output folder")->required();
    cmd->add_option("--mesh", o->mesh, "brain surface (PLY/VTP/STL/OBJ, LPS mm, e.g. a plan's brain_surface.ply); "
                                       "otherwise built from the case's volume");
    cmd->add_option("--max-triangles", o->max_triangles, "triangle budget when the surface is built here")->capture_default_str();
    cmd->add_option("--opacity", o->opacity, "photo opacity over the volume rendering")->check(CLI::Range(0.0, 1.0))->capture_default_str();
    cmd->add_option("--view-width", o->view_width, "width of the fused pictures, px")->check(CLI::Range(64, 4000))->capture_default_str();
    cmd->add_option("--yaw", o->yaws, "free viewpoints: orbit angles about the vertical, degrees")->capture_default_str();
    cmd->add_option("--pitch", o->pitches, "free viewpoints: orbit angles about the horizontal, degrees")->capture_default_str();
    cmd->add_option("--tf", o->tf, "transfer function preset or JSON file for the volume")->capture_default_str();
    cmd->add_option("--plan", o->plan, "a `cortexfuse plan` folder of this case's T1: its brain surface (unless --mesh) "
                                       "and its CT / fMRI on the T1 grid, fused in the volume rendering");
    cmd->add_option("--renderer", o->renderer, "volume rendering: auto (GL when the plan adds modalities and a GL "
                                               "context can be made, else CPU), cpu or gl")
        ->capture_default_str();
    cmd->add_option("--ct-weight", o->ct_weight, "weight of the plan's CT layer (0 hides it)")
        ->check(CLI::Range(0.0, 1.0))->capture_default_str();
    cmd->add_option("--fmri-weight", o->fmri_weight, "weight of the plan's fMRI layer (0 hides it)")
        ->check(CLI::Range(0.0, 1.0))->capture_default_str();
    cmd->add_option("--cast-back", o->cast, "photo pixel \"u,v\" to cast back onto the surface (repeatable)");
    cmd->callback([o] {
        run_guarded("overlay", [o]() -> int {
            const auto t0 = std::chrono::steady_clock::now();
            const RendererKind kind = parse_renderer_kind(o->renderer);
            const CaseSpec cs = read_case(o->case_dir);
            const Pose T = parse_pose(read_json_file(o->result), o->result);
            std::vector<Eigen::Vector2d> cast_px;
            for (const auto& s : o->cast) {
                double u, v;
                char comma;
                std::istringstream in(s);
                if (!(in >> u >> comma >> v) || comma != ',') throw InputError("--cast-back " + s, "expected \"u,v\"");
                cast_px.emplace_back(u, v);
            }
            const cv::Mat photo = load_photo(cs.photo_path);
            Intrinsics K = cs.camera;
            if (photo.cols != K.width || photo.rows != K.height) K = K.resized(photo.cols, photo.rows);
            const Volume vol = load_volume(cs.volume_path);
            ProgressBar bar("overlay");
            LabelVolume mask;
            if (cs.brain_mask_path) {
                mask = load_mask(*cs.brain_mask_path);
                if (!mask.geom.same_grid(vol.geom)) throw InputError(cs.brain_mask_path->string(), "not on the volume's grid");
            } else {
                mask = skull_strip(vol, {}, &bar.progress());
            }
            if (mask.count_nonzero() == 0)
                throw InputError(cs.brain_mask_path ? cs.brain_mask_path->string() : cs.volume_path.string() + " (skull strip)",
                                 "the brain mask is empty: no brain to draw or to map the photo onto");
            // The plan's extra modalities, all on the plan's T1 grid, which must be the case's.
            struct Layer {
                std::string name;
                Volume volume;
                TransferFunction tf;
                double weight;
            };
            std::vector<Layer> extra;
            const fs::path plan(o->plan);
            if (!o->plan.empty()) {
                if (!fs::is_directory(plan)) throw InputError(o->plan, "--plan: not a folder");
                const fs::path pm = plan / "brain_mask.nii.gz";
                if (fs::exists(pm)) {
                    const LabelVolume plan_mask = load_mask(pm);
                    if (!plan_mask.geom.same_grid(vol.geom))
                        throw InputError(o->plan, "the plan was made from another T1 (its grid differs from the case volume's "
                                                  "grid): plan the case's own volume");
                    if (plan_mask.count_nonzero() == 0) throw InputError(pm.string(), "the plan's brain mask is empty");
                }
                // Another patient's T1 on an identical grid: plan.json keeps the T1's fingerprint.
                if (fs::exists(plan / "plan.json")) {
                    const nlohmann::json pj = read_json_file(plan / "plan.json");
                    if (pj.contains("t1_fingerprint") && pj["t1_fingerprint"].is_string() &&
                        pj["t1_fingerprint"].get<std::string>() != volume_fingerprint(vol))
                        throw InputError(o->plan, "the plan was made from another T1 (its voxels differ from the case "
                                                  "volume's: another patient's or another scan's plan): plan the case's own volume");
                }
                if (fs::exists(plan / "ct_on_t1.nii.gz") && o->ct_weight > 0)
                    extra.push_back({"ct", load_volume(plan / "ct_on_t1.nii.gz"), preset_transfer_function("ct_bone"),
                                     o->ct_weight});
                if (fs::exists(plan / "fmri_on_t1.nii.gz") && o->fmri_weight > 0) {
                    const fs::path tfp = plan / "fmri_transfer_function.json";
                    extra.push_back({"fmri", load_volume(plan / "fmri_on_t1.nii.gz"),
                                     fs::exists(tfp) ? load_transfer_function(tfp) : preset_transfer_function("fmri_hot"),
                                     o->fmri_weight});
                }
                for (const auto& L : extra) {
                    if (!L.volume.geom.same_grid(vol.geom))
                        throw InputError((plan / (L.name + "_on_t1.nii.gz")).string(),
                                         "not on the case volume's grid (the plan was made from another T1)");
                    const bool any = std::any_of(L.volume.voxels.begin(), L.volume.voxels.end(),
                                                 [&](float v) { return L.name == "ct" ? v > -1000.f : v != 0.f; });
                    if (!any)
                        throw InputError((plan / (L.name + "_on_t1.nii.gz")).string(),
                                         L.name == "ct" ? "empty: the CT holds only air (-1000 HU) on the T1 grid"
                                                        : "empty: no active voxel on the T1 grid");
                }
            }
            SurfaceMesh mesh;
            const std::string mesh_path =
                !o->mesh.empty() ? o->mesh
                                 : (!o->plan.empty() && fs::exists(plan / "brain_surface.ply") ? (plan / "brain_surface.ply").string()
                                                                                              : std::string());
            if (!mesh_path.empty()) {
                mesh = load_mesh(mesh_path);
            } else {
                SurfaceParams sp;
                sp.max_triangles = o->max_triangles;
                mesh = build_brain_surface(vol, mask, sp, bar.progress());
            }
            check_mesh_on_brain(mesh, mesh_path.empty() ? std::string("brain surface (built from the case volume)") : mesh_path,
                                mask);
            const cv::Mat alpha = cs.roi ? roi_mask(*cs.roi, photo.cols, photo.rows) : cv::Mat();
            TextureMapping tm;
            try {
                tm = map_texture(mesh, K, T, alpha);
            } catch (const InputError& e) {
                // Name the file the pose came from, not just "result pose".
                if (e.input() == "result pose") throw InputError(o->result, std::string(e.what()).substr(e.input().size() + 2));
                throw;
            }
            Eigen::Vector3d pivot = Eigen::Vector3d::Zero();
            size_t np = 0;
            for (size_t i = 0; i < mesh.vertices.size(); ++i)
                if (tm.in_roi[i]) pivot += mesh.vertices[i].cast<double>(), ++np;
            if (np == 0)
                throw InputError(cs.roi_path ? cs.roi_path->string() : o->result,
                                 "no visible surface inside the ROI with this pose (wrong result or ROI?)");
            pivot /= double(np);
            const cv::Mat tex = texture_rgba(photo, alpha);
            StagedOutput staged(o->out);
            const fs::path out = staged.stage;
            write_textured_obj(mesh, tm, tex, out / "textured_surface.obj");
            write_textured_glb(mesh, tm, tex, out / "textured_surface.glb");

            // Fused pictures: from the camera's pose and orbiting about the exposed cortex.
            TransferFunction tf = fs::exists(o->tf) ? load_transfer_function(o->tf) : preset_transfer_function(o->tf);
            // The volume rendering: the T1 alone on the CPU ray caster (the reference), or the
            // plan's modalities fused in one GL ray-casting pass (the CPU caster draws one layer).
            std::unique_ptr<Renderer> renderer;
            std::vector<std::string> drawn{"t1"};
            std::string fallback_note;
            if (!extra.empty() && kind != RendererKind::cpu) {
                try {
                    auto fr = make_gl_fusion_renderer();
                    fr->add_layer(vol, tf, &mask);
                    for (const auto& L : extra) {
                        LabelVolume keep;
                        if (L.name == "ct") keep = craniotomy_keep_mask(L.volume.geom, mesh, K, T, alpha, 3.0);
                        LayerSettings ls;
                        ls.weight = L.weight;
                        fr->add_layer(L.volume, L.tf, L.name == "ct" ? &keep : nullptr, ls);
                        drawn.push_back(L.name);
                    }
                    renderer = std::move(fr);
                } catch (const GlError& e) {
                    if (kind == RendererKind::gl) throw;
                    drawn.assign(1, "t1");
                    fallback_note = std::string("GL unavailable (") + e.what() + ")";
                }
            }
            if (!renderer && !extra.empty()) {
                std::string names;
                for (const auto& L : extra) names += (names.empty() ? "" : ", ") + L.name;
                std::cerr << "overlay: note: the CPU renderer cannot fuse modalities; only the T1 is drawn (" << names
                          << " of the plan left out" << (fallback_note.empty() ? "" : ": " + fallback_note) << ")\n";
            }
            if (!renderer) {
                if (kind == RendererKind::gl) renderer = make_renderer(kind, vol, tf, &mask);
                else renderer = make_cpu_renderer(vol, tf, &mask);
            }
            const double s = std::min(1.0, double(o->view_width) / K.width);
            const Intrinsics Kv = K.scaled(s);
            nlohmann::json views = nlohmann::json::array();
            auto view = [&](const std::string& name, const Pose& Tv) {
                const cv::Mat img = render_fused(*renderer, mesh, tm, tex, Kv, Tv, o->opacity);
                const fs::path f = out / (name + ".png");
                if (!cv::imwrite(f.string(), img)) throw InputError(f.string(), "cannot write");
                views.push_back({{"file", f.filename().string()}, {"T_camera_from_world", pose_to_json(Tv)}});
            };
            view("fused_camera", T);
            for (double y : o->yaws) view("fused_yaw" + std::to_string(int(std::lround(y))), orbit_pose(T, pivot, y, 0));
            for (double p : o->pitches) view("fused_pitch" + std::to_string(int(std::lround(p))), orbit_pose(T, pivot, 0, p));

            nlohmann::json casts = nlohmann::json::array();
            for (const auto& px : cast_px) {
                const auto h = cast_back(mesh, K, T, px);
                if (h)
                    casts.push_back({{"pixel", {px.x(), px.y()}},
                                     {"p_world_mm", {h->p_world_mm.x(), h->p_world_mm.y(), h->p_world_mm.z()}},
                                     {"depth_mm", h->depth_mm}});
                else
                    casts.push_back({{"pixel", {px.x(), px.y()}}, {"p_world_mm", nullptr}});
            }
            const nlohmann::json j = {{"format", "cortexfuse-overlay/1"},
                                      {"case", o->case_dir},
                                      {"result", o->result},
                                      {"mesh", mesh_path.empty() ? "built from the case volume" : mesh_path},
                                      {"plan", o->plan.empty() ? nlohmann::json(nullptr) : nlohmann::json(o->plan)},
                                      {"renderer", renderer->name()},
                                      {"modalities", drawn},
                                      {"vertices", mesh.vertices.size()},
                                      {"triangles", mesh.triangles.size()},
                                      {"visible_vertices", tm.visible_count},
                                      {"roi_vertices", tm.roi_count},
                                      {"back_facing", tm.back_facing},
                                      {"occluded", tm.occluded},
                                      {"outside_image", tm.outside_image},
                                      {"opacity", o->opacity},
                                      {"textured_obj", "textured_surface.obj"},
                                      {"textured_glb", "textured_surface.glb"},
                                      {"views", views},
                                      {"cast_back", casts},
                                      {"seconds", std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()}};
            write_file_atomic(out / "overlay.json", j.dump(1));
            staged.commit();
            std::cout << "overlay: " << tm.visible_count << " visible vertices, " << tm.roi_count << " in the ROI -> " << o->out
                      << "\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
