#include "cortexfuse/core/install_paths.hpp"

#include <cstdlib>
#include <system_error>

namespace cf {

namespace fs = std::filesystem;

namespace {

/// <prefix>/share/cortexfuse/<sub> for the running executable at <prefix>/bin/<name>, when
/// `probe` exists in it; empty otherwise.
fs::path installed(const char* sub, const char* probe) {
    std::error_code ec;
    const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
    if (ec || exe.empty()) return {};
    const fs::path dir = exe.parent_path().parent_path() / "share" / "cortexfuse" / sub;
    return fs::exists(dir / probe, ec) ? dir : fs::path();
}

fs::path pick(const char* env, const char* sub, const char* probe, const fs::path& build_default) {
    if (const char* e = std::getenv(env); e && *e) return e;
    if (fs::path p = installed(sub, probe); !p.empty()) return p;
    return build_default;
}

}  // namespace

fs::path bundled_data_dir(const fs::path& build_default) { return pick("CF_DATA_DIR", "data", "t1_head_mne_ecog.nii.gz", build_default); }

fs::path bundled_ui_dir(const fs::path& build_default) { return pick("CF_UI_DIR", "ui", "index.html", build_default); }

}  // namespace cf
