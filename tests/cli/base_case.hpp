#pragma once
// The small valid case folders the CLI tests start from, generated at test time from the
// shipped MRI (data/): the volume cropped around the brain and resampled to 64^3, its brain
// mask, and a phantom photo with landmarks, ROI and truth (cf::generate_phantom_case).
#include <filesystem>

namespace cf::test {

/// Writes ROOT/small (375x250 photo) and ROOT/medium (750x500) case folders, each holding its
/// own t1.nii.gz and brain_mask.nii.gz. Written into a temporary folder and renamed, so ROOT is
/// whole or absent (parallel test processes may race; the first rename wins).
void make_base_cases(const std::filesystem::path& root);

/// The generated base cases (CF_CLI_BASE_DIR), made now if a previous step has not made them.
const std::filesystem::path& base_cases();

/// The built `cortexfuse` (CF_CORTEXFUSE_EXE).
std::string cortexfuse_exe();

}  // namespace cf::test
