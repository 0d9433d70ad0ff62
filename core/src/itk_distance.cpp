// ITK code only: this file must include no Eigen header (ITK 5.2 bundles a clashing one).
#include "itk_distance.hpp"

#include <itkImage.h>

#include <algorithm>

#include "itk_image.hpp"

namespace cf::itkb {

namespace {

using MaskImage = itk::Image<uint8_t, 3>;
using DistImage = itk::Image<double, 3>;

}  // namespace

void midpoint_signed_distance(const std::array<int, 3>& dims, const std::array<double, 3>& spacing_mm,
                              const uint8_t* mask, std::vector<double>& phi) {
    Grid g;
    g.dims = dims;
    g.spacing = spacing_mm;
    const size_t n = g.count();
    auto inside = image_from<MaskImage>(g, mask);
    auto outside = make_image<MaskImage>(g);
    uint8_t* o = outside->GetBufferPointer();
    for (size_t i = 0; i < n; ++i) o[i] = mask[i] ? 0 : 1;
    // Maurer's own signed map is zero on the set's edge voxels, so its zero level would sit on
    // them, not between them and their outside neighbours; two unsigned maps do not.
    const auto to_inside = signed_maurer_distance<DistImage>(inside.GetPointer());
    const auto to_outside = signed_maurer_distance<DistImage>(outside.GetPointer());
    const double* a = to_inside->GetBufferPointer();
    const double* b = to_outside->GetBufferPointer();
    phi.resize(n);
    for (size_t i = 0; i < n; ++i) phi[i] = std::max(a[i], 0.0) - std::max(b[i], 0.0);
}

}  // namespace cf::itkb
