#pragma once
// A progress bar on stderr when it is a terminal; silent otherwise (logs stay clean).
// Ctrl-C cancels the running operation through the CancelToken.
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <cstdio>
#include <string>

#include "cortexfuse/core/progress.hpp"

namespace cf::cli {

class ProgressBar {
public:
    explicit ProgressBar(std::string label) : label_(std::move(label)), tty_(::isatty(2)) {
        progress_.cancel = &cancel_;
        progress_.report = [this](const std::string& stage, double f) { draw(stage, f); };
        active_ = &cancel_;
        std::signal(SIGINT, [](int) {
            if (active_) active_->cancel();
        });
    }
    ~ProgressBar() {
        if (tty_ && drawn_) std::fputs("\n", stderr);
        std::signal(SIGINT, SIG_DFL);
        active_ = nullptr;
    }
    const Progress& progress() const { return progress_; }
    CancelToken& cancel() { return cancel_; }

private:
    void draw(const std::string& stage, double f) {
        if (!tty_) return;
        const auto now = std::chrono::steady_clock::now();
        if (drawn_ && f < 1.0 && now - last_ < std::chrono::milliseconds(100)) return;
        last_ = now;
        drawn_ = true;
        const int width = 30, fill = int(f * width + 0.5);
        std::fprintf(stderr, "\r%s [%.*s%*s] %3d%% %-24s", label_.c_str(), fill, "##############################",
                     width - fill, "", int(f * 100 + 0.5), stage.c_str());
        std::fflush(stderr);
    }
    std::string label_;
    bool tty_;
    bool drawn_ = false;
    std::chrono::steady_clock::time_point last_{};
    CancelToken cancel_;
    Progress progress_;
    static inline CancelToken* active_ = nullptr;  // the one bar a process shows at a time (signal handler)
};

}  // namespace cf::cli
