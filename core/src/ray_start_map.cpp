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
    for (const auto& b : frontier) {
        const Eigen::Vector3f p0 = origin + float(b[0]) * ex + float(b[1]) * ey + float(b[2]) * ez;
        float zmin = std::numeric_limits<float>::infinity();
        float xlo = zmin, ylo = zmin, xhi = -zmin, yhi = -zmin;
        for (int c = 0; c < 8; ++c) {
            const Eigen::Vector3f pc = p0 + offset[size_t(c)];
            if (!(pc.z() > 1e-3f)) return false;  // reaches behind the camera: no bound this frame
            zmin = std::min(zmin, pc.z());
            const float inv_z = 1.f / pc.z();
            const float x = pc.x() * inv_z, y = pc.y() * inv_z;
            xlo = std::min(xlo, x), xhi = std::max(xhi, x), ylo = std::min(ylo, y), yhi = std::max(yhi, y);
        }
        // The perspective image of a convex brick in front of the camera lies inside the box of
        // its corners' images; a little wider for the rounding of the rays' coordinates.
        xlo -= 1e-4f, ylo -= 1e-4f, xhi += 1e-4f, yhi += 1e-4f;
        const int cx0 = std::max(0, int(std::floor((xlo - x0_) * inv_cell_)));
        const int cx1 = std::min(nx_ - 1, int(std::floor((xhi - x0_) * inv_cell_)));
        const int cy0 = std::max(0, int(std::floor((ylo - y0_) * inv_cell_)));
        const int cy1 = std::min(ny_ - 1, int(std::floor((yhi - y0_) * inv_cell_)));
        for (int cy = cy0; cy <= cy1; ++cy)
            for (int cx = cx0; cx <= cx1; ++cx) {
                float& z = z_[size_t(cy) * size_t(nx_) + size_t(cx)];
                z = std::min(z, zmin);
            }
    }
    return true;
}

}  // namespace cf
