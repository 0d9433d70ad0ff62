// daemon_memory: the memory benchmark of issue 6 ("the daemon with a case open stays under
// 2 GiB"). Starts cortexfused (its embedded defaults: the bundled 256^3 T1 as data.t1; the
// tracker and camera off so that only the case work counts; the renderer asked for), lets it
// generate --cases phantom cases (each the bundled 256^3 T1, its brain mask, a photo and an ROI),
// imports them into the case store, plans each (plan job), stores the phantom's true pose as each
// case's registration (a second connection to the store, as the tests do), then renders --rounds
// rounds of per-case views through the API: for every case a volume render (POST /api/render with
// case_id, left and right views alternately) and its fused view (POST /api/cases/{id}/fused).
// The daemon's RSS is read from /proc/<pid>/status: VmHWM (peak) and VmRSS (steady: the median
// over the rounds' ends), after setup and after the renders.
//
// Prints one JSON object on stdout (medians of the render latencies, RSS in MiB, load average,
// date). Exit code: 0 when every request succeeded and peak RSS <= --max-rss-mib (2048 by
// default), 1 otherwise, 2 for a bad command line, 3 when the daemon could not be set up.
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/db/case_store.hpp"

#include <httplib.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include "daemon_process.hpp"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace fs = std::filesystem;
using json = nlohmann::json;
using Clock = std::chrono::steady_clock;

namespace {

using cf::bench::loadavg;
using cf::bench::proc_status_kb;
using cf::bench::read_file;
using cf::bench::wait_exit;

double mib(long kb) { return double(kb) / 1024.0; }


double median(std::vector<double> v) {
    if (v.empty()) return 0;
    std::sort(v.begin(), v.end());
    const std::size_t n = v.size();
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

pid_t g_pid = -1;
fs::path g_dir;
bool g_keep = false;


void stop_daemon() {
    if (g_pid > 0) {
        kill(g_pid, SIGTERM);
        wait_exit(g_pid, 30);
        g_pid = -1;
    }
}

[[noreturn]] void fail(const std::string& what) {
    std::cerr << "daemon_memory: " << what << "\n";
    stop_daemon();
    if (!g_dir.empty()) std::cerr << "daemon log (" << (g_dir / "cortexfused.log").string() << "):\n" << read_file(g_dir / "cortexfused.log") << "\n";
    std::exit(3);
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"Memory benchmark of cortexfused: RSS with cases open, planned, registered and rendered (issue 6)"};
    std::string daemon_exe = CF_CORTEXFUSED, renderer = "auto";
    int cases = 1, rounds = 5, width = 640, height = 480, max_triangles = 60000;
    double max_rss_mib = 2048;
    std::vector<std::string> sets;
    app.add_option("--daemon", daemon_exe, "cortexfused executable")->check(CLI::ExistingFile);
    app.add_option("--renderer", renderer, "renderer.kind of the daemon")->check(CLI::IsMember({"auto", "gl", "cpu"}));
    app.add_option("--cases", cases, "Cases open at once (phantom cases on the bundled 256^3 T1)")->check(CLI::Range(1, 8));
    app.add_option("--rounds", rounds, "Rounds of renders (each: a volume render and a fused view of every case)")->check(CLI::Range(1, 1000));
    app.add_option("--width", width, "Render width in pixels")->check(CLI::Range(16, 4096));
    app.add_option("--height", height, "Render height in pixels")->check(CLI::Range(16, 4096));
    app.add_option("--max-triangles", max_triangles, "The plan job's max_triangles")->check(CLI::Range(1000, 2000000));
    app.add_option("--max-rss-mib", max_rss_mib, "Fail (exit 1) when the daemon's peak RSS exceeds this")->check(CLI::Range(1.0, 1e6));
    app.add_option("--set", sets, "A configuration override KEY=JSON for the daemon, e.g. render.case_renderers_cached=1 (repeatable)");
    app.add_flag("--keep", g_keep, "Keep the temporary state folder");
    CLI11_PARSE(app, argc, argv);

    char tmpl[] = "/tmp/cf-daemon-memory-XXXXXX";
    if (!mkdtemp(tmpl)) {
        std::perror("daemon_memory: mkdtemp");
        return 3;
    }
    g_dir = tmpl;
    const auto load_before = loadavg();
    const std::time_t started = std::time(nullptr);

    // The configuration: the embedded defaults with the renderer, the phantom cases and no devices.
    json cfg;
    {
        const std::string cmd = daemon_exe + " --print-default-config";
        FILE* p = popen(cmd.c_str(), "r");
        if (!p) fail("cannot run " + cmd);
        std::string out;
        char buf[4096];
        for (std::size_t n; (n = fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, n);
        pclose(p);
        cfg = json::parse(out, nullptr, false);
        if (!cfg.is_object()) fail(cmd + " did not print a JSON object");
    }
    cfg["renderer"]["kind"] = renderer;
    cfg["tracker"]["enabled"] = false;
    cfg["camera"]["backend"] = "none";
    cfg["jobs"]["phantom_cases_at_start"] = cases;
    for (const auto& s : sets) {
        const auto eq = s.find('=');
        if (eq == std::string::npos) fail("--set " + s + ": not KEY=JSON");
        const json v = json::parse(s.substr(eq + 1), nullptr, false);
        if (v.is_discarded()) fail("--set " + s + ": the value is not JSON");
        cfg[json::json_pointer("/" + [&] {
            std::string k = s.substr(0, eq);
            std::replace(k.begin(), k.end(), '.', '/');
            return k;
        }())] = v;
    }
    std::ofstream(g_dir / "config.json") << cfg.dump(2);

    // Start the daemon and read its port from the log.
    g_pid = cf::bench::spawn_logged({daemon_exe, "--config", (g_dir / "config.json").string(), "--listen", "127.0.0.1:0",
                                     "--state-dir", (g_dir / "state").string()},
                                    g_dir / "cortexfused.log");
    const int port = cf::bench::wait_for_port(g_pid, g_dir / "cortexfused.log", 60);
    if (port < 0) {
        g_pid = -1;
        fail("cortexfused exited before listening");
    }
    if (port == 0) fail("cortexfused did not print its port within 60 s");

    httplib::Client ctl("127.0.0.1", port);
    ctl.set_read_timeout(600, 0);
    auto get = [&](const std::string& path) {
        auto r = ctl.Get(path);
        if (!r || r->status != 200) fail("GET " + path + ": " + (r ? std::to_string(r->status) + " " + r->body : "no answer"));
        return json::parse(r->body);
    };
    auto post = [&](const std::string& path, const json& body, int expect) {
        auto r = ctl.Post(path, body.dump(), "application/json");
        if (!r || r->status != expect) fail("POST " + path + ": " + (r ? std::to_string(r->status) + " " + r->body : "no answer"));
        return r->body;
    };
    auto wait_job = [&](long id, double timeout_s) {
        const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
        json j;
        while (Clock::now() < end) {
            j = get("/api/jobs/" + std::to_string(id));
            const std::string s = j.value("state", "");
            if (s == "succeeded") return j;
            if (s == "failed" || s == "cancelled") fail("job " + std::to_string(id) + " ended " + s + ": " + j.dump());
            std::this_thread::sleep_for(std::chrono::milliseconds(200));
        }
        fail("job " + std::to_string(id) + " did not end within " + std::to_string(timeout_s) + " s: " + j.dump());
    };

    // The phantom cases generated at start, imported, planned and registered.
    const auto t_setup = Clock::now();
    for (;;) {
        if (Clock::now() - t_setup > std::chrono::seconds(600)) fail("the phantom job at start did not succeed within 600 s");
        bool done = false;
        const json jobs = get("/api/jobs");
        for (const auto& j : jobs["jobs"])
            if (j["kind"] == "phantom") {
                if (j["state"] == "succeeded") done = true;
                if (j["state"] == "failed" || j["state"] == "cancelled") fail("the phantom job at start ended " + j.dump());
            }
        if (done) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
    std::vector<std::int64_t> ids;
    std::vector<double> plan_s;
    for (int i = 0; i < cases; ++i) {
        char folder[32];
        std::snprintf(folder, sizeof folder, "phantom/case_%04d", i);
        std::cerr << "daemon_memory: importing and planning " << folder << "\n";
        const json c = json::parse(post("/api/cases/import", {{"folder", folder}}, 201));
        const std::int64_t id = c.value("id", std::int64_t{0});
        ids.push_back(id);
        if (i > 0) {
            // The phantom cases share the bundled T1 (one content hash, so one cache entry in the
            // daemon): every case after the first gets its own T1 and mask, the same voxels with
            // the origin moved by i mm, uploaded as its newest volumes, so that each case open
            // holds its own loaded volume and renderer as different patients would.
            const cf::CaseSpec spec = cf::read_case(g_dir / "state" / "cases" / folder);
            if (!spec.brain_mask_path) fail(std::string(folder) + ": no brain mask");
            cf::Volume t1 = cf::load_volume(spec.volume_path);
            cf::LabelVolume m = cf::load_mask(*spec.brain_mask_path);
            t1.geom.origin_mm.x() += double(i);
            m.geom.origin_mm.x() += double(i);
            cf::save_volume(t1, g_dir / "t1_own.nii.gz");
            cf::save_mask(m, g_dir / "mask_own.nii.gz");
            const std::string base = "/api/cases/" + std::to_string(id) + "/volumes?name=";
            for (const auto& [name, mod] : {std::pair{"t1_own.nii.gz", "T1"}, std::pair{"mask_own.nii.gz", "mask"}}) {
                auto r = ctl.Post(base + name + "&modality=" + mod, read_file(g_dir / name), "application/octet-stream");
                if (!r || r->status != 201) fail(std::string("upload ") + name + ": " + (r ? std::to_string(r->status) + " " + r->body : "no answer"));
            }
        }
        const auto t0 = Clock::now();
        const json job = json::parse(post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", max_triangles}}}}, 202));
        wait_job(job.value("id", -1L), 900);
        plan_s.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
        const cf::CaseSpec pc = cf::read_case(g_dir / "state" / "cases" / folder);
        if (!pc.truth) fail(std::string(folder) + ": no truth.json");
        auto store = cf::db::CaseStore::open(g_dir / "state" / "store");
        cf::db::RegistrationInput in;
        in.final_pose = json{{"T_camera_from_world", cf::pose_to_json(pc.truth->T_camera_from_world)}};
        in.initial_pose = in.final_pose;
        in.nmi = 1.0;
        store->add_registration(id, in, cf::db::Actor{"daemon_memory", std::nullopt});
    }
    const double setup_s = std::chrono::duration<double>(Clock::now() - t_setup).count();
    const long rss_setup_kb = proc_status_kb(g_pid, "VmRSS"), hwm_setup_kb = proc_status_kb(g_pid, "VmHWM");

    std::cerr << "daemon_memory: set up in " << setup_s << " s; rendering\n";
    // The renders.
    std::vector<double> render_ms, fused_ms, rss_rounds_mib;
    int errors = 0;
    for (int r = 0; r < rounds; ++r) {
        for (const std::int64_t id : ids) {
            const json body = {{"case_id", id}, {"width", width}, {"height", height}, {"view", r % 2 ? "right" : "left"}};
            auto t0 = Clock::now();
            auto res = ctl.Post("/api/render", body.dump(), "application/json");
            render_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
            if (!res || res->status != 200) {
                ++errors;
                std::cerr << "POST /api/render case " << id << ": " << (res ? std::to_string(res->status) + " " + res->body : "no answer") << "\n";
            }
            t0 = Clock::now();
            res = ctl.Post("/api/cases/" + std::to_string(id) + "/fused", json{{"width", width}, {"height", height}}.dump(), "application/json");
            fused_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
            if (!res || res->status != 200) {
                ++errors;
                std::cerr << "POST /api/cases/" << id << "/fused: " << (res ? std::to_string(res->status) + " " + res->body : "no answer") << "\n";
            }
        }
        rss_rounds_mib.push_back(mib(proc_status_kb(g_pid, "VmRSS")));
    }
    const long hwm_kb = proc_status_kb(g_pid, "VmHWM");
    const json status = get("/api/status");
    const auto load_after = loadavg();
    stop_daemon();
    if (!g_keep) fs::remove_all(g_dir);

    char date[32];
    std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&started));
    const bool ok = errors == 0 && mib(hwm_kb) <= max_rss_mib;
    const json out = {{"benchmark", "daemon_memory"},
                      {"date_utc", date},
                      {"renderer_asked", renderer},
                      {"renderer", status["modules"].contains("renderer") ? status["modules"]["renderer"] : json()},
                      {"cases", cases},
                      {"rounds", rounds},
                      {"size", {width, height}},
                      {"setup_s", setup_s},
                      {"plan_s", plan_s},
                      {"render_ms_median", median(render_ms)},
                      {"fused_ms_median", median(fused_ms)},
                      {"errors", errors},
                      {"rss_after_setup_mib", mib(rss_setup_kb)},
                      {"peak_rss_after_setup_mib", mib(hwm_setup_kb)},
                      {"steady_rss_mib_median", median(rss_rounds_mib)},
                      {"rss_rounds_mib", rss_rounds_mib},
                      {"peak_rss_mib", mib(hwm_kb)},
                      {"max_rss_mib", max_rss_mib},
                      {"ok", ok},
                      {"loadavg_before", load_before},
                      {"loadavg_after", load_after}};
    std::cout << out.dump(2) << "\n";
    return ok ? 0 : 1;
}
