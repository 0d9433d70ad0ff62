#pragma once
// Multimodal fusion: a scene of up to four co-registered volume layers (e.g. MRI, CT, fMRI
// activation, a segmentation), each with its own transfer function, weight, visibility and
// rigid transform, composited in one ray-casting pass, plus opaque geometry (a triangle mesh)
// drawn with depth so that rays stop at it.
//
// Compositing (the seed's weighted compositing): at each ray sample every visible layer l
// gives colour c_l, shading s_l and opacity per step a_l = 1 - (1 - w_l * o_l)^step (o_l the
// layer's opacity per mm, w_l its weight in [0, 1]); the sample's opacity is
// 1 - prod(1 - a_l) and its colour sum(a_l c_l s_l) / sum(a_l). With one layer of weight 1
// this is exactly the single-volume ray caster.
//
// Backends: the GL renderer (cf_render_gl) implements all of it. The CPU renderer implements
// one layer of weight 1 and no mesh (the Renderer interface); it stays the reference for that.
#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "cortexfuse/core/renderer.hpp"

namespace cf {

/// Settings of one layer that can change without uploading its volume again.
struct LayerSettings {
    double weight = 1.0;   // scales the layer's opacity, 0..1
    bool visible = true;
    /// Rigid transform from the layer's own world (LPS mm, its file's frame) to the scene's
    /// world (the reference MRI's): the co-registration result.
    Pose T_scene_from_layer = Pose::Identity();
};

/// Opaque triangle geometry in scene world coordinates (LPS mm). Colour is per vertex
/// (0..1); where `texture` is not empty, it is multiplied by the texture at `uv` (OpenCV image
/// convention: u right, v down, in [0,1], texture 8-bit BGR as OpenCV loads it). Rasterised
/// with the undistorted pinhole of the intrinsics (lens distortion is ignored for meshes).
struct OpaqueMesh {
    std::vector<Eigen::Vector3f> p_world_mm;
    std::vector<Eigen::Vector3f> colour;      // one per vertex, or empty: white
    std::vector<Eigen::Vector2f> uv;          // one per vertex when texture is set
    std::vector<uint32_t> triangles;          // 3 indices a triangle
    cv::Mat texture;                          // CV_8UC3 BGR, optional
    /// Throws InputError(context, ...) on mismatched sizes or out-of-range indices.
    void validate(const std::string& context) const;
};

/// A renderer of a fusion scene. Layer 0 is the reference: Renderer::set_transfer_function()
/// changes it, and the first-surface refinement (depth, shading) follows its surface level.
/// Thread contract: as Renderer (one call at a time).
class FusionRenderer : public Renderer {
public:
    static constexpr int kMaxLayers = 4;
    /// Adds a layer and uploads its volume (quantised; `mask` hides what is outside it).
    /// `volume`, `mask` borrowed during the call. Returns the layer index. Throws InputError
    /// beyond kMaxLayers or on a mask of another grid.
    virtual int add_layer(const Volume& volume, const TransferFunction& tf, const LabelVolume* mask = nullptr,
                          const LayerSettings& settings = {}) = 0;
    virtual int layer_count() const = 0;
    /// None of these uploads a volume again (see volume_uploads()).
    virtual void set_layer_transfer_function(int layer, const TransferFunction& tf) = 0;
    virtual void set_layer_settings(int layer, const LayerSettings& settings) = 0;
    virtual const LayerSettings& layer_settings(int layer) const = 0;
    /// Opaque geometry drawn with depth before the volume pass; nullptr removes it. Copied.
    virtual void set_mesh(const OpaqueMesh* mesh) = 0;
    /// Volumes uploaded so far (one per add_layer): the test that settings cost no upload.
    virtual int volume_uploads() const = 0;
};

}  // namespace cf
