#pragma once
// Studholme's NMI, (H(A) + H(B)) / H(A,B), of a bins x bins joint histogram of n samples
// (row: A's bin, column: B's). Shared by the co-registration's NMI metric and its optimum gate
// (core/src/nmi_coregistration.cpp, core/src/coregistration.cpp). The photo-to-render metric
// (similarity.cpp) keeps its own: it scales by 1/n and serves MI too, and changing its rounding
// would move the 3D-2D registration's evaluation path.
#include <cmath>
#include <cstddef>
#include <vector>

namespace cf::detail {

/// 1.0 (no shared information) when the joint entropy is zero: two constant images.
inline double nmi_of_joint(const std::vector<double>& joint, int bins, double n) {
    const std::size_t B = std::size_t(bins);
    std::vector<double> pa(B, 0.0), pb(B, 0.0);
    double hab = 0;
    for (std::size_t x = 0; x < B; ++x)
        for (std::size_t y = 0; y < B; ++y) {
            const double p = joint[x * B + y] / n;
            pa[x] += p, pb[y] += p;
            if (p > 0) hab -= p * std::log(p);
        }
    double ha = 0, hb = 0;
    for (std::size_t x = 0; x < B; ++x) {
        if (pa[x] > 0) ha -= pa[x] * std::log(pa[x]);
        if (pb[x] > 0) hb -= pb[x] * std::log(pb[x]);
    }
    return hab > 0 ? (ha + hb) / hab : 1.0;
}

}  // namespace cf::detail
