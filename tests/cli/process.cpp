#include "process.hpp"

#include "../sanitized.hpp"

#include <fcntl.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

namespace fs = std::filesystem;

namespace cf::test {

namespace {

std::string slurp(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}
}  // namespace

ProcessResult run_process(const std::vector<std::string>& argv, double timeout_s, double max_as_gib) {
    ProcessResult r;
    char tmpl[] = "/tmp/cf_proc_XXXXXX";
    const char* d = ::mkdtemp(tmpl);
    if (!d) return r;
    const fs::path dir(d);
    const std::string out_path = (dir / "stdout").string(), err_path = (dir / "stderr").string();
    std::vector<char*> args;
    for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);

    const pid_t pid = ::fork();
    if (pid == 0) {
        const int fo = ::open(out_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
        const int fe = ::open(err_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
        const int fi = ::open("/dev/null", O_RDONLY);
        if (fo < 0 || fe < 0 || fi < 0) ::_exit(126);
        ::dup2(fi, 0);
        ::dup2(fo, 1);
        ::dup2(fe, 2);
        if (!kSanitized && max_as_gib > 0) {
            rlimit lim{};
            lim.rlim_cur = lim.rlim_max = rlim_t(max_as_gib * 1024.0 * 1024.0 * 1024.0);
            ::setrlimit(RLIMIT_AS, &lim);
        }
        ::execv(args[0], args.data());
        ::_exit(127);
    }
    if (pid < 0) return r;
    const auto t0 = std::chrono::steady_clock::now();
    int status = 0;
    for (;;) {
        const pid_t w = ::waitpid(pid, &status, WNOHANG);
        if (w == pid) break;
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() > timeout_s) {
            ::kill(pid, SIGKILL);
            ::waitpid(pid, &status, 0);
            r.timed_out = true;
            break;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
    r.out = slurp(out_path);
    r.err = slurp(err_path);
    std::error_code ec;
    fs::remove_all(dir, ec);
    return r;
}

}  // namespace cf::test
