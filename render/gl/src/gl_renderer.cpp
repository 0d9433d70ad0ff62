// The GL ray caster: one EGL context per renderer, volumes as R16 3D textures of the same
// quantised values the CPU ray caster uses, transfer functions as rows of a table texture,
// brick visibility as small 3D textures, outputs in four framebuffer attachments read back
// straight into the caller's RenderImage (no staging copy, no per-frame allocation once the
// size is known). See shaders/raycast.frag for the ray loop.
#include <epoxy/gl.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <map>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/render/gl_renderer.hpp"
#include "egl_context.hpp"
#include "gl_util.hpp"
#include "shader_sources.hpp"

namespace cf {
namespace {

using namespace cf::gl;

constexpr int kBrick = 8;       // as raycast_cpu.cpp and raycast.frag
constexpr int kLutSize = 4096;  // quantised levels = table entries, as raycast_cpu.cpp
constexpr int kMaxGradPts = 8;  // gradient-opacity points the shader takes per layer
constexpr int kMaxBrickDistance = 31;  // cap of the brick distance map (raycast_cpu.cpp: the same)
// The shader's empty-space skipping cells: 4^3 voxels, finer than the 8^3 bricks of the box and
// the start map. On llvmpipe every step of the search loop costs all 8 lanes of a SIMD group;
// from the start map to the skin (bench render, 375x250) rays took 13.1 steps (mean; 15.0 the
// slowest of 4x2 pixels) with 8^3 cells, 9.7 (11.3) with 4^3, 8.6 (10.1) with 2^3. Skipping is
// conservative (a cell and its one-voxel apron hold no visible level), so pictures do not change.
constexpr int kCell = 4;

// The fragment shader with NLAYERS set: constant loop bounds let the compiler unroll the
// per-layer loops (llvmpipe in particular).
std::string raycast_fragment_source(int layers) {
    std::string src = shader_source("raycast.frag");
    const size_t eol = src.find('\n');
    src.insert(eol + 1, "#define NLAYERS " + std::to_string(layers) + "\n#define CELL " + std::to_string(kCell) + "\n");
    // Test hooks: CF_GL_BREAK_SHADER=link leaves the fragment stage without main (it compiles,
    // the program does not link); any other value breaks the compile.
    if (const char* e = std::getenv("CF_GL_BREAK_SHADER"); e && *e && std::strcmp(e, "0") != 0)
        src.insert(eol + 1, std::strcmp(e, "link") == 0 ? "#define main cf_main_renamed_by_CF_GL_BREAK_SHADER\n" : "this is not GLSL;\n");
    return src;
}

// IEEE half of n / 2 for |n| <= 8190 (round to nearest even): the gradient texture's values.
uint16_t half_of_half_int(int n) {
    if (n == 0) return 0;
    const uint16_t sign = n < 0 ? 0x8000 : 0;
    unsigned m = unsigned(n < 0 ? -n : n);  // value = m * 2^-1
    int e = -1;
    while (m >= 2048) {  // keep 11 significant bits, rounding to nearest even
        const unsigned rem = m & 1u;
        m >>= 1;
        if (rem && (m & 1u)) ++m;
        ++e;
    }
    while (m < 1024) {
        m <<= 1;
        --e;
    }
    if (m >= 2048) {
        m >>= 1;
        ++e;
    }
    // value = m * 2^e with 1024 <= m < 2048: exponent field e + 10 + 15.
    return uint16_t(sign | uint16_t((e + 25) << 10) | uint16_t(m & 0x3ffu));
}

struct Layer {
    VolumeGeometry geom;
    double lo = 0, hi = 1;  // robust range: quantised 0..4095 spans it
    std::array<int, 3> nb{};
    std::vector<uint16_t> brick_min, brick_max;
    std::array<int, 3> nc{};                     // skipping cells (kCell^3 voxels) per axis
    std::vector<uint16_t> cell_min, cell_max;
    Texture volume, bricks, gradient;
    TransferFunction tf;
    BakedTransferFunction baked;
    LayerSettings settings;
    float iso_q = -1.f;
    float grad_scale = 1.f;
    std::array<float, 3> box_lo{}, box_hi{};
    std::vector<uint8_t> brick_visible;
    std::vector<std::array<int, 3>> frontier;  // the frontier of the visible kCell^3 cells: where rays enter them
    std::vector<uint8_t> shown;  // per table entry: opacity > 0, as the skipping structures above were made for
};

struct RaycastProgram {
    Program prog;
    GLint R = -1, cam = -1, ifw = -1, dims = -1, box_lo = -1, box_hi = -1, weight = -1, grad_scale = -1, grad_n = -1,
          grad_pts = -1, iso = -1, step = -1, phase = -1, ambient = -1, diffuse = -1, term = -1, cov = -1, shading = -1, has_mesh = -1, light = -1, light_world = -1, light_pos_world = -1, surface_only = -1,
          start_on = -1, start_origin = -1, start_inv_cell = -1, start_cells = -1;
};

class GlRenderer final : public FusionRenderer {
public:
    GlRenderer() {
        ctx_.make_current();
        program(1);  // builds (and checks) the common program now, so a broken driver fails early
        mesh_prog_.reset(build_program("mesh", shader_source("mesh.vert"), shader_source("mesh.frag")));
        mesh_loc_T_ = glGetUniformLocation(mesh_prog_.get(), "u_camera_from_world");
        mesh_loc_K_ = glGetUniformLocation(mesh_prog_.get(), "u_K");
        mesh_loc_size_ = glGetUniformLocation(mesh_prog_.get(), "u_size");
        mesh_loc_nf_ = glGetUniformLocation(mesh_prog_.get(), "u_near_far");
        mesh_loc_textured_ = glGetUniformLocation(mesh_prog_.get(), "u_textured");
        empty_vao_.reset(gen_vertex_array());
        lut_.reset(gen_texture());
        glBindTexture(GL_TEXTURE_2D, lut_.get());
        glTexStorage2D(GL_TEXTURE_2D, 1, GL_RGBA32F, kLutSize, kMaxLayers);
        set_nearest(GL_TEXTURE_2D);
        rays_.reset(gen_texture());
        glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max_3d_texture_size_);
        // Test hook: the context is lost at this renderer's Nth frame (the owners' recovery path).
        if (const char* e = std::getenv("CF_GL_LOSE_CONTEXT_AT_FRAME"); e && *e) lose_context_at_frame_ = std::atol(e);
        check_gl("GL renderer setup");
    }

    ~GlRenderer() override {
        // GL objects are deleted with the context current; the context goes last (member order).
        try {
            ctx_.make_current();
        } catch (...) {
            abandon_gl_objects();
        }
    }

    // The context is lost or gone: its objects went with it, and deleting them now would call GL
    // with no context current, or another renderer's.
    void abandon_gl_objects() {
        for (auto& [n, P] : programs_) P.prog.abandon();
        for (auto& L : layers_) {
            L->volume.abandon();
            L->bricks.abandon();
            L->gradient.abandon();
        }
        for (Texture* t : {&mesh_tex_, &lut_, &rays_, &out_rgb_, &out_grey_, &out_depth_, &out_cov_, &mesh_rgb_, &mesh_z_}) t->abandon();
        mesh_prog_.abandon();
        empty_vao_.abandon();
        mesh_vao_.abandon();
        mesh_vbo_.abandon();
        mesh_ebo_.abandon();
        start_buf_.abandon();
        mesh_depth_.abandon();
        fbo_.abandon();
        mesh_fbo_.abandon();
    }

    const char* name() const override { return "gl"; }
    const GlInfo& info() const { return ctx_.info(); }

    int add_layer(const Volume& volume, const TransferFunction& tf, const LabelVolume* mask,
                  const LayerSettings& settings) override {
        if (int(layers_.size()) >= kMaxLayers)
            throw InputError("fusion scene", "at most " + std::to_string(kMaxLayers) + " layers");
        if (mask && !mask->geom.same_grid(volume.geom)) throw InputError("mask", "is not on the volume's grid");
        if (volume.voxels.size() != volume.geom.voxel_count() || volume.geom.voxel_count() == 0)
            throw InputError("volume", "empty or inconsistent with its dimensions");
        const auto range = robust_range(volume, mask);  // of the volume as given
        // A mask on thick slices: drawn from the finer copy (renderer.hpp), as the CPU one does.
        const auto copy = masked_render_copy(volume, mask, range);
        const Volume& v = copy ? *copy : volume;
        if (copy) mask = nullptr;  // faded into the copy
        ctx_.make_current();
        // Said before anything is allocated: glTexStorage3D would only say GL_INVALID_VALUE.
        const auto& dims = v.geom.dims;
        if (std::max({dims[0], dims[1], dims[2]}) > max_3d_texture_size_)
            throw GlError("volume of " + std::to_string(dims[0]) + "x" + std::to_string(dims[1]) + "x" + std::to_string(dims[2]) +
                          " voxels: larger than this GL's 3D textures (GL_MAX_3D_TEXTURE_SIZE " +
                          std::to_string(max_3d_texture_size_) + " voxels per side); resample it or use the CPU renderer");
        auto L = std::make_unique<Layer>();
        L->geom = v.geom;
        L->settings = settings;
        L->lo = range[0];
        L->hi = range[1];
        // Quantised exactly like raycast_cpu.cpp, so both sample the same numbers.
        const auto& d = v.geom.dims;
        std::vector<uint16_t> q(v.geom.voxel_count());
        const double s = (kLutSize - 1) / (L->hi - L->lo);
        for (size_t i = 0; i < q.size(); ++i) {
            double x = (double(v.voxels[i]) - L->lo) * s;
            if (mask && !mask->voxels[i]) x = 0;
            q[i] = uint16_t(std::clamp(x, 0.0, double(kLutSize - 1)));
        }
        block_min_max(q, v.geom.dims, kBrick, L->nb, L->brick_min, L->brick_max);
        block_min_max(q, v.geom.dims, kCell, L->nc, L->cell_min, L->cell_max);
        L->volume.reset(gen_texture());
        glBindTexture(GL_TEXTURE_3D, L->volume.get());
        glTexStorage3D(GL_TEXTURE_3D, 1, GL_R16, d[0], d[1], d[2]);
        glPixelStorei(GL_UNPACK_ALIGNMENT, 2);
        glTexSubImage3D(GL_TEXTURE_3D, 0, 0, 0, 0, d[0], d[1], d[2], GL_RED, GL_UNSIGNED_SHORT, q.data());
        glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
        glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
        for (GLenum w : {GL_TEXTURE_WRAP_S, GL_TEXTURE_WRAP_T, GL_TEXTURE_WRAP_R})
            glTexParameteri(GL_TEXTURE_3D, w, GL_CLAMP_TO_EDGE);
        // Per-voxel central differences (clamped at the border, as the CPU's sample_clamped),
        // as half floats: the differences are multiples of 0.5 below 2048, so they are exact
        // up to 1024 and within 0.5 above.
        {
            std::vector<uint16_t> g(q.size() * 4);
            const size_t sy = size_t(d[0]), sz = sy * size_t(d[1]);
            for (int k = 0; k < d[2]; ++k)
                for (int j = 0; j < d[1]; ++j)
                    for (int i = 0; i < d[0]; ++i) {
                        const size_t c = v.geom.linear(i, j, k);
                        const int dx = int(q[c + (i + 1 < d[0] ? 1 : 0)]) - int(q[c - (i > 0 ? 1 : 0)]);
                        const int dy = int(q[c + (j + 1 < d[1] ? sy : 0)]) - int(q[c - (j > 0 ? sy : 0)]);
                        const int dz = int(q[c + (k + 1 < d[2] ? sz : 0)]) - int(q[c - (k > 0 ? sz : 0)]);
                        uint16_t* o = g.data() + 4 * c;
                        o[0] = half_of_half_int(dx);
                        o[1] = half_of_half_int(dy);
                        o[2] = half_of_half_int(dz);
                        o[3] = 0;
                    }
            L->gradient.reset(gen_texture());
            glBindTexture(GL_TEXTURE_3D, L->gradient.get());
            glTexStorage3D(GL_TEXTURE_3D, 1, GL_RGBA16F, d[0], d[1], d[2]);
            glTexSubImage3D(GL_TEXTURE_3D, 0, 0, 0, 0, d[0], d[1], d[2], GL_RGBA, GL_HALF_FLOAT, g.data());
            glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
            glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
            for (GLenum w : {GL_TEXTURE_WRAP_S, GL_TEXTURE_WRAP_T, GL_TEXTURE_WRAP_R})
                glTexParameteri(GL_TEXTURE_3D, w, GL_CLAMP_TO_EDGE);
        }
        L->bricks.reset(gen_texture());
        glBindTexture(GL_TEXTURE_3D, L->bricks.get());
        glTexStorage3D(GL_TEXTURE_3D, 1, GL_R8UI, L->nc[0], L->nc[1], L->nc[2]);
        set_nearest(GL_TEXTURE_3D);
        check_gl("volume upload");
        ++uploads_;
        layers_.push_back(std::move(L));
        apply_transfer_function(int(layers_.size()) - 1, tf);
        return int(layers_.size()) - 1;
    }

    int layer_count() const override { return int(layers_.size()); }

    void set_transfer_function(const TransferFunction& tf) override { set_layer_transfer_function(0, tf); }

    void set_layer_transfer_function(int layer, const TransferFunction& tf) override {
        check_layer(layer);
        ctx_.make_current();
        apply_transfer_function(layer, tf);
    }

    void set_layer_settings(int layer, const LayerSettings& s) override {
        check_layer(layer);
        if (!(s.weight >= 0.0 && s.weight <= 1.0)) throw InputError("layer weight", "must be in [0, 1]");
        layers_[size_t(layer)]->settings = s;  // uniforms only: nothing to upload
    }

    const LayerSettings& layer_settings(int layer) const override {
        check_layer(layer);
        return layers_[size_t(layer)]->settings;
    }

    void set_mesh(const OpaqueMesh* mesh) override {
        ctx_.make_current();
        mesh_triangles_ = 0;
        if (!mesh || mesh->triangles.empty()) return;
        mesh->validate("mesh");
        const size_t n = mesh->p_world_mm.size();
        std::vector<float> vb(n * 8);
        for (size_t i = 0; i < n; ++i) {
            float* p = vb.data() + i * 8;
            for (int a = 0; a < 3; ++a) p[a] = mesh->p_world_mm[i][a];
            for (int a = 0; a < 3; ++a) p[3 + a] = mesh->colour.empty() ? 1.f : mesh->colour[i][a];
            p[6] = mesh->uv.size() == n ? mesh->uv[i][0] : 0.f;
            p[7] = mesh->uv.size() == n ? mesh->uv[i][1] : 0.f;
        }
        if (!mesh_vao_) {
            mesh_vao_.reset(gen_vertex_array());
            mesh_vbo_.reset(gen_buffer());
            mesh_ebo_.reset(gen_buffer());
        }
        glBindVertexArray(mesh_vao_.get());
        glBindBuffer(GL_ARRAY_BUFFER, mesh_vbo_.get());
        glBufferData(GL_ARRAY_BUFFER, GLsizeiptr(vb.size() * sizeof(float)), vb.data(), GL_STATIC_DRAW);
        glBindBuffer(GL_ELEMENT_ARRAY_BUFFER, mesh_ebo_.get());
        glBufferData(GL_ELEMENT_ARRAY_BUFFER, GLsizeiptr(mesh->triangles.size() * 4), mesh->triangles.data(), GL_STATIC_DRAW);
        for (GLuint a = 0; a < 3; ++a) glEnableVertexAttribArray(a);
        glVertexAttribPointer(0, 3, GL_FLOAT, GL_FALSE, 32, reinterpret_cast<void*>(0));
        glVertexAttribPointer(1, 3, GL_FLOAT, GL_FALSE, 32, reinterpret_cast<void*>(12));
        glVertexAttribPointer(2, 2, GL_FLOAT, GL_FALSE, 32, reinterpret_cast<void*>(24));
        glBindVertexArray(0);
        mesh_textured_ = !mesh->texture.empty();
        if (mesh_textured_) {
            cv::Mat tex = mesh->texture.isContinuous() ? mesh->texture : mesh->texture.clone();
            mesh_tex_.reset(gen_texture());
            glBindTexture(GL_TEXTURE_2D, mesh_tex_.get());
            glTexStorage2D(GL_TEXTURE_2D, 1, GL_RGBA8, tex.cols, tex.rows);
            glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
            glTexSubImage2D(GL_TEXTURE_2D, 0, 0, 0, tex.cols, tex.rows, GL_BGR, GL_UNSIGNED_BYTE, tex.data);
            glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
            glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
            glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
            glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);
        }
        mesh_triangles_ = GLsizei(mesh->triangles.size());
        check_gl("mesh upload");
    }

    int volume_uploads() const override { return uploads_; }

    void render(const Intrinsics& K, const Pose& T, const RenderOptions& opt, RenderImage& out) override {
        if (K.width <= 0 || K.height <= 0) throw InputError("intrinsics", "image size must be positive");
        if (!(opt.sample_distance_mm > 0)) throw InputError("sample distance", "must be positive");
        if (++frames_ == lose_context_at_frame_) ctx_.lose();
        ctx_.make_current();
        prepare_targets(K);
        const Eigen::Matrix4d Tw = T.inverse();  // world_from_camera
        // The layers drawn: visible ones with weight > 0, in scene order (layer 0 first).
        std::array<const Layer*, kMaxLayers> drawn{};
        int n_drawn = 0;
        for (const auto& L : layers_)
            if (L->settings.visible && L->settings.weight > 0) drawn[size_t(n_drawn++)] = L.get();

        if (mesh_triangles_ > 0) draw_mesh(K, T);

        glBindFramebuffer(GL_FRAMEBUFFER, fbo_.get());
        glViewport(0, 0, K.width, K.height);
        glDisable(GL_DEPTH_TEST);
        if (n_drawn == 0 && mesh_triangles_ == 0) {
            // Nothing to draw: clear to the empty picture.
            const float zero[4] = {0, 0, 0, 1};
            const GLuint zu[4] = {0, 0, 0, 0};
            glClearBufferfv(GL_COLOR, 0, zero);
            glClearBufferfv(GL_COLOR, 1, zero);
            glClearBufferfv(GL_COLOR, 2, zero);
            glClearBufferuiv(GL_COLOR, 3, zu);
        } else {
            const int n = std::max(1, n_drawn);
            const RaycastProgram& P = program(n);
            glUseProgram(P.prog.get());
            // Fixed-size arrays: nothing is allocated per frame.
            std::array<float, 16 * kMaxLayers> ifw{};
            std::array<float, 3 * kMaxLayers> dims{}, blo{}, bhi{};
            std::array<float, kMaxLayers> weight{}, gscale{};
            std::array<float, 2 * kMaxGradPts * kMaxLayers> gpts{};
            std::array<GLint, kMaxLayers> gn{};
            for (int l = 0; l < n; ++l) {
                if (n_drawn == 0) {  // mesh only: a layer no ray ever enters
                    for (int a = 0; a < 3; ++a) { dims[size_t(3 * l + a)] = 1; blo[size_t(3 * l + a)] = 0; bhi[size_t(3 * l + a)] = -1; }
                    Eigen::Map<Eigen::Matrix4f>(ifw.data() + 16 * l).setIdentity();
                    continue;
                }
                const Layer& L = *drawn[size_t(l)];
                // index_from_scene = index_from_layer_world * layer_from_scene.
                const Eigen::Matrix4d M = L.geom.index_from_world().matrix() * L.settings.T_scene_from_layer.inverse();
                Eigen::Map<Eigen::Matrix4f>(ifw.data() + 16 * l) = M.cast<float>();
                for (int a = 0; a < 3; ++a) {
                    dims[size_t(3 * l + a)] = float(L.geom.dims[a]);
                    blo[size_t(3 * l + a)] = L.box_lo[a];
                    bhi[size_t(3 * l + a)] = L.box_hi[a];
                }
                weight[size_t(l)] = float(L.settings.weight);
                gscale[size_t(l)] = L.grad_scale;
                gn[size_t(l)] = GLint(L.baked.gradient_opacity.size());
                for (size_t i = 0; i < L.baked.gradient_opacity.size(); ++i) {
                    gpts[size_t(l) * 2 * kMaxGradPts + 2 * i] = float(L.baked.gradient_opacity[i][0]);
                    gpts[size_t(l) * 2 * kMaxGradPts + 2 * i + 1] = float(L.baked.gradient_opacity[i][1]);
                }
                glActiveTexture(GL_TEXTURE1 + GLenum(l));
                glBindTexture(GL_TEXTURE_3D, L.volume.get());
                glActiveTexture(GL_TEXTURE5 + GLenum(l));
                glBindTexture(GL_TEXTURE_3D, L.bricks.get());
                glActiveTexture(GL_TEXTURE12 + GLenum(l));
                glBindTexture(GL_TEXTURE_3D, L.gradient.get());
            }
            const Eigen::Matrix3f Rwc = Tw.topLeftCorner<3, 3>().cast<float>();
            const Eigen::Vector3f cam = Tw.topRightCorner<3, 1>().cast<float>();
            glUniformMatrix3fv(P.R, 1, GL_FALSE, Rwc.data());
            glUniform3fv(P.cam, 1, cam.data());
            glUniformMatrix4fv(P.ifw, n, GL_FALSE, ifw.data());
            glUniform3fv(P.dims, n, dims.data());
            glUniform3fv(P.box_lo, n, blo.data());
            glUniform3fv(P.box_hi, n, bhi.data());
            glUniform1fv(P.weight, n, weight.data());
            glUniform1fv(P.grad_scale, n, gscale.data());
            glUniform1iv(P.grad_n, n, gn.data());
            glUniform2fv(P.grad_pts, n * kMaxGradPts, gpts.data());
            // The first-surface refinement follows the reference layer (layer 0) when drawn.
            glUniform1f(P.iso, n_drawn > 0 && drawn[0] == layers_[0].get() ? drawn[0]->iso_q : -1.f);
            glUniform1f(P.step, float(opt.sample_distance_mm));
            glUniform1f(P.phase, float(sample_lattice_phase_mm(opt, Tw.topRightCorner<3, 1>())));
            glUniform1f(P.ambient, float(opt.ambient));
            glUniform1f(P.diffuse, float(opt.diffuse));
            glUniform1f(P.term, float(opt.early_termination_alpha));
            glUniform1f(P.cov, float(opt.coverage_alpha));
            glUniform1i(P.shading, opt.shading ? 1 : 0);
            {
                const Eigen::Matrix3d R_world_from_camera = T.topLeftCorner<3, 3>().transpose();
                const Eigen::Vector3f L = (R_world_from_camera * Eigen::Vector3d(opt.light_direction_camera[0], opt.light_direction_camera[1],
                                                                                 opt.light_direction_camera[2]))
                                              .normalized()
                                              .cast<float>();
                const Eigen::Vector3f Lp = (Tw * Eigen::Vector4d(opt.light_position_camera_mm[0], opt.light_position_camera_mm[1],
                                                                           opt.light_position_camera_mm[2], 1.0))
                                               .head<3>()
                                               .cast<float>();
                glUniform1i(P.light, opt.light == Light::distant ? 1 : opt.light == Light::point ? 2 : 0);
                glUniform3f(P.light_pos_world, Lp.x(), Lp.y(), Lp.z());
                glUniform1i(P.surface_only, opt.surface_only ? 1 : 0);
                glUniform3f(P.light_world, L.x(), L.y(), L.z());
            }
            glUniform1i(P.has_mesh, mesh_triangles_ > 0 ? 1 : 0);
            // Where rays may start (core's RayStartMap, as the CPU ray caster): the drawn layers'
            // frontier cells projected on the CPU, a few thousand grid cells in a storage buffer.
            const bool start_on = opt.ray_start_map && n_drawn > 0 && start_map_for(T, drawn, n_drawn);
            glUniform1i(P.start_on, start_on ? 1 : 0);
            if (start_on) {
                glUniform2f(P.start_origin, start_map_.x0(), start_map_.y0());
                glUniform1f(P.start_inv_cell, start_map_.inv_cell());
                glUniform2i(P.start_cells, start_map_.cells_x(), start_map_.cells_y());
                const auto& cells = start_map_.cells();
                const GLsizeiptr bytes = GLsizeiptr(cells.size() * sizeof(float));
                if (!start_buf_.get() || bytes != start_buf_bytes_) {
                    start_buf_.reset(gen_buffer());
                    glBindBuffer(GL_SHADER_STORAGE_BUFFER, start_buf_.get());
                    glBufferData(GL_SHADER_STORAGE_BUFFER, bytes, nullptr, GL_DYNAMIC_DRAW);
                    start_buf_bytes_ = bytes;
                }
                glBindBuffer(GL_SHADER_STORAGE_BUFFER, start_buf_.get());
                glBufferSubData(GL_SHADER_STORAGE_BUFFER, 0, bytes, cells.data());
                glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, start_buf_.get());
            }
            glActiveTexture(GL_TEXTURE0);
            glBindTexture(GL_TEXTURE_2D, rays_.get());
            glActiveTexture(GL_TEXTURE9);
            glBindTexture(GL_TEXTURE_2D, lut_.get());
            glActiveTexture(GL_TEXTURE10);
            glBindTexture(GL_TEXTURE_2D, mesh_rgb_.get());
            glActiveTexture(GL_TEXTURE11);
            glBindTexture(GL_TEXTURE_2D, mesh_z_.get());
            glBindVertexArray(empty_vao_.get());
            glDrawArrays(GL_TRIANGLES, 0, 3);
            glBindVertexArray(0);
        }
        check_gl("ray casting");
        read_back(K, opt, out);
    }

private:
    static void set_nearest(GLenum target) {
        glTexParameteri(target, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
        glTexParameteri(target, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    }

    /// The start map for this frame over the drawn layers: false when rays must start at the
    /// box (the camera inside a layer's box, or a frontier brick reaching behind it).
    bool start_map_for(const Pose& T, const std::array<const Layer*, kMaxLayers>& drawn, int n_drawn) {
        if (start_map_.empty()) return false;
        start_map_.clear();
        const Eigen::Vector4d cam_scene = T.inverse().col(3);
        for (int l = 0; l < n_drawn; ++l) {
            const Layer& L = *drawn[size_t(l)];
            const Eigen::Matrix4d index_from_scene = L.geom.index_from_world().matrix() * L.settings.T_scene_from_layer.inverse();
            const Eigen::Vector4d o = index_from_scene * cam_scene;
            bool inside = true;
            for (int a = 0; a < 3; ++a) inside = inside && o[a] >= L.box_lo[a] - 1.0 && o[a] <= L.box_hi[a] + 1.0;
            if (inside) return false;
            if (L.frontier.empty()) continue;
            if (!start_map_.add(T * index_from_scene.inverse(), L.frontier, kCell)) return false;
        }
        return true;
    }

    void check_layer(int layer) const {
        if (layer < 0 || layer >= int(layers_.size()))
            throw InputError("layer " + std::to_string(layer), "no such layer (" + std::to_string(layers_.size()) + " in the scene)");
    }

    const RaycastProgram& program(int layers) {
        auto it = programs_.find(layers);
        if (it != programs_.end()) return it->second;
        RaycastProgram P;
        P.prog.reset(build_program("raycast (" + std::to_string(layers) + " layers)", shader_source("raycast.vert"),
                                   raycast_fragment_source(layers)));
        const GLuint p = P.prog.get();
        auto loc = [&](const char* n) { return glGetUniformLocation(p, n); };
        P.R = loc("u_R_world_from_camera");
        P.cam = loc("u_cam_world");
        P.ifw = loc("u_index_from_world");
        P.dims = loc("u_dims");
        P.box_lo = loc("u_box_lo");
        P.box_hi = loc("u_box_hi");
        P.weight = loc("u_weight");
        P.grad_scale = loc("u_grad_scale");
        P.grad_n = loc("u_grad_n");
        P.grad_pts = loc("u_grad_pts");
        P.iso = loc("u_iso");
        P.step = loc("u_step");
        P.phase = loc("u_phase");
        P.ambient = loc("u_ambient");
        P.diffuse = loc("u_diffuse");
        P.term = loc("u_term");
        P.cov = loc("u_cov");
        P.shading = loc("u_shading");
        P.light = loc("u_light");
        P.light_pos_world = loc("u_light_pos_world");
        P.surface_only = loc("u_surface_only");
        P.light_world = loc("u_light_world");
        P.has_mesh = loc("u_has_mesh");
        P.start_on = loc("u_start_on");
        P.start_origin = loc("u_start_origin");
        P.start_inv_cell = loc("u_start_inv_cell");
        P.start_cells = loc("u_start_cells");
        return programs_.emplace(layers, std::move(P)).first->second;
    }

    void apply_transfer_function(int layer, const TransferFunction& tf) {
        Layer& L = *layers_[size_t(layer)];
        L.baked = bake(tf, L.lo, L.hi, kLutSize);
        if (L.baked.gradient_opacity.size() > size_t(kMaxGradPts))
            throw InputError("transfer function \"" + tf.name + "\"",
                             "the GL renderer takes at most " + std::to_string(kMaxGradPts) + " gradient-opacity points");
        L.tf = tf;
        L.grad_scale = float((L.hi - L.lo) / (kLutSize - 1));
        L.iso_q = -1.f;
        for (int i = 0; i < kLutSize; ++i)
            if (L.baked.rgba[size_t(i)][3] >= 0.5f) {
                L.iso_q = float(i) - 0.5f;
                break;
            }
        glBindTexture(GL_TEXTURE_2D, lut_.get());
        glTexSubImage2D(GL_TEXTURE_2D, 0, 0, layer, kLutSize, 1, GL_RGBA, GL_FLOAT, L.baked.rgba.data());
        // The empty-space skipping below depends only on which table entries have opacity > 0:
        // when those are the ones it was made for (a weight, an opacity slider, a colour, a
        // point dragged within the shown range; every request of a view sets its transfer
        // function again), it stands. Its distance transform was a quarter of the daemon's time
        // for a fused preview (perf, 2026-11-27).
        std::vector<uint8_t> shown(kLutSize);
        for (int i = 0; i < kLutSize; ++i) shown[size_t(i)] = L.baked.rgba[size_t(i)][3] > 0.f ? 1 : 0;
        if (shown == L.shown) {
            check_gl("transfer function upload");
            return;
        }
        L.shown = std::move(shown);
        // Brick visibility: any table entry in the brick's [min, max] with opacity > 0, by a
        // prefix count of such entries.
        std::vector<int> count(kLutSize + 1, 0);
        for (int i = 0; i < kLutSize; ++i) count[size_t(i + 1)] = count[size_t(i)] + L.shown[size_t(i)];
        L.brick_visible.assign(L.brick_min.size(), 0);
        std::array<int, 3> lo{L.nb[0], L.nb[1], L.nb[2]}, hi{-1, -1, -1};
        for (int bz = 0; bz < L.nb[2]; ++bz)
            for (int by = 0; by < L.nb[1]; ++by)
                for (int bx = 0; bx < L.nb[0]; ++bx) {
                    const size_t b = (size_t(bz) * L.nb[1] + by) * L.nb[0] + bx;
                    const int a = L.brick_min[b], c = L.brick_max[b];
                    if (a > c || count[size_t(c + 1)] - count[size_t(a)] == 0) continue;
                    L.brick_visible[b] = 1;
                    lo = {std::min(lo[0], bx), std::min(lo[1], by), std::min(lo[2], bz)};
                    hi = {std::max(hi[0], bx), std::max(hi[1], by), std::max(hi[2], bz)};
                }
        // The same box around the visible content as the CPU ray caster.
        for (int a = 0; a < 3; ++a) {
            L.box_lo[size_t(a)] = hi[a] < 0 ? 0.f : float(std::max(0, lo[a] * kBrick - 1));
            L.box_hi[size_t(a)] = hi[a] < 0 ? -1.f : float(std::min(L.geom.dims[a] - 1, (hi[a] + 1) * kBrick + 1)) - 1e-3f;
        }
        // The shader reads each kCell^3 cell's Chebyshev distance to a visible one (as the CPU
        // ray caster does with its 8^3 bricks) and crosses the empty cube around it in one
        // jump: on llvmpipe every iteration of the search loop costs all lanes of a SIMD group.
        std::vector<uint8_t> cell_visible(L.cell_min.size(), 0);
        for (size_t b = 0; b < cell_visible.size(); ++b) {
            const int a = L.cell_min[b], c = L.cell_max[b];
            cell_visible[b] = a <= c && count[size_t(c + 1)] - count[size_t(a)] > 0 ? 1 : 0;
        }
        const std::vector<uint8_t> distance = brick_chebyshev_distance(cell_visible, L.nc, kMaxBrickDistance);
        // Rays start at the nearest frontier cell, not brick: within half a brick of the content
        // (the CPU ray caster's 4^3 blocks alike).
        L.frontier = frontier_bricks(cell_visible, L.nc);
        glBindTexture(GL_TEXTURE_3D, L.bricks.get());
        glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
        glTexSubImage3D(GL_TEXTURE_3D, 0, 0, 0, 0, L.nc[0], L.nc[1], L.nc[2], GL_RED_INTEGER, GL_UNSIGNED_BYTE,
                        distance.data());
        check_gl("transfer function upload");
    }

    void prepare_targets(const Intrinsics& K) {
        if (K.width != target_w_ || K.height != target_h_) {
            target_w_ = K.width;
            target_h_ = K.height;
            auto tex2d = [&](Texture& t, GLenum fmt) {
                t.reset(gen_texture());
                glBindTexture(GL_TEXTURE_2D, t.get());
                glTexStorage2D(GL_TEXTURE_2D, 1, fmt, K.width, K.height);
                set_nearest(GL_TEXTURE_2D);
            };
            tex2d(out_rgb_, GL_RGBA8);
            tex2d(out_grey_, GL_R32F);
            tex2d(out_depth_, GL_R32F);
            tex2d(out_cov_, GL_R8UI);
            fbo_.reset(gen_framebuffer());
            glBindFramebuffer(GL_FRAMEBUFFER, fbo_.get());
            glFramebufferTexture(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, out_rgb_.get(), 0);
            glFramebufferTexture(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT1, out_grey_.get(), 0);
            glFramebufferTexture(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT2, out_depth_.get(), 0);
            glFramebufferTexture(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT3, out_cov_.get(), 0);
            const GLenum bufs[4] = {GL_COLOR_ATTACHMENT0, GL_COLOR_ATTACHMENT1, GL_COLOR_ATTACHMENT2, GL_COLOR_ATTACHMENT3};
            glDrawBuffers(4, bufs);
            if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
                throw GlError("the ray-casting framebuffer is incomplete");
            tex2d(mesh_rgb_, GL_RGBA8);
            tex2d(mesh_z_, GL_R32F);
            mesh_depth_.reset(gen_renderbuffer());
            glBindRenderbuffer(GL_RENDERBUFFER, mesh_depth_.get());
            glRenderbufferStorage(GL_RENDERBUFFER, GL_DEPTH_COMPONENT24, K.width, K.height);
            mesh_fbo_.reset(gen_framebuffer());
            glBindFramebuffer(GL_FRAMEBUFFER, mesh_fbo_.get());
            glFramebufferTexture(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, mesh_rgb_.get(), 0);
            glFramebufferTexture(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT1, mesh_z_.get(), 0);
            glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_DEPTH_ATTACHMENT, GL_RENDERBUFFER, mesh_depth_.get());
            glDrawBuffers(2, bufs);
            if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
                throw GlError("the mesh framebuffer is incomplete");
            glBindTexture(GL_TEXTURE_2D, rays_.get());
            rays_.reset(gen_texture());
            glBindTexture(GL_TEXTURE_2D, rays_.get());
            glTexStorage2D(GL_TEXTURE_2D, 1, GL_RGBA32F, K.width, K.height);
            set_nearest(GL_TEXTURE_2D);
            rays_valid_ = false;
            check_gl("render targets");
        }
        if (!rays_valid_ || K.fx != rays_K_.fx || K.fy != rays_K_.fy || K.cx != rays_K_.cx || K.cy != rays_K_.cy ||
            K.distortion != rays_K_.distortion) {
            // Undistorted unit rays, computed once per camera (as the CPU ray caster does).
            auto rays = pixel_rays(K);
            for (auto& r : rays) r.normalize();  // once: for the texture and the start map
            ray_buf_.resize(rays.size() * 4);
            for (size_t i = 0; i < rays.size(); ++i) {
                const Eigen::Vector3f& r = rays[i];
                ray_buf_[4 * i] = r.x();
                ray_buf_[4 * i + 1] = r.y();
                ray_buf_[4 * i + 2] = r.z();
                ray_buf_[4 * i + 3] = 0.f;
            }
            glBindTexture(GL_TEXTURE_2D, rays_.get());
            glPixelStorei(GL_UNPACK_ALIGNMENT, 4);
            glTexSubImage2D(GL_TEXTURE_2D, 0, 0, 0, K.width, K.height, GL_RGBA, GL_FLOAT, ray_buf_.data());
            rays_K_ = K;
            rays_valid_ = true;
            start_map_.set_rays(rays, K.width);
        }
    }

    void draw_mesh(const Intrinsics& K, const Pose& T) {
        glBindFramebuffer(GL_FRAMEBUFFER, mesh_fbo_.get());
        glViewport(0, 0, K.width, K.height);
        const float zero[4] = {0, 0, 0, 0};
        glClearBufferfv(GL_COLOR, 0, zero);
        glClearBufferfv(GL_COLOR, 1, zero);
        glClearBufferfi(GL_DEPTH_STENCIL, 0, 1.f, 0);
        glEnable(GL_DEPTH_TEST);
        glDepthFunc(GL_LESS);
        glUseProgram(mesh_prog_.get());
        const Eigen::Matrix4f Tf = T.cast<float>();
        glUniformMatrix4fv(mesh_loc_T_, 1, GL_FALSE, Tf.data());
        glUniform4f(mesh_loc_K_, float(K.fx), float(K.fy), float(K.cx), float(K.cy));
        glUniform2f(mesh_loc_size_, float(K.width), float(K.height));
        glUniform2f(mesh_loc_nf_, 1.f, 1e5f);
        glUniform1i(mesh_loc_textured_, mesh_textured_ ? 1 : 0);
        glActiveTexture(GL_TEXTURE0);
        glBindTexture(GL_TEXTURE_2D, mesh_textured_ ? mesh_tex_.get() : 0);
        glBindVertexArray(mesh_vao_.get());
        glDrawElements(GL_TRIANGLES, mesh_triangles_, GL_UNSIGNED_INT, nullptr);
        glBindVertexArray(0);
        glDisable(GL_DEPTH_TEST);
        check_gl("mesh pass");
    }

    void read_back(const Intrinsics& K, const RenderOptions& opt, RenderImage& out) {
        const size_t n = size_t(K.width) * K.height;
        out.width = K.width;
        out.height = K.height;
        out.grey.resize(n);
        out.coverage.resize(n);
        if (opt.want_rgb) out.rgb.resize(n * 3); else out.rgb.clear();
        if (opt.want_depth) out.depth_mm.resize(n); else out.depth_mm.clear();
        glBindFramebuffer(GL_READ_FRAMEBUFFER, fbo_.get());
        glPixelStorei(GL_PACK_ALIGNMENT, 1);
        if (opt.want_rgb) {
            glReadBuffer(GL_COLOR_ATTACHMENT0);
            glReadPixels(0, 0, K.width, K.height, GL_RGB, GL_UNSIGNED_BYTE, out.rgb.data());
        }
        glReadBuffer(GL_COLOR_ATTACHMENT1);
        glReadPixels(0, 0, K.width, K.height, GL_RED, GL_FLOAT, out.grey.data());
        if (opt.want_depth) {
            glReadBuffer(GL_COLOR_ATTACHMENT2);
            glReadPixels(0, 0, K.width, K.height, GL_RED, GL_FLOAT, out.depth_mm.data());
        }
        glReadBuffer(GL_COLOR_ATTACHMENT3);
        glReadPixels(0, 0, K.width, K.height, GL_RED_INTEGER, GL_UNSIGNED_BYTE, out.coverage.data());
        check_gl("read back");
    }

    // Member order matters: the context is destroyed last, after every GL object.
    EglContext ctx_;
    std::map<int, RaycastProgram> programs_;
    Program mesh_prog_;
    GLint mesh_loc_T_ = -1, mesh_loc_K_ = -1, mesh_loc_size_ = -1, mesh_loc_nf_ = -1, mesh_loc_textured_ = -1;
    VertexArray empty_vao_, mesh_vao_;
    Buffer mesh_vbo_, mesh_ebo_;
    Texture mesh_tex_;
    GLsizei mesh_triangles_ = 0;
    bool mesh_textured_ = false;
    std::vector<std::unique_ptr<Layer>> layers_;
    int uploads_ = 0;
    GLint max_3d_texture_size_ = 0;
    long frames_ = 0, lose_context_at_frame_ = 0;
    Texture lut_, rays_;
    RayStartMap start_map_;  // rays made with rays_, cells rebuilt each frame
    Buffer start_buf_;       // its cells for the shader (binding 0)
    GLsizeiptr start_buf_bytes_ = 0;
    std::vector<float> ray_buf_;
    Intrinsics rays_K_;
    bool rays_valid_ = false;
    int target_w_ = 0, target_h_ = 0;
    Texture out_rgb_, out_grey_, out_depth_, out_cov_, mesh_rgb_, mesh_z_;
    Renderbuffer mesh_depth_;
    Framebuffer fbo_, mesh_fbo_;
};

}  // namespace

std::unique_ptr<FusionRenderer> make_gl_fusion_renderer(GlInfo* info) {
    auto r = std::make_unique<GlRenderer>();
    if (info) *info = r->info();
    return r;
}

std::unique_ptr<FusionRenderer> make_gl_renderer(const Volume& volume, const TransferFunction& tf, const LabelVolume* mask) {
    auto r = make_gl_fusion_renderer();
    r->add_layer(volume, tf, mask);
    return r;
}

GlInfo probe_gl() {
    gl::EglContext ctx;
    return ctx.info();
}

std::string check_gl_program(const std::string& vs, const std::string& fs) {
    gl::EglContext ctx;
    std::string log;
    const GLuint p = gl::build_program("check", vs, fs, &log);
    glDeleteProgram(p);
    return log;
}

std::vector<EmbeddedShader> embedded_shaders() {
    std::vector<EmbeddedShader> out;
    for (const auto& s : gl::shader_sources()) out.push_back({s.name, s.text});
    return out;
}

}  // namespace cf
