#pragma once
// ITK images made from the bridge's plain grid. Only for itk_*.cpp files: it includes ITK
// (whose bundled Eigen clashes with the system one; see itk_bridge.hpp).
#include <itkImage.h>
#include <itkSignedMaurerDistanceMapImageFilter.h>

#include <cstring>

#include "itk_bridge.hpp"

namespace cf::itkb {

/// A new image with the grid's size, spacing, origin and direction, allocated, not filled.
template <class ImageT>
typename ImageT::Pointer make_image(const Grid& g) {
    auto img = ImageT::New();
    typename ImageT::RegionType region;
    typename ImageT::SizeType size;
    typename ImageT::SpacingType spacing;
    typename ImageT::PointType origin;
    typename ImageT::DirectionType dir;
    for (unsigned a = 0; a < 3; ++a) {
        size[a] = itk::SizeValueType(g.dims[a]);
        spacing[a] = g.spacing[a];
        origin[a] = g.origin[a];
        for (unsigned b = 0; b < 3; ++b) dir(a, b) = g.direction[a * 3 + b];
    }
    region.SetSize(size);
    img->SetRegions(region);
    img->SetSpacing(spacing);
    img->SetOrigin(origin);
    img->SetDirection(dir);
    img->Allocate();
    return img;
}

/// The same, holding a copy of `data` (g.count() pixels).
template <class ImageT, class PixelT>
typename ImageT::Pointer image_from(const Grid& g, const PixelT* data) {
    static_assert(sizeof(PixelT) == sizeof(typename ImageT::PixelType));
    auto img = make_image<ImageT>(g);
    std::memcpy(img->GetBufferPointer(), data, g.count() * sizeof(PixelT));
    return img;
}

/// Maurer's signed distance map of mask `m` in mm (the image's spacing): <= 0 on the mask's
/// voxels (0 on its edge voxels), > 0 outside. DistImageT picks the precision (float for the
/// skull strip's grids, double where the caller stretches an axis to 1e4 mm).
template <class DistImageT, class MaskImageT>
typename DistImageT::Pointer signed_maurer_distance(const MaskImageT* m) {
    auto f = itk::SignedMaurerDistanceMapImageFilter<MaskImageT, DistImageT>::New();
    f->SetInput(m);
    f->SetUseImageSpacing(true);
    f->SetSquaredDistance(false);
    f->SetInsideIsPositive(false);
    f->SetBackgroundValue(0);
    f->Update();
    return f->GetOutput();
}

}  // namespace cf::itkb
