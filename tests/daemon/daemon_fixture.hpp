// The daemon tests' shared fixture: cortexfused's Daemon in-process on a free port with its own
// temp state folder, the HTTP calls to it (cpp-httplib), and the small helpers every daemon test
// needs (file bytes, URL encoding, job polling, the 2 mm copy of the bundled head, a plain
// phantom). Header-only; one daemon a test program through add_shared_daemon(), or as many as a
// test wants through TestDaemon.
// Thread contract: test-thread only (gtest runs the tests of a program one after another).
// Include it after the Eigen-using cortexfuse headers: <httplib.h> pulls in <resolv.h>, whose
// _res macro breaks Eigen's headers.
#pragma once

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/daemon/daemon.hpp"
#include "cortexfuse/db/case_store.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <string>
#include <thread>
#include <utility>

namespace cf::daemon_test {

namespace fs = std::filesystem;
using nlohmann::json;

/// One HTTP answer: status 0 when the request got no answer at all.
struct Reply {
    int status = 0;
    std::string body;
    json j;  // the body parsed as JSON (discarded when it is not JSON)
    std::string content_type;
    httplib::Headers headers;
};

/// One request to 127.0.0.1:`port` (GET, DELETE, or POST or PUT with `body` as `mime`), with a bearer
/// `token` when not empty, waiting up to `read_timeout_s` for the answer.
inline Reply http_request(int port, const std::string& method, const std::string& path, const std::string& body = "",
                          const std::string& mime = "application/json", const std::string& token = "", int read_timeout_s = 120) {
    httplib::Client c("127.0.0.1", port);
    c.set_read_timeout(read_timeout_s, 0);
    httplib::Headers h;
    if (!token.empty()) h.emplace("Authorization", "Bearer " + token);
    httplib::Result r = method == "GET"      ? c.Get(path.c_str(), h)
                        : method == "DELETE" ? c.Delete(path.c_str(), h)
                        : method == "PUT"    ? c.Put(path.c_str(), h, body, mime.c_str())
                                             : c.Post(path.c_str(), h, body, mime.c_str());
    Reply out;
    if (!r) return out;
    out.status = r->status;
    out.body = r->body;
    out.content_type = r->get_header_value("Content-Type");
    out.headers = r->headers;
    out.j = json::parse(r->body, nullptr, false);
    return out;
}

/// The minimal test configuration: listening on a free port, state under `state`, the given
/// renderer kind, no phantom cases made at start. Tests add what they need.
inline json base_test_config(const fs::path& state, const std::string& renderer) {
    json c = cf::daemon::default_config_json();
    c["http"]["listen"] = "127.0.0.1:0";
    c["state_dir"] = state.string();
    c["renderer"]["kind"] = renderer;
    c["jobs"]["phantom_cases_at_start"] = 0;
    return c;
}

/// A daemon started in-process from `config` (its state folder made first), stopped (the stop
/// expected to succeed) when destroyed; and the HTTP calls to it.
class TestDaemon {
public:
    TestDaemon(const fs::path& state, const json& config, int read_timeout_s = 120) : state_(state), timeout_s_(read_timeout_s) {
        fs::create_directories(state_);
        d_ = std::make_unique<cf::daemon::Daemon>(cf::daemon::parse_config(config, "test"));
        d_->start();
    }
    ~TestDaemon() { EXPECT_TRUE(d_->stop()); }
    TestDaemon(const TestDaemon&) = delete;
    TestDaemon& operator=(const TestDaemon&) = delete;

    int port() const { return d_->port(); }
    const fs::path& state() const { return state_; }
    cf::daemon::Daemon& daemon() { return *d_; }

    Reply request(const std::string& method, const std::string& path, const std::string& body = "",
                  const std::string& mime = "application/json", const std::string& token = "") const {
        return http_request(port(), method, path, body, mime, token, timeout_s_);
    }
    Reply get(const std::string& path, const std::string& token = "") const { return request("GET", path, "", "application/json", token); }
    Reply del(const std::string& path, const std::string& token = "") const { return request("DELETE", path, "", "application/json", token); }
    Reply post(const std::string& path, const json& body, const std::string& token = "") const {
        return request("POST", path, body.dump(), "application/json", token);
    }
    Reply put(const std::string& path, const json& body, const std::string& token = "") const {
        return request("PUT", path, body.dump(), "application/json", token);
    }
    Reply post_raw(const std::string& path, const std::string& bytes, const std::string& token = "") const {
        return request("POST", path, bytes, "application/octet-stream", token);
    }

    /// A new case (POST /api/cases, expected 201); its id, 0 when refused.
    std::int64_t new_case(const std::string& title) const {
        const Reply r = post("/api/cases", {{"title", title}});
        EXPECT_EQ(r.status, 201) << r.body;
        return r.j.value("id", std::int64_t{0});
    }
    /// A session token of user `name` with `role` (made by the kiosk, which is admin, when new).
    std::string token_of(const std::string& name, const std::string& role) const {
        Reply r = post("/api/users", {{"name", name}, {"password", "long enough pw"}, {"role", role}});
        EXPECT_TRUE(r.status == 201 || r.status == 409) << r.body;
        r = post("/api/login", {{"name", name}, {"password", "long enough pw"}});
        EXPECT_EQ(r.status, 200) << r.body;
        return r.j.value("token", std::string());
    }

private:
    fs::path state_;
    int timeout_s_;
    std::unique_ptr<cf::daemon::Daemon> d_;
};

/// The test program's one daemon: started on first use with the state folder
/// <tmp>/<prefix>_<pid> and `config(state)`; after the last test `before_stop` runs (when set),
/// then the daemon (if it was started) is stopped and its state folder removed.
class SharedDaemon : public ::testing::Environment {
public:
    using ConfigFn = std::function<json(const fs::path& state)>;
    SharedDaemon(const std::string& prefix, ConfigFn config, int read_timeout_s)
        : state_(fs::temp_directory_path() / (prefix + "_" + std::to_string(::getpid()))), config_(std::move(config)), timeout_s_(read_timeout_s) {}

    const fs::path& state() const { return state_; }
    TestDaemon& get() {
        if (!d_) d_ = std::make_unique<TestDaemon>(state_, config_(state_), timeout_s_);
        return *d_;
    }
    int port() { return get().port(); }

    std::function<void()> before_stop;

    void TearDown() override {
        if (before_stop) before_stop();
        if (!d_) return;
        d_.reset();
        fs::remove_all(state_);
    }

private:
    fs::path state_;
    ConfigFn config_;
    int timeout_s_;
    std::unique_ptr<TestDaemon> d_;
};

/// Registers the program's shared daemon with gtest (which owns it) and returns it.
inline SharedDaemon& add_shared_daemon(const std::string& prefix, SharedDaemon::ConfigFn config, int read_timeout_s = 120,
                                       std::function<void()> before_stop = {}) {
    auto* d = new SharedDaemon(prefix, std::move(config), read_timeout_s);
    d->before_stop = std::move(before_stop);
    return *static_cast<SharedDaemon*>(::testing::AddGlobalTestEnvironment(d));
}

inline std::string read_bytes(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(in), {});
}

/// Percent-encoding of a query value (RFC 3986 unreserved characters kept). httplib has no
/// public encoder for a single query component, hence these lines.
inline std::string url_encode(const std::string& s) {
    std::string o;
    char buf[4];
    for (unsigned char c : s) {
        if (std::isalnum(c) || c == '-' || c == '_' || c == '.' || c == '~') o += char(c);
        else {
            std::snprintf(buf, sizeof buf, "%%%02X", c);
            o += buf;
        }
    }
    return o;
}

/// Polls GET /api/jobs/{id} through `get` every 50 ms until the job leaves queued/running, its
/// GET fails, or `timeout_s` passes; `stages` collects the stages seen on the way. Returns the
/// last record.
inline json poll_job(const std::function<Reply(const std::string&)>& get, std::uint64_t id, double timeout_s = 240,
                     std::set<std::string>* stages = nullptr) {
    const auto t0 = std::chrono::steady_clock::now();
    for (;;) {
        const Reply r = get("/api/jobs/" + std::to_string(id));
        if (r.status != 200) return r.j;
        if (stages) stages->insert(r.j.value("stage", std::string()));
        const std::string s = r.j.value("state", std::string());
        if (s != "queued" && s != "running") return r.j;
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() > timeout_s) return r.j;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
}

/// Waits up to 60 s until the daemon's render volume (data.t1) has loaded.
inline void wait_for_volume(const TestDaemon& d) {
    for (int i = 0; i < 600; ++i) {
        if (d.get("/api/render/volume").status == 200) return;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    FAIL() << "the render volume did not load";
}

/// A camera as the photo upload's `camera` query wants it.
inline json camera_json(const cf::Intrinsics& K) {
    return {{"width", K.width}, {"height", K.height}, {"fx", K.fx}, {"fy", K.fy}, {"cx", K.cx}, {"cy", K.cy},
            {"distortion", {K.distortion[0], K.distortion[1], K.distortion[2], K.distortion[3], K.distortion[4]}}};
}

/// The phantom the daemon tests use: seed 11, 320x240, no size variation, DSLR, distortion,
/// gauze or blood.
inline cf::PhantomParams plain_phantom_params() {
    cf::PhantomParams p;
    p.seed = 11;
    p.width = 320;
    p.height = 240;
    p.vary_size = false;
    p.dslr_fraction = 0;
    p.distortion_prob = 0;
    p.gauze_prob = 0;
    p.blood_prob = 0;
    return p;
}

/// A reply's body decoded as a BGR image (empty when it is not one).
inline cv::Mat decode(const Reply& r) {
    return cv::imdecode(cv::Mat(1, int(r.body.size()), CV_8U, const_cast<char*>(r.body.data())), cv::IMREAD_COLOR);
}
/// The mean absolute difference of two BGR images over their pixels and channels (0..255).
inline double mean_abs_diff(const cv::Mat& a, const cv::Mat& b) {
    cv::Mat d;
    cv::absdiff(a, b, d);
    const cv::Scalar m = cv::mean(d);
    return (m[0] + m[1] + m[2]) / 3.0;
}

/// Stores `T_camera_from_world` as a registration run of case `id` (what a register job stores,
/// NMI 1.2), through a second connection to the store under `store_dir`.
inline void store_registration(const fs::path& store_dir, std::int64_t id, const cf::Pose& T_camera_from_world) {
    auto store = cf::db::CaseStore::open(store_dir);
    cf::db::RegistrationInput in;
    in.final_pose = json{{"T_camera_from_world", cf::pose_to_json(T_camera_from_world)}};
    in.initial_pose = in.final_pose;
    in.nmi = 1.2;
    store->add_registration(id, in, cf::db::Actor{"test", std::nullopt});
}

inline std::string png_bytes(const cv::Mat& bgr) {
    std::vector<uchar> buf;
    cv::imencode(".png", bgr, buf);
    return std::string(buf.begin(), buf.end());
}

#ifdef CF_DATA_DIR
/// The bundled T1 and brain mask resampled to 2 mm (small, fast), saved as t1.nii.gz and
/// mask.nii.gz under `dir` (made), with the files' bytes.
struct Head2mm {
    cf::Volume t1;
    cf::LabelVolume mask;
    fs::path t1_path, mask_path;
    std::string t1_bytes, mask_bytes;
};
inline Head2mm head_2mm(const fs::path& dir) {
    Head2mm h;
    fs::create_directories(dir);
    const cf::Volume t1 = cf::load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
    const cf::LabelVolume m = cf::load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
    const cf::VolumeGeometry g = cf::isotropic_grid(t1.geom, 2.0);
    h.t1 = cf::resample(t1, g);
    h.mask = cf::resample_nearest(m, g);
    h.t1_path = dir / "t1.nii.gz";
    h.mask_path = dir / "mask.nii.gz";
    cf::save_volume(h.t1, h.t1_path);
    cf::save_mask(h.mask, h.mask_path);
    h.t1_bytes = read_bytes(h.t1_path);
    h.mask_bytes = read_bytes(h.mask_path);
    return h;
}
#endif

}  // namespace cf::daemon_test
