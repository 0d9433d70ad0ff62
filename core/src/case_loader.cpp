#include <cmath>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/core/skull_strip.hpp"

namespace fs = std::filesystem;

namespace cf {

LoadedCase load_case(const fs::path& dir, const Progress* progress) {
    LoadedCase c;
    c.spec = read_case(dir);
    c.photo.photo_bgr = load_photo(c.spec.photo_path);
    const auto& K = c.spec.camera;
    const double aspect_photo = double(c.photo.photo_bgr.cols) / c.photo.photo_bgr.rows;
    if (std::abs(aspect_photo / (double(K.width) / K.height) - 1) > 0.01)
        throw InputError(c.spec.photo_path.string(), "is " + std::to_string(c.photo.photo_bgr.cols) + "x" +
                                                         std::to_string(c.photo.photo_bgr.rows) + ", not the " +
                                                         std::to_string(K.width) + "x" + std::to_string(K.height) +
                                                         " (or same aspect ratio) that case.json's camera says");
    c.photo.camera = K;
    c.photo.landmarks = c.spec.landmarks;
    c.photo.roi = c.spec.roi;
    c.photo.initial_pose = c.spec.initial_pose;
    c.volume = load_volume(c.spec.volume_path);
    if (c.spec.brain_mask_path) {
        c.mask = load_mask(*c.spec.brain_mask_path, c.volume.geom);
        if (c.mask.count_nonzero() < 1000)
            throw InputError(c.spec.brain_mask_path->string(), "brain mask is empty or does not overlap the volume");
    } else {
        c.mask = skull_strip(c.volume, {}, progress);
        c.mask_computed = true;
    }
    return c;
}

}  // namespace cf
