// Trilinear sampling of a 16-bit volume and its central differences: the CPU ray caster's
// inner kernels, apart so that a test can hold them against the plain formulas.
// Internal to core (not installed).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <cstring>
#if defined(__SSE4_1__)
#include <immintrin.h>
#endif

namespace cf {

#if defined(__SSE4_1__)
/// Four x-pairs (p[o], p[o + 1]) as 32-bit lanes, low half the first.
inline __m128i u16_pairs(const uint16_t* p, ptrdiff_t o0, ptrdiff_t o1, ptrdiff_t o2, ptrdiff_t o3) {
    auto pair = [p](ptrdiff_t o) {
        int v;
        std::memcpy(&v, p + o, 4);
        return v;
    };
    return _mm_insert_epi32(_mm_insert_epi32(_mm_insert_epi32(_mm_cvtsi32_si128(pair(o0)), pair(o1), 1), pair(o2), 2), pair(o3), 3);
}
#endif

/// Trilinear sample of the x-fastest grid `q` (dims) at index-space (x, y, z), which must lie
/// in [0, d - 1) on each axis.
inline float trilinear_u16(const uint16_t* q, const std::array<int, 3>& dims, float x, float y, float z) {
    const int i = int(x), j = int(y), k = int(z);
    const float fx = x - float(i), fy = y - float(j), fz = z - float(k);
    const ptrdiff_t sy = dims[0], sz = sy * dims[1];
    const uint16_t* p = q + ptrdiff_t(k) * sz + ptrdiff_t(j) * sy + i;
#if defined(__SSE4_1__)
    // The cell's four x-pairs of corners as 32-bit lanes (low half: x = i, high: i + 1), lerped
    // along x in one 4-wide step: samples are a fifth of a frame's time.
    const __m128i v = u16_pairs(p, 0, sy, sz, sz + sy);
    const __m128 a = _mm_cvtepi32_ps(_mm_and_si128(v, _mm_set1_epi32(0xFFFF)));
    const __m128 b = _mm_cvtepi32_ps(_mm_srli_epi32(v, 16));
    const __m128 c = _mm_add_ps(a, _mm_mul_ps(_mm_set1_ps(fx), _mm_sub_ps(b, a)));  // c00 c10 c01 c11
    alignas(16) float cc[4];
    _mm_store_ps(cc, c);
    const float c0 = cc[0] + fy * (cc[1] - cc[0]), c1 = cc[2] + fy * (cc[3] - cc[2]);
#else
    const float c00 = float(p[0]) + fx * (float(p[1]) - float(p[0]));
    const float c10 = float(p[sy]) + fx * (float(p[sy + 1]) - float(p[sy]));
    const float c01 = float(p[sz]) + fx * (float(p[sz + 1]) - float(p[sz]));
    const float c11 = float(p[sz + sy]) + fx * (float(p[sz + sy + 1]) - float(p[sz + sy]));
    const float c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
#endif
    return c0 + fz * (c1 - c0);
}

/// trilinear(p + e_a) - trilinear(p - e_a) along each axis a, for p with 1 <= p_a <= d_a - 2 - 1e-3.
/// The six samples share p's cell weights, so this is the trilinear interpolation of the
/// voxels' central differences at p: 32 voxels read once and one set of weights, instead of
/// six samples of 8 (the gradient was a third of a shaded sample's cost). Equal up to float
/// rounding.
inline Eigen::Vector3f central_difference_u16(const uint16_t* q, const std::array<int, 3>& dims, float x, float y, float z) {
    const int i = int(x), j = int(y), k = int(z);
    const float fx = x - float(i), fy = y - float(j), fz = z - float(k);
    const ptrdiff_t sy = dims[0], sz = sy * dims[1];
    const uint16_t* p = q + ptrdiff_t(k) * sz + ptrdiff_t(j) * sy + i;
#if defined(__SSE4_1__)
    // Lanes are the four x-rows of the cell's corners (y, z) = (j, k), (j+1, k), (j, k+1),
    // (j+1, k+1); each pair holds the differences at x = i (low) and i + 1 (high).
    const ptrdiff_t r1 = sy, r2 = sz, r3 = sz + sy;
    const __m128i lo16 = _mm_set1_epi32(0xFFFF);
    const __m128 vfx = _mm_set1_ps(fx);
    auto lerp_x = [&](__m128i plus, __m128i minus) {
        const __m128 d0 = _mm_cvtepi32_ps(_mm_sub_epi32(_mm_and_si128(plus, lo16), _mm_and_si128(minus, lo16)));
        const __m128 d1 = _mm_cvtepi32_ps(_mm_sub_epi32(_mm_srli_epi32(plus, 16), _mm_srli_epi32(minus, 16)));
        return _mm_add_ps(d0, _mm_mul_ps(vfx, _mm_sub_ps(d1, d0)));
    };
    const __m128 dx = lerp_x(u16_pairs(p + 1, 0, r1, r2, r3), u16_pairs(p - 1, 0, r1, r2, r3));
    const __m128 dy = lerp_x(u16_pairs(p + sy, 0, r1, r2, r3), u16_pairs(p - sy, 0, r1, r2, r3));
    const __m128 dz = lerp_x(u16_pairs(p + sz, 0, r1, r2, r3), u16_pairs(p - sz, 0, r1, r2, r3));
    const __m128 w = _mm_setr_ps((1.f - fy) * (1.f - fz), fy * (1.f - fz), (1.f - fy) * fz, fy * fz);
    const __m128 h = _mm_hadd_ps(_mm_hadd_ps(_mm_mul_ps(dx, w), _mm_mul_ps(dy, w)), _mm_hadd_ps(_mm_mul_ps(dz, w), _mm_setzero_ps()));
    alignas(16) float g[4];
    _mm_store_ps(g, h);
    return {g[0], g[1], g[2]};
#else
    const float wy[2] = {1.f - fy, fy}, wz[2] = {1.f - fz, fz};
    float gx = 0, gy = 0, gz = 0;
    for (int c = 0; c < 2; ++c)
        for (int b = 0; b < 2; ++b) {
            const uint16_t* r = p + c * sz + b * sy;  // the row of corners (0, b, c) and (1, b, c)
            const float w = wy[b] * wz[c];
            const float dx0 = float(r[1]) - float(r[-1]), dx1 = float(r[2]) - float(r[0]);
            const float dy0 = float(r[sy]) - float(r[-sy]), dy1 = float(r[sy + 1]) - float(r[1 - sy]);
            const float dz0 = float(r[sz]) - float(r[-sz]), dz1 = float(r[sz + 1]) - float(r[1 - sz]);
            gx += w * (dx0 + fx * (dx1 - dx0));
            gy += w * (dy0 + fx * (dy1 - dy0));
            gz += w * (dz0 + fx * (dz1 - dz0));
        }
    return {gx, gy, gz};
#endif
}

}  // namespace cf
