#pragma once
// Rigid co-registration by true normalized mutual information (coregistration.cpp's
// CoregParams::Metric::Nmi); see nmi_coregistration.cpp.
#include <Eigen/Geometry>

#include "cortexfuse/core/coregistration.hpp"
#include "itk_coregister.hpp"

namespace cf::detail {

/// Registers `moving` to `fixed` (both already clipped as CoregParams::clip_intensities says)
/// by maximising Studholme's NMI = (H(F)+H(M))/H(F,M) with NLopt's Nelder-Mead, level by level
/// (p.shrink, p.smooth_mm, p.iterations). The Euler3D parameters (rx, ry, rz rad, tx, ty, tz mm)
/// are about `center_world_mm` (fixed world), starting at zero angles and `t0_mm`.
/// `fixed_mask` (fixed grid, may be null) limits where samples are drawn; `samples` is the
/// sample count per level. Honours cancellation (cf::Cancelled) and reports progress.
itkb::CoregOutput nmi_coregister(const Volume& fixed, const Volume& moving, const LabelVolume* fixed_mask, size_t samples,
                                 const CoregParams& p, const Eigen::Vector3d& center_world_mm, const Eigen::Vector3d& t0_mm,
                                 const Progress& progress);

}  // namespace cf::detail
