#pragma once
// Where the bundled read-only files are: the build tree's folders for a binary run from the
// build, the installed layout's for a packaged one (docs/packaging.md). The binaries are built
// with the source tree's paths (CF_DATA_DIR, CF_UI_DIR) as `build_default`; an installed binary
// finds the installed copies beside it instead (<prefix>/bin -> <prefix>/share/cortexfuse), so it
// never reaches into a build tree that may not exist on the cart.
//
// Thread contract: any thread (reads the environment and the file system only).
#include <filesystem>

namespace cf {

/// The folder of the bundled MRI and brain mask: $CF_DATA_DIR when set and not empty; else
/// <folder of the running executable>/../share/cortexfuse/data when it holds the bundled T1
/// (t1_head_mne_ecog.nii.gz); else `build_default`.
std::filesystem::path bundled_data_dir(const std::filesystem::path& build_default);

/// The folder of the built web UI: $CF_UI_DIR when set and not empty; else
/// <folder of the running executable>/../share/cortexfuse/ui when it has an index.html; else
/// `build_default`.
std::filesystem::path bundled_ui_dir(const std::filesystem::path& build_default);

}  // namespace cf
