// The CPU ray caster: perspective rays from intrinsics and pose, trilinear sampling of a
// 16-bit quantised copy of the volume, front-to-back compositing, Lambert shading from a
// headlight, early ray termination and empty-space skipping over 8^3 bricks; each ray starts
// at the nearest visible 4^3-cell block projected onto its pixel. Each pixel is computed
// independently, so the output does not depend on the thread count.
#include <tbb/blocked_range.h>
#include <tbb/blocked_range2d.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>

#include "cortexfuse/core/renderer.hpp"
#include "huge_page_allocator.hpp"
#include "trilinear.hpp"

namespace cf {
namespace {

constexpr int kBrick = 8;      // brick edge in voxels for empty-space skipping
constexpr int kLutSize = 4096; // entries of the baked transfer function
constexpr int kBrickShift = 3;  // log2(kBrick)
static_assert((1 << kBrickShift) == kBrick);

constexpr int kMaxBrickDistance = 31;   // cap of the brick distance map, in bricks
constexpr int kSurfaceBisections = 2;  // before the secant step to the surface level (raycast.frag too)

/// Cell bits are stored brick by brick: a brick's 8^3 cells are 512 bits, 8 words, one cache
/// line, in (z, y, x) order inside it. A ray crosses a brick in a few steps and tests them all
/// on the same line (in voxel order every step along y or z read another line of a 2 MB map;
/// on the skin benchmark the gain was within the noise, 2026-11-23).
constexpr int kWordsPerBrick = kBrick * kBrick * kBrick / 64;
inline size_t cell_word(size_t brick, int k) { return brick * kWordsPerBrick + size_t(k & (kBrick - 1)); }
inline uint64_t cell_mask(int i, int j) { return uint64_t(1) << (((j & (kBrick - 1)) << kBrickShift) | (i & (kBrick - 1))); }
static_assert(kBrick * kBrick == 64, "one brick z-slice of cells is one 64-bit word");

/// The ray start map's unit: blocks of 4^3 cells, 8 to a brick, so that a ray starts within half
/// a brick of what it can show (empty space is still crossed brick by brick).
constexpr int kBlock = kBrick / 2;

}  // namespace

double sample_lattice_phase_mm(const RenderOptions& opt, const Eigen::Vector3d& camera_world_mm) {
    if (!opt.sample_anchor_world_mm) return 0.0;
    const auto& a = *opt.sample_anchor_world_mm;
    return std::fmod((Eigen::Vector3d(a[0], a[1], a[2]) - camera_world_mm).norm(), opt.sample_distance_mm);
}

// Separable: exact 1D transforms along x, then y, then z, each taking the max with the offset
// along that axis. Grids are ~32^3, so O(n^2) lines are fine.
std::vector<uint8_t> brick_chebyshev_distance(const std::vector<uint8_t>& visible, const std::array<int, 3>& n, int cap) {
    const size_t total = visible.size();
    std::vector<int> d(total);
    for (size_t i = 0; i < total; ++i) d[i] = visible[i] ? 0 : cap;
    const size_t stride[3] = {1, size_t(n[0]), size_t(n[0]) * size_t(n[1])};
    std::vector<int> line, out;
    for (int axis = 0; axis < 3; ++axis) {
        const int len = n[axis];
        line.resize(size_t(len));
        out.resize(size_t(len));
        for (size_t base = 0; base < total; ++base) {
            // `base` runs over every cell whose coordinate along `axis` is 0.
            if ((base / stride[axis]) % size_t(len) != 0) continue;
            for (int i = 0; i < len; ++i) line[size_t(i)] = d[base + size_t(i) * stride[axis]];
            for (int i = 0; i < len; ++i) {
                int best = cap;
                // Offsets beyond the cap cannot beat it.
                for (int j = std::max(0, i - cap); j <= std::min(len - 1, i + cap); ++j)
                    best = std::min(best, std::max(std::abs(i - j), line[size_t(j)]));
                out[size_t(i)] = best;
            }
            for (int i = 0; i < len; ++i) d[base + size_t(i) * stride[axis]] = out[size_t(i)];
        }
    }
    std::vector<uint8_t> r(total);
    for (size_t i = 0; i < total; ++i) r[i] = uint8_t(std::min(d[i], cap));
    return r;
}

namespace {

class CpuRenderer final : public Renderer {
public:
    CpuRenderer(const Volume& volume, const TransferFunction& tf, const LabelVolume* mask) {
        const auto range = robust_range(volume, mask);  // of the volume as given
        lo_ = range[0];
        hi_ = range[1];
        // A mask on thick slices: drawn from the finer copy (renderer.hpp), as the GL one does.
        const auto copy = masked_render_copy(volume, mask, range);
        const Volume& v = copy ? *copy : volume;
        if (copy) mask = nullptr;  // faded into the copy
        geom_ = v.geom;
        // Volume range for the table: values above the robust max saturate, which is what a
        // normalized transfer function wants anyway.
        const auto& d = geom_.dims;
        q_.resize(geom_.voxel_count());
        const double s = (kLutSize - 1) / (hi_ - lo_);
        for (size_t i = 0; i < q_.size(); ++i) {
            double x = (double(v.voxels[i]) - lo_) * s;
            if (mask && !mask->voxels[i]) x = 0;
            q_[i] = uint16_t(std::clamp(x, 0.0, double(kLutSize - 1)));
        }
        // Brick min/max including a one-voxel apron, since trilinear samples reach it.
        block_min_max(q_, d, kBrick, nb_, brick_min_, brick_max_);
        set_transfer_function(tf);
        // Index-space geometry.
        index_from_world_ = geom_.index_from_world().matrix().cast<float>();
        world_from_index_linear_ = geom_.world_from_index().linear().cast<float>();
    }

    void set_transfer_function(const TransferFunction& tf) override {
        baked_ = bake(tf, lo_, hi_, kLutSize);
        // Prefix maximum of opacity lets a brick be tested in O(1): visible iff any entry in
        // [min, max] has opacity > 0. A sparse table would do; a max over the span is cheap enough.
        std::vector<float> op(kLutSize);
        for (int i = 0; i < kLutSize; ++i) op[size_t(i)] = baked_.rgba[size_t(i)][3];
        brick_visible_.assign(brick_min_.size(), 0);
        // Range-max via a sparse table over the LUT (log levels).
        const int levels = 13;
        std::vector<std::vector<float>> st(levels, std::vector<float>(kLutSize));
        st[0] = op;
        for (int l = 1; l < levels; ++l)
            for (int i = 0; i + (1 << l) <= kLutSize; ++i)
                st[size_t(l)][size_t(i)] = std::max(st[size_t(l - 1)][size_t(i)], st[size_t(l - 1)][size_t(i + (1 << (l - 1)))]);
        for (size_t b = 0; b < brick_min_.size(); ++b) {
            const int a = brick_min_[b], c = brick_max_[b];
            if (a > c) continue;
            const int len = c - a + 1;
            const int l = 31 - __builtin_clz(unsigned(len));
            const float m = std::max(st[size_t(l)][size_t(a)], st[size_t(l)][size_t(c - (1 << l) + 1)]);
            brick_visible_[b] = m > 0.f;
        }
        // Third level, per trilinear cell inside visible bricks: one bit "some value between the
        // cell's 8 corner values has opacity > 0". A sample's table index lies between its
        // cell's corner values, so where the bit is 0 the sample's opacity is exactly 0: the ray
        // steps on without sampling, through the same positions, and the image is unchanged.
        // (Noise and tissue below the opacity ramp fill visible bricks; most samples there are
        // transparent.)
        std::vector<int> positive(kLutSize + 1, 0);  // positive[i]: entries < i with opacity > 0
        for (int i = 0; i < kLutSize; ++i) positive[size_t(i + 1)] = positive[size_t(i)] + (op[size_t(i)] > 0.f ? 1 : 0);
        cell_bits_ = cell_bits_where(brick_visible_, [&](uint16_t mn, uint16_t mx) { return positive[size_t(mx) + 1] - positive[mn] > 0; });
        // Gradient modulation in quantised units per voxel.
        grad_scale_ = float((hi_ - lo_) / (kLutSize - 1));
        // The box around everything visible: rays start there.
        std::array<int, 3> lo{nb_[0], nb_[1], nb_[2]}, hi{-1, -1, -1};
        for (int bz = 0; bz < nb_[2]; ++bz)
            for (int by = 0; by < nb_[1]; ++by)
                for (int bx = 0; bx < nb_[0]; ++bx)
                    if (brick_visible_[(size_t(bz) * nb_[1] + by) * nb_[0] + bx]) {
                        lo = {std::min(lo[0], bx), std::min(lo[1], by), std::min(lo[2], bz)};
                        hi = {std::max(hi[0], bx), std::max(hi[1], by), std::max(hi[2], bz)};
                    }
        // Empty space is crossed with a Chebyshev distance map over bricks: an empty brick at
        // distance d (in bricks) from the nearest visible one sits in a cube of (2d - 1)^3 empty
        // bricks, and the ray jumps to where it leaves that cube. Near the brain that is one
        // brick, far from it many at once (a fixed two-level hierarchy of 8^3 and 32^3 voxels
        // cost 17 % more; a finer map over 4^3 blocks built from the cell bits gained nothing).
        brick_distance_ = brick_chebyshev_distance(brick_visible_, nb_, kMaxBrickDistance);
        for (int a = 0; a < 3; ++a) {
            box_lo_[a] = hi[a] < 0 ? 0.f : float(std::max(0, lo[a] * kBrick - 1));
            box_hi_[a] = hi[a] < 0 ? -1.f : float(std::min(geom_.dims[a] - 1, (hi[a] + 1) * kBrick + 1)) - 1e-3f;
        }
        block_frontier_ = frontier_blocks(cell_bits_);
        alpha_step_for_ = -1.0;
        iso_q_ = -1.f;
        int iso_i = -1;
        for (int i = 0; i < kLutSize; ++i)
            if (baked_.rgba[size_t(i)][3] >= 0.5f) {
                iso_q_ = float(i) - 0.5f;
                iso_i = i;
                break;
            }
        // Surface-only rendering (registration) shows the first sample at or above the surface
        // level, so its empty space is wider: every cell whose 8 corners all lie below the level
        // (a trilinear sample there is below it too). Tissue under the opacity ramp but below
        // the level (partial volume at the brain's edge, sulcal CSF) is stepped over instead of
        // sampled; the pictures are the same bit for bit.
        iso_cell_bits_.clear();
        iso_brick_distance_.clear();
        if (iso_i >= 0) {
            std::vector<uint8_t> iso_visible(brick_max_.size(), 0);
            for (size_t b = 0; b < brick_max_.size(); ++b) iso_visible[b] = brick_min_[b] <= brick_max_[b] && brick_max_[b] >= iso_i;
            iso_brick_distance_ = brick_chebyshev_distance(iso_visible, nb_, kMaxBrickDistance);
            const uint16_t level = uint16_t(iso_i);
            iso_cell_bits_ = cell_bits_where(iso_visible, [&](uint16_t, uint16_t mx) { return mx >= level; });
            iso_block_frontier_ = frontier_blocks(iso_cell_bits_);
        }
    }

    /// The frontier of the 4^3-cell blocks holding a cell whose bit is set in `bits` (a block
    /// grid of twice the bricks along each axis; blocks past the volume's edge stay empty).
    std::vector<std::array<int, 3>> frontier_blocks(const std::vector<uint64_t>& bits) const {
        const std::array<int, 3> nblk{nb_[0] * 2, nb_[1] * 2, nb_[2] * 2};
        std::vector<uint8_t> visible(static_cast<size_t>(nblk[0]) * nblk[1] * nblk[2], 0);
        for (int bz = 0; bz < nb_[2]; ++bz)
            for (int by = 0; by < nb_[1]; ++by)
                for (int bx = 0; bx < nb_[0]; ++bx) {
                    const uint64_t* w = bits.data() + ((size_t(bz) * nb_[1] + by) * nb_[0] + bx) * kWordsPerBrick;
                    for (int sz = 0; sz < 2; ++sz) {
                        // A brick's word k is its z-slice k; bit (j << 3) | i is cell (i, j) in it.
                        const uint64_t slab = w[sz * 4] | w[sz * 4 + 1] | w[sz * 4 + 2] | w[sz * 4 + 3];
                        if (!slab) continue;
                        for (int sy = 0; sy < 2; ++sy)
                            for (int sx = 0; sx < 2; ++sx)
                                if (slab & (uint64_t(0x0F0F0F0F) << (sx * kBlock + sy * 32)))
                                    visible[(size_t(2 * bz + sz) * nblk[1] + size_t(2 * by + sy)) * nblk[0] + size_t(2 * bx + sx)] = 1;
                    }
                }
        return frontier_bricks(visible, nblk);
    }

    /// The start map for this frame: false when rays must start at the box (the camera inside
    /// the box around the visible bricks, or a frontier block reaching behind it).
    bool start_map_for(const Pose& T, const std::vector<std::array<int, 3>>& frontier, const Eigen::Vector3f& cam_index) {
        bool inside = true;
        for (int a = 0; a < 3; ++a) inside = inside && cam_index[a] >= box_lo_[a] - 1.f && cam_index[a] <= box_hi_[a] + 1.f;
        if (inside || frontier.empty()) return false;
        start_map_.clear();
        return start_map_.add(T * geom_.world_from_index().matrix(), frontier, kBlock);
    }

    /// One bit per trilinear cell (brick-major) inside the bricks marked in `bricks`: set where
    /// `may_show(min, max)` of the cell's 8 corner values says a sample there can show.
    template <class MayShow>
    std::vector<uint64_t> cell_bits_where(const std::vector<uint8_t>& bricks, MayShow may_show) const {
        const auto& d = geom_.dims;
        std::vector<uint64_t> bits(brick_min_.size() * kWordsPerBrick, 0);
        tbb::parallel_for(0, nb_[2], [&](int bz) {
            for (int by = 0; by < nb_[1]; ++by)
                for (int bx = 0; bx < nb_[0]; ++bx) {
                    const size_t brick = (size_t(bz) * nb_[1] + by) * nb_[0] + bx;
                    if (!bricks[brick]) continue;
                    for (int k = bz * kBrick; k < std::min(d[2] - 1, (bz + 1) * kBrick); ++k)
                        for (int j = by * kBrick; j < std::min(d[1] - 1, (by + 1) * kBrick); ++j) {
                            const uint16_t* p0 = q_.data() + geom_.linear(0, j, k);
                            const uint16_t* p1 = p0 + d[0];
                            const uint16_t* p2 = p0 + size_t(d[0]) * d[1];
                            const uint16_t* p3 = p2 + d[0];
                            // The brick's words belong to this task alone (brick-major layout).
                            for (int i = bx * kBrick; i < std::min(d[0] - 1, (bx + 1) * kBrick); ++i) {
                                const uint16_t mn = std::min({p0[i], p0[i + 1], p1[i], p1[i + 1], p2[i], p2[i + 1], p3[i], p3[i + 1]});
                                const uint16_t mx = std::max({p0[i], p0[i + 1], p1[i], p1[i + 1], p2[i], p2[i + 1], p3[i], p3[i + 1]});
                                if (may_show(mn, mx)) bits[cell_word(brick, k)] |= cell_mask(i, j);
                            }
                        }
                }
        });
        return bits;
    }

    const char* name() const override { return "cpu"; }

    void render(const Intrinsics& K, const Pose& T, const RenderOptions& opt, RenderImage& out) override {
        if (alpha_step_for_ != opt.sample_distance_mm) {
            alpha_step_.resize(kLutSize);
            for (int i = 0; i < kLutSize; ++i) {
                const double a = baked_.rgba[size_t(i)][3];
                alpha_step_[size_t(i)] = a >= 1.0 ? 1.f : float(1.0 - std::pow(1.0 - a, opt.sample_distance_mm));
            }
            alpha_step_for_ = opt.sample_distance_mm;
        }
        if (rays_.size() != size_t(K.width) * K.height || K.fx != rays_K_.fx || K.fy != rays_K_.fy || K.cx != rays_K_.cx ||
            K.cy != rays_K_.cy || K.distortion != rays_K_.distortion || K.width != rays_K_.width) {
            rays_ = pixel_rays(K);
            for (auto& r : rays_) r = r.normalized();  // cast() wants unit directions
            rays_K_ = K;
            start_map_.set_rays(rays_, K.width);
        }
        out.width = K.width;
        out.height = K.height;
        const size_t n = size_t(K.width) * K.height;
        out.grey.resize(n);
        out.coverage.resize(n);
        if (opt.want_rgb) out.rgb.resize(n * 3); else out.rgb.clear();
        if (opt.want_depth) out.depth_mm.resize(n); else out.depth_mm.clear();

        const Eigen::Matrix4d Tw = T.inverse();  // world_from_camera
        Frame f;
        f.R_world_from_camera = Tw.topLeftCorner<3, 3>().cast<float>();
        f.cam_index = (index_from_world_ * Tw.topRightCorner<3, 1>().cast<float>().homogeneous()).head<3>();
        f.cam_z_axis_world = T.block<1, 3>(2, 0).cast<float>();  // row 2 of R: camera z in world
        f.cam_t_z = float(T(2, 3));
        f.light = opt.light;
        f.light_world = (f.R_world_from_camera *
                         Eigen::Vector3d(opt.light_direction_camera[0], opt.light_direction_camera[1], opt.light_direction_camera[2])
                             .cast<float>())
                            .normalized();
        f.cam_world = Tw.topRightCorner<3, 1>().cast<float>();
        f.light_pos_world = (Tw * Eigen::Vector4d(opt.light_position_camera_mm[0], opt.light_position_camera_mm[1],
                                                  opt.light_position_camera_mm[2], 1.0))
                                .head<3>()
                                .cast<float>();
        f.phase = float(sample_lattice_phase_mm(opt, Tw.topRightCorner<3, 1>()));
        const bool iso_skip = opt.surface_only && !iso_cell_bits_.empty();
        f.brick_distance = iso_skip ? iso_brick_distance_.data() : brick_distance_.data();
        f.cell_bits = iso_skip ? iso_cell_bits_.data() : cell_bits_.data();
        f.start_map = opt.ray_start_map && start_map_for(T, iso_skip ? iso_block_frontier_ : block_frontier_, f.cam_index) ? &start_map_ : nullptr;
        const int w = K.width;
        // Square-ish tiles: neighbouring rays in both directions read the same bricks, which
        // a row strip of the same pixel count does not (fewer cache misses on a 32 MB volume).
        if (opt.ray_mask && opt.ray_mask->size() != n) throw std::invalid_argument("render: ray_mask is not width*height");
        const uint8_t* mask = opt.ray_mask ? opt.ray_mask->data() : nullptr;
        auto body = [&](const tbb::blocked_range2d<int>& tile) {
            for (int v = tile.rows().begin(); v < tile.rows().end(); ++v)
                for (int u = tile.cols().begin(); u < tile.cols().end(); ++u) {
                    const size_t px = size_t(v) * w + u;
                    if (mask && !mask[px]) {
                        skip(px, out);
                        continue;
                    }
                    cast(f, px, opt, out);
                }
        };
        const tbb::blocked_range2d<int> all(0, K.height, 8, 0, K.width, 16);
        if (opt.threads > 0) {
            // The arena is kept between frames: making one per frame costs a registration loop
            // a few percent at small image sizes.
            if (!arena_ || arena_threads_ != opt.threads) {
                arena_ = std::make_unique<tbb::task_arena>(opt.threads);
                arena_threads_ = opt.threads;
            }
            arena_->execute([&] { tbb::parallel_for(all, body); });
        } else {
            tbb::parallel_for(all, body);
        }
    }

private:
    struct Frame {
        Eigen::Matrix3f R_world_from_camera;
        Eigen::Vector3f cam_index;
        Eigen::Vector3f cam_world;
        Eigen::Vector3f cam_z_axis_world;
        float cam_t_z;
        Light light;
        Eigen::Vector3f light_world;      // unit, scene towards the light (Light::distant)
        Eigen::Vector3f light_pos_world;  // the lamp, world mm (Light::point)
        const uint8_t* brick_distance;  // the empty-space maps this frame steps with (borrowed)
        const uint64_t* cell_bits;
        const RayStartMap* start_map;  // where rays may start (borrowed); null: at the box
        float phase = 0.f;             // the sample lattice's offset, mm (RenderOptions::sample_anchor_world_mm)
    };

    // Trilinear sample of the quantised volume at index-space p (must be inside [0, d-1)).
    inline float sample(float x, float y, float z) const { return trilinear_u16(q_.data(), geom_.dims, x, y, z); }

    /// sample(p + e_a) - sample(p - e_a) along each axis a, clamped as sample_clamped (the
    /// shared-weight form inside, trilinear.hpp).
    inline Eigen::Vector3f central_difference(float x, float y, float z) const {
        const auto& d = geom_.dims;
        if (!(x >= 1.f && y >= 1.f && z >= 1.f && x <= float(d[0] - 2) - 1e-3f && y <= float(d[1] - 2) - 1e-3f &&
              z <= float(d[2] - 2) - 1e-3f))
            return {sample_clamped(x + 1, y, z) - sample_clamped(x - 1, y, z), sample_clamped(x, y + 1, z) - sample_clamped(x, y - 1, z),
                    sample_clamped(x, y, z + 1) - sample_clamped(x, y, z - 1)};
        return central_difference_u16(q_.data(), d, x, y, z);
    }

    inline float sample_clamped(float x, float y, float z) const {
        const auto& d = geom_.dims;
        x = std::clamp(x, 0.f, float(d[0] - 1) - 1e-3f);
        y = std::clamp(y, 0.f, float(d[1] - 1) - 1e-3f);
        z = std::clamp(z, 0.f, float(d[2] - 1) - 1e-3f);
        return sample(x, y, z);
    }

    /// A pixel left out by RenderOptions::ray_mask: no hit.
    static void skip(size_t px, RenderImage& out) {
        out.grey[px] = 0.f;
        out.coverage[px] = 0;
        if (!out.rgb.empty()) out.rgb[px * 3 + 0] = out.rgb[px * 3 + 1] = out.rgb[px * 3 + 2] = 0;
        if (!out.depth_mm.empty()) out.depth_mm[px] = 0.f;
    }

    void cast(const Frame& f, size_t px, const RenderOptions& opt, RenderImage& out) const {
        const Eigen::Vector3f& dir_cam = rays_[px];  // unit length
        const Eigen::Vector3f dir_world = f.R_world_from_camera * dir_cam;
        const Eigen::Vector3f dir_index = index_from_world_.topLeftCorner<3, 3>() * dir_world;  // per mm
        const Eigen::Vector3f& o = f.cam_index;
        // Clip the ray against the volume box [0, d-1) in index space.
        float t0 = 0.f, t1 = std::numeric_limits<float>::max();
        for (int a = 0; a < 3; ++a) {
            const float lo = box_lo_[a], hi = box_hi_[a];
            if (std::abs(dir_index[a]) < 1e-12f) {
                if (o[a] < lo || o[a] > hi) { t1 = -1.f; break; }
                continue;
            }
            float ta = (lo - o[a]) / dir_index[a], tb = (hi - o[a]) / dir_index[a];
            if (ta > tb) std::swap(ta, tb);
            t0 = std::max(t0, ta);
            t1 = std::min(t1, tb);
        }
        float r = 0, g = 0, b = 0, alpha = 0, depth = 0;
        bool hit = false, refined = false;
        const float step = float(opt.sample_distance_mm);
        const float inv_step = 1.f / step;
        // Reciprocals once a ray: a jump needs three divisions otherwise.
        const float inv_dir[3] = {1.f / dir_index[0], 1.f / dir_index[1], 1.f / dir_index[2]};
        const float term = float(opt.early_termination_alpha);
        const float cov = float(opt.coverage_alpha);
        // (Without a surface level, no opacity reaching 0.5, the first visible sample is shown.)
        const bool surface_only = opt.surface_only;
        if (t1 > t0) {
            // Samples on a fixed lattice t = phase + n * step so that moving the camera slightly
            // does not make the sampling jump around (a registration loop moves it every frame;
            // the phase keeps the lattice put near an anchor, RenderOptions::sample_anchor_world_mm).
            // A ray enters the visible cells through a frontier block, and a point at camera
            // depth z lies at t = z / dir_z along it: no lattice point before that can show
            // anything, so the ray starts there (the same lattice, the same picture).
            // (0.05 mm earlier for rounding.)
            if (f.start_map) t0 = std::max(t0, f.start_map->start_z(px) / dir_cam.z() - 0.05f);
            const float phase = f.phase;
            float t = phase + std::ceil((t0 - phase) / step) * step;
            const float lut_scale = 1.f;
            const bool grad_op = baked_.uses_gradient();
            while (t <= t1) {
                const float x0 = o.x() + t * dir_index.x(), y0 = o.y() + t * dir_index.y(), z0 = o.z() + t * dir_index.z();
                // Inside the box the coordinates are > -1, so int() is >= 0 and a shift divides.
                const int bi[3] = {int(x0) >> kBrickShift, int(y0) >> kBrickShift, int(z0) >> kBrickShift};
                const size_t brick = (size_t(bi[2]) * unsigned(nb_[1]) + unsigned(bi[1])) * unsigned(nb_[0]) + unsigned(bi[0]);
                const int dist = f.brick_distance[brick];
                if (dist) {
                    // Jump to where the ray leaves the empty cube of bricks [bi - (dist - 1),
                    // bi + dist) around this one, on the sample lattice.
                    float texit = t1;
                    const float p[3] = {x0, y0, z0};
                    for (int a = 0; a < 3; ++a) {
                        if (dir_index[a] > 1e-12f) texit = std::min(texit, t + (float((bi[a] + dist) << kBrickShift) - p[a]) * inv_dir[a]);
                        else if (dir_index[a] < -1e-12f) texit = std::min(texit, t + (float((bi[a] - dist + 1) << kBrickShift) - p[a]) * inv_dir[a]);
                    }
                    const float tn = phase + std::ceil((texit - phase) * inv_step + 1e-4f) * step;
                    t = std::max(tn, t + step);
                    continue;
                }
                {
                    const int ix = int(x0), iy = int(y0);
                    if (!(f.cell_bits[cell_word(brick, int(z0))] & cell_mask(ix, iy))) {  // transparent cell (or below the surface level): nothing shown here
                        t += step;
                        continue;
                    }
                }
                const float s = sample(x0, y0, z0) * lut_scale;
                const int li = int(s + 0.5f);
                const auto& e = baked_.rgba[size_t(li)];
                float a = e[3];
                // Surface only: nothing before the first crossing of the surface level counts.
                if (a > 0.f && surface_only && !(s >= iso_q_)) a = 0.f;
                if (a > 0.f) {
                    float x = x0, y = y0, z = z0, t_at = t;
                    if (!refined && iso_q_ >= 0.f && s >= iso_q_) {
                        // The first crossing of the surface level lies between the last lattice
                        // sample and this one: two bisection steps bracket it to a quarter of a
                        // step, and a secant step places it there, where the trilinear field is
                        // close to linear. Without this, depth and shading jump with the camera
                        // in sample-distance steps and the similarity landscape turns jagged.
                        // (Six bisection steps made a registration's CPU time ~17 % longer; a
                        // secant over the whole step lost ~0.1 mm on the seed protocol.)
                        refined = true;
                        float ta = t - step, tb = t, sb = s;
                        float sa = sample_clamped(o.x() + ta * dir_index.x(), o.y() + ta * dir_index.y(), o.z() + ta * dir_index.z());
                        for (int it = 0; it < kSurfaceBisections; ++it) {
                            const float tm = 0.5f * (ta + tb);
                            const float sm = sample_clamped(o.x() + tm * dir_index.x(), o.y() + tm * dir_index.y(), o.z() + tm * dir_index.z());
                            if (sm >= iso_q_)
                                tb = tm, sb = sm;
                            else
                                ta = tm, sa = sm;
                        }
                        const float frac = sb - sa > 1e-6f ? std::clamp((iso_q_ - sa) / (sb - sa), 0.f, 1.f) : 1.f;
                        const float tc = ta + frac * (tb - ta);
                        t_at = tc;
                        x = o.x() + tc * dir_index.x();
                        y = o.y() + tc * dir_index.y();
                        z = o.z() + tc * dir_index.z();
                    }
                    // Opacity per mm -> per step.
                    float shade = 1.f;
                    if (opt.shading || grad_op) {
                        // Index-space gradient to world: g_world = A^-T g_index (A = world_from_index linear).
                        // Index-space gradient to world: g_world = A^-T g_index (A = world_from_index linear).
                        const Eigen::Vector3f gi = central_difference(x, y, z) * 0.5f;
                        const Eigen::Vector3f gw = index_from_world_.topLeftCorner<3, 3>().transpose() * gi;
                        const float gn = gw.norm();
                        if (grad_op) a *= baked_.gradient_factor(gn * grad_scale_);
                        if (opt.shading) {
                            // Two-sided Lambert, |cos|: the gradient's sign depends on the
                            // transfer function (bright inside or outside). For the distant light
                            // too: a one-sided max(0, n.L) with the normal turned to the camera
                            // lost on the wide capture test and gained nothing on the seed
                            // protocol (2026-11-23, docs/registration.md), so it stays two-sided.
                            Eigen::Vector3f light = f.light == Light::distant ? f.light_world : dir_world;
                            if (f.light == Light::point) {
                                // From the sample to the lamp; at the lamp itself, the ray's.
                                const Eigen::Vector3f to_lamp = f.light_pos_world - (f.cam_world + t_at * dir_world);
                                const float d = to_lamp.norm();
                                if (d > 1e-3f) light = to_lamp / d;
                            }
                            const float lambert = gn > 1e-6f ? std::abs(gw.dot(light)) / gn : 0.f;
                            shade = float(opt.ambient) + float(opt.diffuse) * lambert;
                        }
                    }
                    // Opacity per mm -> per step (table for the unmodulated case).
                    const float a_step = surface_only ? 1.f
                                         : grad_op    ? (a >= 1.f ? 1.f : 1.f - std::pow(1.f - a, step))
                                                      : alpha_step_[size_t(li)];
                    const float wgt = (1.f - alpha) * a_step;
                    r += wgt * e[0] * shade;
                    g += wgt * e[1] * shade;
                    b += wgt * e[2] * shade;
                    alpha += wgt;
                    if (!hit && alpha >= cov) {
                        hit = true;
                        const Eigen::Vector3f pw = f.cam_world + t_at * dir_world;
                        depth = f.cam_z_axis_world.dot(pw) + f.cam_t_z;
                    }
                    if (alpha >= term) break;
                }
                t += step;
            }
        }
        r = std::min(r, 1.f);
        g = std::min(g, 1.f);
        b = std::min(b, 1.f);
        out.grey[px] = 0.299f * r + 0.587f * g + 0.114f * b;
        out.coverage[px] = hit ? 1 : 0;
        if (!out.rgb.empty()) {
            out.rgb[px * 3 + 0] = uint8_t(r * 255.f + 0.5f);
            out.rgb[px * 3 + 1] = uint8_t(g * 255.f + 0.5f);
            out.rgb[px * 3 + 2] = uint8_t(b * 255.f + 0.5f);
        }
        if (!out.depth_mm.empty()) out.depth_mm[px] = hit ? depth : 0.f;
    }

    VolumeGeometry geom_;
    double lo_ = 0, hi_ = 1;
    std::vector<uint16_t, detail::HugePageAllocator<uint16_t>> q_;  // 2 MiB pages where the kernel agrees
    std::array<int, 3> nb_{};
    std::vector<uint16_t> brick_min_, brick_max_;
    std::vector<uint8_t> brick_visible_;
    std::vector<uint64_t> cell_bits_;  // per voxel cell (i, j, k) = floor of a sample: 1 if it may be opaque (brick-major)
    std::vector<uint8_t> brick_distance_;  // per brick: Chebyshev distance in bricks to a visible one (0: visible)
    std::vector<uint64_t> iso_cell_bits_;      // as cell_bits_, for "may reach the surface level" (surface_only)
    std::vector<uint8_t> iso_brick_distance_;  // as brick_distance_, to a brick reaching the surface level
    std::unique_ptr<tbb::task_arena> arena_;  // owned; made for arena_threads_ threads
    int arena_threads_ = 0;
    std::array<float, 3> box_lo_{}, box_hi_{};  // index-space box around all visible bricks
    std::vector<float> alpha_step_;            // opacity per sample step, per LUT entry
    double alpha_step_for_ = -1.0;              // the step alpha_step_ was made for
    float iso_q_ = -1.f;  // quantised level where opacity reaches 0.5: the surface hits are refined to it
    BakedTransferFunction baked_;
    float grad_scale_ = 1.f;
    Eigen::Matrix4f index_from_world_;
    Eigen::Matrix3f world_from_index_linear_;
    std::vector<Eigen::Vector3f> rays_;
    Intrinsics rays_K_;
    // Frontier 4^3-cell blocks of the visible / surface-level cells (4x the bricks' corner
    // projections a frame; rays start within half a brick of the surface: -11 % CPU time on
    // the skin benchmark, also at registration's 128x85 surface-only frames, 2026-11-23).
    std::vector<std::array<int, 3>> block_frontier_, iso_block_frontier_;
    RayStartMap start_map_;  // rebuilt each frame
};

}  // namespace

std::unique_ptr<Renderer> make_cpu_renderer(const Volume& volume, const TransferFunction& tf, const LabelVolume* mask) {
    if (mask && !mask->geom.same_grid(volume.geom))
        throw std::invalid_argument("make_cpu_renderer: mask is not on the volume's grid");
    return std::make_unique<CpuRenderer>(volume, tf, mask);
}

}  // namespace cf
