// Crash safety: a child process (cf_db_crash_writer) performs >= 200 writes through CaseStore,
// confirming each on a pipe after it committed; the parent SIGKILLs it at random (seeded)
// moments, over several rounds, resuming after the last confirmed write. Afterwards
// PRAGMA integrity_check is ok, every confirmed write is there and complete, and nothing is
// half there (every row's blob is present and hashes right, every registration has its result).
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <map>
#include <random>
#include <set>

#include "crash_ops.hpp"
#include "db_test_util.hpp"

using namespace cf::db;
using namespace cfdbtest;

namespace {

struct Round {
    std::vector<int> confirmed;
    bool killed = false;
    int exit_code = -1;
    std::string stderr_text;
};

/// Runs the writer for [first, end); kills it after `kill_after_lines` confirmations plus
/// `delay_us` (or `delay_us` after the start when kill_after_lines < 0). Reads every line it
/// wrote before dying.
Round run_writer(const fs::path& store, int first, int end, int kill_after_lines, int delay_us) {
    int out[2], err[2];
    if (pipe(out) != 0 || pipe(err) != 0) throw std::runtime_error("pipe failed");
    const pid_t pid = fork();
    if (pid == 0) {
        dup2(out[1], 1);
        dup2(err[1], 2);
        close(out[0]);
        close(err[0]);
        close(out[1]);
        close(err[1]);
        const std::string a = std::to_string(first), b = std::to_string(end);
        execl(CF_DB_CRASH_WRITER, CF_DB_CRASH_WRITER, store.c_str(), a.c_str(), b.c_str(), static_cast<char*>(nullptr));
        _exit(127);
    }
    close(out[1]);
    close(err[1]);
    fcntl(err[0], F_SETFL, O_NONBLOCK);
    Round r;
    std::string buf;
    int lines = 0;
    bool kill_armed = false;
    auto kill_at = std::chrono::steady_clock::now() + std::chrono::hours(1);
    if (kill_after_lines < 0) {
        kill_armed = true;
        kill_at = std::chrono::steady_clock::now() + std::chrono::microseconds(delay_us);
    }
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    bool eof = false;
    while (!eof) {
        const auto now = std::chrono::steady_clock::now();
        if (now > deadline) {
            kill(pid, SIGKILL);
            throw std::runtime_error("writer hung");
        }
        if (kill_armed && !r.killed && now >= kill_at) {
            kill(pid, SIGKILL);
            r.killed = true;
        }
        int timeout_ms = 100;
        if (kill_armed && !r.killed)
            timeout_ms = static_cast<int>(std::max<std::int64_t>(
                0, std::chrono::duration_cast<std::chrono::milliseconds>(kill_at - now).count()));
        pollfd p{out[0], POLLIN, 0};
        if (poll(&p, 1, timeout_ms) <= 0) continue;
        char tmp[4096];
        const ssize_t n = read(out[0], tmp, sizeof tmp);
        if (n <= 0) {
            eof = true;
            break;
        }
        buf.append(tmp, static_cast<std::size_t>(n));
        for (std::size_t nl; (nl = buf.find('\n')) != std::string::npos;) {
            const std::string line = buf.substr(0, nl);
            buf.erase(0, nl + 1);
            if (line.rfind("ok ", 0) == 0) r.confirmed.push_back(std::stoi(line.substr(3)));
            if (++lines == kill_after_lines && !kill_armed) {
                kill_armed = true;
                kill_at = std::chrono::steady_clock::now() + std::chrono::microseconds(delay_us);
            }
        }
    }
    close(out[0]);
    int status = 0;
    waitpid(pid, &status, 0);
    char tmp[4096];
    for (ssize_t n; (n = read(err[0], tmp, sizeof tmp)) > 0;) r.stderr_text.append(tmp, static_cast<std::size_t>(n));
    close(err[0]);
    if (WIFEXITED(status)) r.exit_code = WEXITSTATUS(status);
    if (WIFSIGNALED(status)) r.killed = WTERMSIG(status) == SIGKILL;
    return r;
}

}  // namespace

TEST(DbCrash, ConfirmedWritesSurviveSigkill) {
    TempDir t;
    const fs::path store = t.path / "store";
    constexpr int kWrites = 240;
    std::mt19937 rng(20261122);
    std::set<int> confirmed;
    int next = 0, rounds = 0, kills = 0;
    while (next < kWrites) {
        ASSERT_LT(rounds, 200) << "too many rounds";
        int after = -1, delay_us = 0;
        if (rounds % 4 == 1) {
            delay_us = std::uniform_int_distribution<int>(0, 30000)(rng);  // any moment, open included
        } else {
            after = std::uniform_int_distribution<int>(1, 40)(rng);
            delay_us = std::uniform_int_distribution<int>(0, 3000)(rng);
        }
        const Round r = run_writer(store, next, kWrites, after, delay_us);
        ++rounds;
        ASSERT_TRUE(r.killed || r.exit_code == 0) << "writer failed (exit " << r.exit_code << "): " << r.stderr_text;
        kills += r.killed ? 1 : 0;
        for (int i : r.confirmed) {
            ASSERT_EQ(i, next) << "confirmations out of order";
            confirmed.insert(i);
            ++next;
        }
    }
    EXPECT_GE(static_cast<int>(confirmed.size()), 200);
    EXPECT_GE(kills, 5) << "rounds " << rounds;
    std::printf("crash test: %d confirmed writes, %d rounds, %d SIGKILLs\n", static_cast<int>(confirmed.size()), rounds, kills);
    RecordProperty("rounds", rounds);
    RecordProperty("kills", kills);

    // PRAGMA integrity_check on a fresh connection of its own.
    {
        sqlite3* h = nullptr;
        ASSERT_EQ(sqlite3_open((store / "cortexfuse.sqlite").c_str(), &h), SQLITE_OK);
        sqlite3_stmt* st = nullptr;
        ASSERT_EQ(sqlite3_prepare_v2(h, "PRAGMA integrity_check", -1, &st, nullptr), SQLITE_OK);
        ASSERT_EQ(sqlite3_step(st), SQLITE_ROW);
        EXPECT_STREQ(reinterpret_cast<const char*>(sqlite3_column_text(st, 0)), "ok");
        sqlite3_finalize(st);
        sqlite3_close(h);
    }
    auto s = CaseStore::open(store, fast_options());
    const auto rep = s->check_integrity(true);  // integrity_check, foreign keys, every blob re-hashed
    EXPECT_TRUE(rep.ok) << (rep.problems.empty() ? "" : rep.problems[0]);

    CaseQuery q;
    q.limit = 10000;
    std::map<std::string, std::vector<CaseRecord>> by_title;
    for (const auto& c : s->list_cases(q)) by_title[c.title].push_back(s->get_case(c.id));
    // Nothing half there: every registration has its one result file, readable and intact.
    for (const auto& [title, cases] : by_title)
        for (const auto& c : cases)
            for (const auto& reg : c.registrations) {
                ASSERT_EQ(reg.results.size(), 1u) << title << " registration " << reg.id;
                EXPECT_EQ(s->read_blob(reg.results[0].blob.sha256), cfcrash::payload(reg.params["op"].get<int>()));
            }
    // Every confirmed write is there and complete.
    for (int i : confirmed) {
        SCOPED_TRACE("write " + std::to_string(i));
        const auto it = by_title.find(cfcrash::case_title(i));
        ASSERT_NE(it, by_title.end());
        bool found = false;
        for (const auto& c : it->second) {
            switch (i % 4) {
                case 0: found = true; break;
                case 1:
                    for (const auto& set : s->landmark_history(c.summary.id)) found |= set.points == cfcrash::landmark_points(i);
                    break;
                case 2:
                    for (const auto& reg : c.registrations)
                        if (reg.params["op"] == i) {
                            found = reg.params == cfcrash::registration(i).params && reg.final_pose &&
                                    *reg.final_pose == *cfcrash::registration(i).final_pose;
                        }
                    break;
                case 3:
                    for (const auto& v : c.volumes)
                        if (v.original_name == cfcrash::volume_name(i)) {
                            found = v.blob.sha256 == BlobStore::sha256_of(cfcrash::payload(i)) &&
                                    s->read_blob(v.blob.sha256) == cfcrash::payload(i);
                        }
                    break;
            }
        }
        EXPECT_TRUE(found);
    }
}
