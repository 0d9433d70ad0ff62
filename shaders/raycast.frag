#version 450 core
// The ray caster of core/src/raycast_cpu.cpp, for NLAYERS co-registered volumes (defined by
// the renderer when it builds the program, 1..4). Per pixel: the ray from the camera through
// the pixel (undistorted on the CPU into u_rays), samples on the lattice t = u_phase + n * step (mm
// from the camera), trilinear interpolation of the quantised volume (0..4095), the transfer
// function as a 4096-entry table, two bisection steps and a secant step to the first crossing
// of the reference layer's surface level (depth and shading there), Lambert headlight shading from the central-
// difference gradient, front-to-back compositing, early termination, and empty-space skipping
// over CELL^3 cells (a distance map: the empty cube around a cell in one jump), rays starting at
// the nearest frontier brick (u_start_z, core's RayStartMap). Image row v is
// framebuffer row v (no flip; read back row by row).
// Weighted fusion of several layers: see cortexfuse/core/fusion.hpp.
#ifndef NLAYERS
#define NLAYERS 1
#endif
// Empty-space skipping cells (CELL^3 voxels), defined by the renderer like NLAYERS: finer than
// the CPU's 8^3 bricks (the box and the start map keep those), so the search loop, whose every
// step costs all lanes of a SIMD group on llvmpipe, samples fewer empty points.
#ifndef CELL
#define CELL 8
#endif
#define FLT_BIG 3.402823e38

layout(location = 0) out vec4 o_rgb;
layout(location = 1) out float o_grey;
layout(location = 2) out float o_depth;
layout(location = 3) out uint o_coverage;

layout(binding = 0) uniform sampler2D u_rays;              // unit camera-frame ray per pixel
layout(binding = 1) uniform sampler3D u_vol[NLAYERS];      // R16 unorm: quantised value / 65535
layout(binding = 5) uniform usampler3D u_bricks[NLAYERS];  // per CELL^3 cell: Chebyshev distance in cells to a visible one (0: visible)
layout(binding = 9) uniform sampler2D u_lut;               // row l: layer l's rgb, opacity per mm
layout(binding = 10) uniform sampler2D u_mesh_rgb;          // opaque geometry, drawn first
layout(binding = 11) uniform sampler2D u_mesh_z;            // its camera-frame z (mm); 0: none
// Central differences of the quantised volume per voxel (RGBA16F): trilinear
// interpolation of them equals the central difference of the interpolated volume at +-1 voxel
// (the CPU ray caster's gradient), in one fetch instead of six.
layout(binding = 12) uniform sampler3D u_grad[NLAYERS];

uniform mat3 u_R_world_from_camera;
uniform vec3 u_cam_world;
uniform mat4 u_index_from_world[NLAYERS];  // the layer's voxel index from scene world
uniform vec3 u_dims[NLAYERS];
uniform vec3 u_box_lo[NLAYERS];            // index-space box of the visible content
uniform vec3 u_box_hi[NLAYERS];
uniform float u_weight[NLAYERS];
uniform float u_grad_scale[NLAYERS];        // quantised unit -> volume unit
uniform int u_grad_n[NLAYERS];              // gradient-opacity points (0: none)
uniform vec2 u_grad_pts[NLAYERS * 8];
uniform float u_iso;                        // layer 0's surface level (quantised), < 0: none
uniform float u_step;
uniform float u_phase;  // samples at t = u_phase + n * u_step (RenderOptions::sample_anchor_world_mm)
uniform float u_ambient;
uniform float u_diffuse;
uniform float u_term;
uniform float u_cov;
uniform bool u_shading;
uniform int u_light;                        // core's Light: 0 headlight, 1 distant (u_light_world), 2 point (u_light_pos_world)
uniform bool u_surface_only;                // layer 0: only its first surface crossing, opaque (RenderOptions::surface_only)
uniform vec3 u_light_world;
uniform vec3 u_light_pos_world;
uniform bool u_has_mesh;
// Where rays may start (core's RayStartMap): the nearest camera depth of a frontier brick per
// cell of a grid over normalised image coordinates (x/z, y/z).
uniform bool u_start_on;
uniform vec2 u_start_origin;
uniform float u_start_inv_cell;
uniform ivec2 u_start_cells;
layout(std430, binding = 0) readonly buffer StartMap { float u_start_z[]; };

float vol(int l, vec3 p) {
    return texture(u_vol[l], (p + 0.5) / u_dims[l]).r * 65535.0;
}
// The same sample at texture coordinates q = (p + 0.5) / u_dims[l] (the search loop steps in them).
float volt(int l, vec3 q) {
    return texture(u_vol[l], q).r * 65535.0;
}

float vol_clamped(int l, vec3 p) {
    return vol(l, clamp(p, vec3(0.0), u_dims[l] - 1.0 - 1e-3));
}

float gradient_factor(int l, float g) {
    const int n = u_grad_n[l];
    const int b = l * 8;
    if (g <= u_grad_pts[b].x) return u_grad_pts[b].y;
    if (g >= u_grad_pts[b + n - 1].x) return u_grad_pts[b + n - 1].y;
    for (int i = 1; i < n; ++i) {
        const vec2 q = u_grad_pts[b + i];
        if (g < q.x) {
            const vec2 p = u_grad_pts[b + i - 1];
            const float w = q.x > p.x ? (g - p.x) / (q.x - p.x) : 1.0;
            return p.y + w * (q.y - p.y);
        }
    }
    return u_grad_pts[b + n - 1].y;
}

void main() {
    const ivec2 px = ivec2(gl_FragCoord.xy);
    const vec3 ray_cam = texelFetch(u_rays, px, 0).xyz;
    const vec3 dir_world = u_R_world_from_camera * ray_cam;

    vec3 o[NLAYERS];
    vec3 d[NLAYERS];
    vec3 oq[NLAYERS];     // o and d in texture coordinates
    vec3 dq[NLAYERS];
    vec3 inv_d[NLAYERS];  // 1 / d: the cell exits without divisions
    float lt0[NLAYERS];
    float lt1[NLAYERS];
    float t0 = FLT_BIG, t1 = -FLT_BIG;
    for (int l = 0; l < NLAYERS; ++l) {
        o[l] = (u_index_from_world[l] * vec4(u_cam_world, 1.0)).xyz;
        d[l] = mat3(u_index_from_world[l]) * dir_world;
        oq[l] = (o[l] + 0.5) / u_dims[l];
        dq[l] = d[l] / u_dims[l];
        inv_d[l] = 1.0 / d[l];
        float a0 = 0.0, a1 = FLT_BIG;
        for (int a = 0; a < 3; ++a) {
            const float lo = u_box_lo[l][a], hi = u_box_hi[l][a];
            if (abs(d[l][a]) < 1e-12) {
                if (o[l][a] < lo || o[l][a] > hi) a1 = -1.0;
                continue;
            }
            float ta = (lo - o[l][a]) / d[l][a], tb = (hi - o[l][a]) / d[l][a];
            if (ta > tb) { const float s = ta; ta = tb; tb = s; }
            a0 = max(a0, ta);
            a1 = min(a1, tb);
        }
        lt0[l] = a0;
        lt1[l] = a1;
        if (a1 > a0) {
            t0 = min(t0, a0);
            t1 = max(t1, a1);
        }
    }

    float t_mesh = FLT_BIG, z_mesh = 0.0;
    vec3 mesh_rgb = vec3(0.0);
    if (u_has_mesh) {
        z_mesh = texelFetch(u_mesh_z, px, 0).r;
        if (z_mesh > 0.0) {
            t_mesh = z_mesh / ray_cam.z;
            mesh_rgb = texelFetch(u_mesh_rgb, px, 0).rgb;
        }
    }

    vec3 c = vec3(0.0);
    float alpha = 0.0, depth = 0.0;
    bool hit = false, refined = false;
    const float step = u_step;
    if (t1 > t0) {
        // Three phases, so that each loop is short: search (empty-space skipping and the
        // opacity test only), refinement (once per ray), compositing (shading) while samples
        // contribute. A software rasteriser (llvmpipe) runs every branch of a loop body for
        // all lanes of a SIMD group, so one loop holding all three would cost them all at
        // every step. The samples taken and their order are the CPU ray caster's.
        if (u_start_on) {
            // No visible brick before depth z, so none before t = z / ray_cam.z (0.05 mm earlier
            // for rounding): the same lattice points show anything, the same picture.
            const ivec2 cell = clamp(ivec2(floor((ray_cam.xy / ray_cam.z - u_start_origin) * u_start_inv_cell)), ivec2(0), u_start_cells - 1);
            t0 = max(t0, u_start_z[cell.y * u_start_cells.x + cell.x] / ray_cam.z - 0.05);
        }
        float t = u_phase + ceil((t0 - u_phase) / step) * step;
        bool done = false;
        bool have_ref = false;  // the next composited sample is the refined surface crossing
        float t_ref = 0.0;
        while (!done) {
            bool found = false;
            while (t <= t1 && t < t_mesh) {
                bool visible = false;
                float t_exit = FLT_BIG;
                for (int l = 0; l < NLAYERS; ++l) {
                    if (lt1[l] <= lt0[l]) continue;
                    if (t < lt0[l]) { t_exit = min(t_exit, lt0[l]); continue; }
                    if (t > lt1[l]) continue;
                    const vec3 p = o[l] + t * d[l];
                    const ivec3 b = ivec3(p) / CELL;
                    const int dist = int(texelFetch(u_bricks[l], b, 0).r);
                    if (dist == 0) { visible = true; break; }
                    // Leave the empty cube of bricks [b - (dist - 1), b + dist) around this one.
                    {
                        // The exit plane of each axis (none where the ray runs parallel to it).
                        const vec3 plane = vec3(mix(b - dist + 1, b + dist, greaterThan(d[l], vec3(0.0))) * CELL);
                        const vec3 ta = mix(vec3(FLT_BIG), (plane - p) * inv_d[l], greaterThan(abs(d[l]), vec3(1e-12)));
                        t_exit = min(t_exit, t + min(ta.x, min(ta.y, ta.z)));
                    }
                    t_exit = min(t_exit, lt1[l]);
                }
                if (!visible) {
                    // Jump to where the ray leaves the invisible cell(s), on the lattice, and
                    // sample there in this same iteration (a point in an empty cell finds
                    // nothing): a jump and the sample after it cost one loop step, not two.
                    t = max(u_phase + ceil((t_exit - u_phase) / step + 1e-4) * step, t + step);
                }
                for (int l = 0; l < NLAYERS; ++l) {
                    if (lt1[l] <= lt0[l] || t < lt0[l] || t > lt1[l] || t >= t_mesh) continue;
                    const float s = volt(l, oq[l] + t * dq[l]);
                    if (l == 0 && u_surface_only && !(s >= u_iso)) continue;
                    if (texelFetch(u_lut, ivec2(int(s + 0.5), l), 0).a * u_weight[l] > 0.0) found = true;
                }
                if (found) break;
                t += step;
            }
            if (!found) break;
            if (!refined && u_iso >= 0.0 && lt1[0] > lt0[0] && t >= lt0[0] && t <= lt1[0]) {
                const float s0 = vol(0, o[0] + t * d[0]);
                if (s0 >= u_iso && texelFetch(u_lut, ivec2(int(s0 + 0.5), 0), 0).a * u_weight[0] > 0.0) {
                    // First crossing of the surface level, between the last sample and this one.
                    refined = true;
                    have_ref = true;
                    // Two bisection steps, then a secant step, as the CPU ray caster does.
                    float ta = t - step, tb = t, sb = s0;
                    float sa = vol_clamped(0, o[0] + ta * d[0]);
                    for (int it = 0; it < 2; ++it) {
                        const float tm = 0.5 * (ta + tb);
                        const float sm = vol_clamped(0, o[0] + tm * d[0]);
                        if (sm >= u_iso) { tb = tm; sb = sm; }
                        else { ta = tm; sa = sm; }
                    }
                    const float frac = sb - sa > 1e-6 ? clamp((u_iso - sa) / (sb - sa), 0.0, 1.0) : 1.0;
                    t_ref = ta + frac * (tb - ta);
                }
            }
            while (t <= t1 && t < t_mesh) {
                vec3 c_sum = vec3(0.0);
                float a_sum = 0.0, transmit = 1.0;
                int n_contrib = 0;
                bool need_refine = false;
                for (int l = 0; l < NLAYERS; ++l) {
                    if (lt1[l] <= lt0[l] || t < lt0[l] || t > lt1[l]) continue;
                    vec3 p = o[l] + t * d[l];
                    const float s = vol(l, p);
                    const vec4 e = texelFetch(u_lut, ivec2(int(s + 0.5), l), 0);
                    float a = e.a * u_weight[l];
                    if (l == 0 && u_surface_only && !(s >= u_iso)) a = 0.0;
                    if (a <= 0.0) continue;
                    if (l == 0 && !refined && u_iso >= 0.0 && s >= u_iso) { need_refine = true; break; }
                    if (l == 0 && have_ref) p = o[0] + t_ref * d[0];
                    float shade = 1.0;
                    const bool grad_op = u_grad_n[l] > 0;
                    if (u_shading || grad_op) {
                        vec3 gi;
                        // The CPU's clamped central differences from the one fetch, no six-fetch
                        // border path (llvmpipe runs both sides of a branch, so that cost every
                        // sample): a refined point up to a voxel outside the grid (before the box)
                        // has (1 + p) times the first voxel's difference along that axis
                        // ((1 + dims - 1 - p) times the last's; none farther out), and the clamped
                        // texture gives the other axes' clamping. Within a voxel of the far faces
                        // the CPU clamps its forward sample 1e-3 voxel short of the last voxel:
                        // its difference differs by 1e-3 of the last voxel step.
                        gi = texture(u_grad[l], (p + 0.5) / u_dims[l]).rgb * clamp(min(1.0 + p, u_dims[l] - p), 0.0, 1.0);
                        const vec3 gw = transpose(mat3(u_index_from_world[l])) * gi;
                        const float gn = length(gw);
                        if (grad_op) a *= gradient_factor(l, gn * u_grad_scale[l]);
                        // Two-sided Lambert, |cos|, for every kind of light (raycast_cpu.cpp: why).
                        if (u_shading) {
                            vec3 light = u_light == 1 ? u_light_world : dir_world;
                            if (u_light == 2) {
                                const vec3 to_lamp = u_light_pos_world - (u_cam_world + ((l == 0 && have_ref) ? t_ref : t) * dir_world);
                                const float dl = length(to_lamp);
                                if (dl > 1e-3) light = to_lamp / dl;
                            }
                            shade = u_ambient + u_diffuse * (gn > 1e-6 ? abs(dot(gw, light)) / gn : 0.0);
                        }
                    }
                    const float a_step = (l == 0 && u_surface_only) || a >= 1.0 ? 1.0 : 1.0 - pow(1.0 - a, step);
                    c_sum += a_step * e.rgb * shade;
                    a_sum += a_step;
                    transmit *= 1.0 - a_step;
                    ++n_contrib;
                }
                if (need_refine || n_contrib == 0) break;  // refine first / back to searching
                // One layer: exactly the single-volume ray caster; several: weighted fusion.
                const float sa = n_contrib == 1 ? a_sum : 1.0 - transmit;
                const float w = 1.0 - alpha;
                c += n_contrib == 1 ? w * c_sum : w * (sa / a_sum) * c_sum;
                alpha += w * sa;
                if (!hit && alpha >= u_cov) {
                    hit = true;
                    depth = (have_ref ? t_ref : t) * ray_cam.z;
                }
                have_ref = false;
                if (alpha >= u_term) { done = true; break; }
                t += step;
            }
            if (!(t <= t1 && t < t_mesh)) break;
        }
    }
    if (z_mesh > 0.0 && alpha < u_term) {
        // Opaque geometry behind what the ray gathered.
        c += (1.0 - alpha) * mesh_rgb;
        alpha = 1.0;
        if (!hit) {
            hit = true;
            depth = z_mesh;
        }
    }
    c = min(c, vec3(1.0));
    o_rgb = vec4(c, 1.0);
    o_grey = 0.299 * c.r + 0.587 * c.g + 0.114 * c.b;
    o_depth = hit ? depth : 0.0;
    o_coverage = hit ? 1u : 0u;
}
