// The ray start map shared by the CPU and GLSL ray casters (renderer.hpp).
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include <tbb/parallel_for.h>

#include "cortexfuse/core/renderer.hpp"

namespace cf {

void block_min_max(std::span<const uint16_t> q, const std::array<int, 3>& d, int B, std::array<int, 3>& nb,
                   std::vector<uint16_t>& bmin, std::vector<uint16_t>& bmax) {
    nb = {(d[0] + B - 1) / B, (d[1] + B - 1) / B, (d[2] + B - 1) / B};
    const size_t n = size_t(nb[0]) * size_t(nb[1]) * size_t(nb[2]);
    bmin.assign(n, std::numeric_limits<uint16_t>::max());
    bmax.assign(n, 0);
    const size_t sy = size_t(d[0]), sz = sy * size_t(d[1]);
    tbb::parallel_for(0, nb[2], [&](int bz) {
        for (int by = 0; by < nb[1]; ++by)
            for (int bx = 0; bx < nb[0]; ++bx) {
                uint16_t mn = std::numeric_limits<uint16_t>::max(), mx = 0;
                for (int k = std::max(0, bz * B - 1); k <= std::min(d[2] - 1, (bz + 1) * B); ++k)
                    for (int j = std::max(0, by * B - 1); j <= std::min(d[1] - 1, (by + 1) * B); ++j) {
                        const uint16_t* row = q.data() + size_t(k) * sz + size_t(j) * sy;
                        for (int i = std::max(0, bx * B - 1); i <= std::min(d[0] - 1, (bx + 1) * B); ++i) {
                            mn = std::min(mn, row[i]);
                            mx = std::max(mx, row[i]);
                        }
                    }
                const size_t b = (size_t(bz) * size_t(nb[1]) + size_t(by)) * size_t(nb[0]) + size_t(bx);
                bmin[b] = mn;
                bmax[b] = mx;
            }
    });
}

std::vector<std::array<int, 3>> frontier_bricks(const std::vector<uint8_t>& visible, const std::array<int, 3>& n) {
    std::vector<std::array<int, 3>> out;
    auto vis = [&](int x, int y, int z) {
        if (x < 0 || y < 0 || z < 0 || x >= n[0] || y >= n[1] || z >= n[2]) return false;
        return visible[(size_t(z) * size_t(n[1]) + size_t(y)) * size_t(n[0]) + size_t(x)] != 0;
    };
    for (int bz = 0; bz < n[2]; ++bz)
        for (int by = 0; by < n[1]; ++by)
            for (int bx = 0; bx < n[0]; ++bx) {
                if (!vis(bx, by, bz)) continue;
                bool inner = true;
                for (int dz = -1; dz <= 1 && inner; ++dz)
                    for (int dy = -1; dy <= 1 && inner; ++dy)
                        for (int dx = -1; dx <= 1 && inner; ++dx) inner = vis(bx + dx, by + dy, bz + dz);
                if (!inner) out.push_back({bx, by, bz});
            }
    // Grouped for RayStartMap::add, which tests a group's box before its bricks.
    std::stable_sort(out.begin(), out.end(), [](const std::array<int, 3>& a, const std::array<int, 3>& b) {
        return start_map_group(a) < start_map_group(b);
    });
    return out;
}

void RayStartMap::set_rays(const std::vector<Eigen::Vector3f>& rays, int width) {
    float xlo = std::numeric_limits<float>::infinity(), ylo = xlo, xhi = -xlo, yhi = -xlo;
    for (const auto& r : rays) {
        const float x = r.x() / r.z(), y = r.y() / r.z();
        xlo = std::min(xlo, x), xhi = std::max(xhi, x), ylo = std::min(ylo, y), yhi = std::max(yhi, y);
    }
    if (rays.empty()) {
        nx_ = ny_ = 0;
        return;
    }
    // About one cell per 4x4 pixels: finer costs more splatting, coarser starts rays earlier.
    const float cell = std::max((xhi - xlo) / float(std::max(1, width / 4)), 1e-6f);
    inv_cell_ = 1.f / cell;
    x0_ = xlo;
    y0_ = ylo;
    nx_ = int(std::floor((xhi - xlo) * inv_cell_)) + 1;
    ny_ = int(std::floor((yhi - ylo) * inv_cell_)) + 1;
    z_.assign(size_t(nx_) * size_t(ny_), 0.f);
    cell_.resize(rays.size());
    for (size_t i = 0; i < rays.size(); ++i) {
        const float x = rays[i].x() / rays[i].z(), y = rays[i].y() / rays[i].z();
        const int cx = std::clamp(int(std::floor((x - xlo) * inv_cell_)), 0, nx_ - 1);
        const int cy = std::clamp(int(std::floor((y - ylo) * inv_cell_)), 0, ny_ - 1);
        cell_[i] = uint32_t(cy * nx_ + cx);
    }
}

void RayStartMap::clear() { std::fill(z_.begin(), z_.end(), std::numeric_limits<float>::infinity()); }

bool RayStartMap::add(const Eigen::Matrix4d& T_camera_from_index, const std::vector<std::array<int, 3>>& frontier, int edge) {
    if (nx_ == 0) return false;
    // Corners are affine in the brick's index: the camera-frame image of brick b's corner c is
    // origin + b.x * ex + b.y * ey + b.z * ez + (c's offsets along ex, ey, ez), with ex, ey, ez the
    // images of one brick edge along each axis. Eight adds a corner instead of a 4x4 product:
    // a registration renders small frames, where the splat is a fixed cost per frame.
    const Eigen::Matrix4f M = T_camera_from_index.cast<float>();
    const Eigen::Vector3f origin = M.col(3).head<3>();
    const Eigen::Vector3f ex = M.col(0).head<3>() * float(edge), ey = M.col(1).head<3>() * float(edge), ez = M.col(2).head<3>() * float(edge);
    std::array<Eigen::Vector3f, 8> offset;
    for (int c = 0; c < 8; ++c) offset[size_t(c)] = float(c & 1) * ex + float((c >> 1) & 1) * ey + float((c >> 2) & 1) * ez;

    // The cells under the image of the box with corners p0 + corner_offset, and its nearest
    // depth; false when a corner is behind the camera. The perspective image of a convex box in
    // front of the camera lies inside the box of its corners' images; a little wider for the
    // rounding of the rays' coordinates.
    struct Cells {
        int cx0, cx1, cy0, cy1;
        float zmin;
    };
    auto project = [&](const Eigen::Vector3f& p0, const std::array<Eigen::Vector3f, 8>& corner_offset, Cells& out) {
        float zmin = std::numeric_limits<float>::infinity();
        float xlo = zmin, ylo = zmin, xhi = -zmin, yhi = -zmin;
        for (size_t c = 0; c < 8; ++c) {
            const Eigen::Vector3f pc = p0 + corner_offset[c];
            if (!(pc.z() > 1e-3f)) return false;
            zmin = std::min(zmin, pc.z());
            const float inv_z = 1.f / pc.z();
            const float x = pc.x() * inv_z, y = pc.y() * inv_z;
            xlo = std::min(xlo, x), xhi = std::max(xhi, x), ylo = std::min(ylo, y), yhi = std::max(yhi, y);
        }
        xlo -= 1e-4f, ylo -= 1e-4f, xhi += 1e-4f, yhi += 1e-4f;
        // In float, so that a box far off the grid does not overflow an int.
        out.cx0 = int(std::clamp(std::floor((xlo - x0_) * inv_cell_), -1.f, float(nx_)));
        out.cx1 = int(std::clamp(std::floor((xhi - x0_) * inv_cell_), -1.f, float(nx_)));
        out.cy0 = int(std::clamp(std::floor((ylo - y0_) * inv_cell_), -1.f, float(ny_)));
        out.cy1 = int(std::clamp(std::floor((yhi - y0_) * inv_cell_), -1.f, float(ny_)));
        out.cx0 = std::max(out.cx0, 0), out.cx1 = std::min(out.cx1, nx_ - 1);
        out.cy0 = std::max(out.cy0, 0), out.cy1 = std::min(out.cy1, ny_ - 1);
        out.zmin = zmin;
        return true;
    };

    // Bricks go in groups (start_map_group(); frontier_bricks() makes a group's bricks
    // consecutive). A group's box holds its bricks, so its image holds theirs and its nearest
    // depth is no farther than theirs: a group whose box misses the grid, or whose cells all
    // start nearer already, changes nothing and is skipped whole. Groups go nearest first, so
    // the back of the brain and the walls of deep sulci are mostly skipped: a registration's
    // cropped frame looks down a column of the brain through a few thousand frontier bricks,
    // of which only the front layer sets a start. Any order of the bricks gives the same map.
    groups_.clear();
    for (size_t i = 0; i < frontier.size();) {
        const uint64_t key = start_map_group(frontier[i]);
        std::array<int, 3> lo = frontier[i], hi = frontier[i];
        size_t j = i;
        for (; j < frontier.size() && start_map_group(frontier[j]) == key; ++j)
            for (size_t a = 0; a < 3; ++a) lo[a] = std::min(lo[a], frontier[j][a]), hi[a] = std::max(hi[a], frontier[j][a]);
        const Eigen::Vector3f p0 = origin + float(lo[0]) * ex + float(lo[1]) * ey + float(lo[2]) * ez;
        std::array<Eigen::Vector3f, 8> box;
        for (size_t c = 0; c < 8; ++c)
            box[c] = float((c & 1) ? hi[0] - lo[0] + 1 : 0) * ex + float((c & 2) ? hi[1] - lo[1] + 1 : 0) * ey +
                     float((c & 4) ? hi[2] - lo[2] + 1 : 0) * ez;
        Cells g{};
        Group group{i, j, -std::numeric_limits<float>::infinity(), 0, -1, 0, -1};
        // A box reaching behind the camera: its bricks are each checked (first, to stop early).
        if (project(p0, box, g)) {
            if (g.cx0 > g.cx1 || g.cy0 > g.cy1) {
                i = j;
                continue;
            }
            group = {i, j, g.zmin, g.cx0, g.cx1, g.cy0, g.cy1};
        }
        groups_.push_back(group);
        i = j;
    }
    std::sort(groups_.begin(), groups_.end(), [](const Group& a, const Group& b) { return a.zmin < b.zmin; });
    for (const Group& g : groups_) {
        if (g.cx0 <= g.cx1) {
            bool changes = false;
            for (int cy = g.cy0; cy <= g.cy1 && !changes; ++cy)
                for (int cx = g.cx0; cx <= g.cx1 && !changes; ++cx) changes = z_[size_t(cy) * size_t(nx_) + size_t(cx)] > g.zmin;
            if (!changes) continue;
        }
        for (size_t i = g.begin; i < g.end; ++i) {
            const auto& b = frontier[i];
            Cells c{};
            if (!project(origin + float(b[0]) * ex + float(b[1]) * ey + float(b[2]) * ez, offset, c))
                return false;  // reaches behind the camera: no bound this frame
            for (int cy = c.cy0; cy <= c.cy1; ++cy)
                for (int cx = c.cx0; cx <= c.cx1; ++cx) {
                    float& z = z_[size_t(cy) * size_t(nx_) + size_t(cx)];
                    z = std::min(z, c.zmin);
                }
        }
    }
    return true;
}

}  // namespace cf
