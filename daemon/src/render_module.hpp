#pragma once
// The render module: one thread that owns the MRI, its brain mask and the renderers (GL when
// renderer.kind allows and a context can be made, else the CPU ray caster: a GL context is
// bound to the thread that made it, so every render runs on this thread). Requests from the
// HTTP/WebSocket threads are queued to it and answered through a future.
//
// Thread contract: start()/stop() from the daemon's main thread; render() and status_json()
// from any thread (render() blocks the caller until the image is ready).
#include <condition_variable>
#include <deque>
#include <functional>
#include <future>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/daemon/config.hpp"

namespace cf::daemon {

struct LoadedCaseVolume;

/// A case's stored volume for a per-case view (POST /api/render with case_id, the pick, the
/// fused view): `key` names its content (volume and mask hashes); `load` gives the loaded volume
/// and its brain mask and is called on the render thread only when no renderer for `key` is
/// prepared (the render thread keeps the prepared renderers of the last
/// RenderModule::kCaseRenderersCached keys, least recently used dropped first).
struct CaseRenderSource {
    std::string key;
    std::string source;  ///< "case 3 volume 7 (T1)": the answer's X-Render-Volume header
    std::function<std::shared_ptr<const LoadedCaseVolume>()> load;
};

/// One layer of a multimodal render (request field `modalities`): the case's T1 or a plan
/// volume on the T1's grid, with its own transfer function, weight and visibility. Settings
/// change without the layer's volume being uploaded again.
struct ModalityLayerSource {
    std::string name;  ///< "t1", "ct", "fmri"
    std::shared_ptr<const CaseRenderSource> volume;
};

struct RenderedImage {
    std::string bytes;  ///< encoded JPEG or PNG
    std::string mime;
    int width = 0, height = 0;
    double render_ms = 0, encode_ms = 0;
    std::string backend;
};

/// The case's textured brain surface for a fused view (POST /api/cases/{id}/fused), gathered
/// from the case store by the caller; the render thread loads and caches what it names.
/// `*_bytes` read the stored files (called on the render thread only when the key is not cached).
struct FusedSource {
    std::shared_ptr<const CaseRenderSource> volume;  ///< the case's T1 and brain mask
    std::string surface_key, texture_key;            ///< sha256 of the surface; texture: photo+roi+pose
    std::function<std::string()> surface_ply_bytes, photo_bytes;
    nlohmann::json photo_intrinsics;  ///< case.json camera of the photo
    nlohmann::json roi;               ///< roi.json, or null (then the whole visible surface is textured)
    Pose T_registered;                ///< the registration's T_camera_from_world (texture mapping)
    std::string scratch_dir;          ///< where volume files are staged for the readers (removed after)
};

/// A volume's geometry as GET /api/render/volume answers it (centre, LPS box, dims, spacing,
/// and `brain`: the mask's box, null without one).
nlohmann::json volume_geometry_json(const Volume& volume, const LabelVolume* brain_mask);

class RenderModule {
public:
    explicit RenderModule(const DaemonConfig& c);
    ~RenderModule();
    /// Starts the thread; the volume loads on it (status "loading" until then).
    void start();
    void stop();
    /// Validates the request (ApiError 400 naming the field), waits for the volume, renders.
    /// Request fields: width, height (16..renderer.max_*), preset (transfer function preset
    /// name) or tf (a custom transfer function, core's JSON shape), opacity (0..1, scales the preset's opacity), brain_only (bool: hide all but the
    /// brain mask; default true for cortex_t1 and surface_white), view ("left", "right",
    /// "anterior", "posterior", "superior", "inferior") and distance_mm, or T_camera_from_world
    /// (4x4 rows, LPS mm -> camera mm); camera (intrinsics JSON as in case.json) or focal_px;
    /// format "jpeg" | "png"; quality (10..100); stream (the client's stream of views: a newer
    /// queued view of the same stream makes this one answer ApiError 409 `superseded`, before it
    /// is drawn or between its bands; see render_in_bands).
    /// With `src`: the case's volume instead of data.t1 (brain_only: its brain mask, when it has
    /// one). `request` may also hold `modalities` (with `layers`: one per named modality, [0]
    /// is the reference t1): [{name, preset | tf, weight, visible}], rendered in one pass by the
    /// GL fusion renderer (ApiError 409 with the CPU renderer; 400 naming the bad entry).
    RenderedImage render(const nlohmann::json& request, std::shared_ptr<const CaseRenderSource> src = nullptr,
                         std::vector<ModalityLayerSource> layers = {});
    /// The world point under a pixel of the view `request` describes (the same fields as
    /// render(), plus `pixel`: [u, v], OpenCV pixel of that view): the camera-frame depth of the
    /// first opaque hit at the pixel (the renderer's depth output; the last render's when its
    /// view is the same), back-projected through the view's camera. Answers {pixel, p_world_mm,
    /// depth_mm, reused_render, renderer}. ApiError 400 for a bad request or a pixel outside the
    /// image, 422 when the ray hits no surface, 503 without a volume.
    nlohmann::json pick(const nlohmann::json& request, std::shared_ptr<const CaseRenderSource> src = nullptr);
    /// A view of a stream (request field `stream`) larger than twice this is drawn in bands of
    /// about this many pixels, so that a newer view of the stream waits at most one band (64k
    /// pixels: a drag during a 930x562 refine showed its preview after 198 ms median on llvmpipe).
    static constexpr int kBandPixels = 24576;
    /// Prepared per-case renderers kept on the render thread.
    static constexpr std::size_t kCaseRenderersCached = 2;
    /// Volumes uploaded to multimodal (fusion) renderers so far: a TF, weight or visibility
    /// change must not add to it (FusionRenderer::volume_uploads summed over the scenes made).
    std::uint64_t fusion_volume_uploads() const;
    /// Per-case renderer preparations so far (volume loaded and quantised for a renderer).
    std::uint64_t case_preparations() const;
    /// The case's volume (src) rendered like render() with its photo-textured brain surface
    /// blended over it at `surface_opacity` (request field, 0..1, default 0.5) times the ROI's
    /// alpha, composited by depth (core's render_fused). With `layers` (request field
    /// `modalities`, as render()): the volume pass is the multimodal scene of those layers (GL
    /// fusion renderer; ApiError 409 with the CPU renderer) and the surface is composited by the
    /// depth of its first opaque hit. ApiError 400/422/503 as render().
    RenderedImage fused(const nlohmann::json& request, std::shared_ptr<const FusedSource> src,
                        std::vector<ModalityLayerSource> layers = {});
    /// The loaded MRI's geometry for clients that place their own camera: centre (the standard
    /// views' target) and box in LPS mm, dims, spacing, and the brain mask's box (`brain`, null
    /// without a mask). ApiError 503 while loading or after a failed load.
    nlohmann::json volume_json() const;
    nlohmann::json status_json() const;
    bool healthy() const;
    /// renderer.max_width / max_height: the largest view a request may ask for.
    int max_width() const { return cfg_.render_max_width; }
    int max_height() const { return cfg_.render_max_height; }

private:
    struct Job;
    struct Scene;
    std::shared_ptr<Job> parse_job(const nlohmann::json& request, const std::vector<std::string>& extra_fields) const;
    void parse_layers(Job& job, const nlohmann::json& request, const std::vector<ModalityLayerSource>& layers) const;
    void enqueue(const std::shared_ptr<Job>& job);
    /// True when a newer job of `job`'s stream is queued (mu_ held; never for picks or without a stream).
    bool superseded_locked(const Job& job) const;
    static ApiError superseded_error(const Job& job);
    /// `r.render` of the whole view, or, for a view of a stream of at least 2 * kBandPixels, in
    /// bands of rows (the same pixels), giving up between bands with ApiError 409 `superseded`
    /// when a newer job of the stream is queued (the render thread is then free for it).
    void render_in_bands(Renderer& r, const Intrinsics& K, const Pose& T, const RenderOptions& ro, RenderImage& img, const Job& job);
    void loop();
    DaemonConfig cfg_;
    std::thread thread_;
    mutable std::mutex mu_;
    std::condition_variable cv_;
    std::deque<std::shared_ptr<Job>> queue_;
    bool stop_ = false;
    std::string state_ = "stopped";  // stopped, loading, ready, failed
    std::string error_;
    nlohmann::json volume_info_;  // set once the volume is loaded
    std::string backend_, backend_reason_;
    std::uint64_t renders_ = 0, failures_ = 0, fusion_uploads_ = 0, case_preparations_ = 0;
    std::uint64_t superseded_ = 0, superseded_in_flight_ = 0, banded_ = 0, fused_passes_reused_ = 0;
    std::uint64_t gl_failures_ = 0;  // GL failures that dropped the GL renderers (status: gl_failures)
    double last_render_ms_ = 0;
    bool thread_done_ = false;
};

}  // namespace cf::daemon
