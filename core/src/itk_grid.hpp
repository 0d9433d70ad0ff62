#pragma once
// Our volume geometry to and from the plain grid the ITK bridge takes (itk_bridge.hpp). For the
// translation units that see Eigen; the itk_*.cpp files never include this one.
#include "cortexfuse/core/volume.hpp"
#include "itk_bridge.hpp"

namespace cf::itkb {

inline Grid to_grid(const VolumeGeometry& g) {
    Grid r;
    r.dims = g.dims;
    for (int a = 0; a < 3; ++a) {
        r.spacing[size_t(a)] = g.spacing_mm[a];
        r.origin[size_t(a)] = g.origin_mm[a];
        for (int b = 0; b < 3; ++b) r.direction[size_t(a * 3 + b)] = g.direction(a, b);
    }
    return r;
}

inline VolumeGeometry from_grid(const Grid& r) {
    VolumeGeometry g;
    g.dims = r.dims;
    for (int a = 0; a < 3; ++a) {
        g.spacing_mm[a] = r.spacing[size_t(a)];
        g.origin_mm[a] = r.origin[size_t(a)];
        for (int b = 0; b < 3; ++b) g.direction(a, b) = r.direction[size_t(a * 3 + b)];
    }
    return g;
}

}  // namespace cf::itkb
