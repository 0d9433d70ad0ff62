// The thread contract: one CaseStore shared by threads (serialised inside), and one CaseStore
// per thread on the same folder (WAL readers, writers waiting on the busy timeout).
#include <atomic>
#include <thread>

#include "db_test_util.hpp"

using namespace cf::db;
using namespace cfdbtest;

TEST(DbConcurrency, SharedInstanceAndInstancePerThread) {
    TempDir t;
    auto shared = CaseStore::open(t.path / "store", fast_options());
    constexpr int kThreads = 4, kEach = 15;
    std::atomic<int> failures{0};
    std::vector<std::thread> threads;
    for (int th = 0; th < kThreads; ++th) {
        threads.emplace_back([&, th] {
            try {
                // Even threads use the shared instance, odd ones their own connection.
                std::unique_ptr<CaseStore> own;
                if (th % 2) own = CaseStore::open(t.path / "store", fast_options());
                CaseStore& s = own ? *own : *shared;
                for (int i = 0; i < kEach; ++i) {
                    const auto c = s.create_case(std::nullopt, "t" + std::to_string(th) + "-" + std::to_string(i));
                    s.set_landmarks(c.id, landmarks(4, th));
                    s.import_volume_bytes(c.id, "volume " + std::to_string(th) + "/" + std::to_string(i), "v.nii",
                                          Modality::T1);
                    const auto r = s.get_case(c.id);
                    if (r.volumes.size() != 1 || !r.landmarks || r.landmarks->points != landmarks(4, th)) ++failures;
                    CaseQuery q;
                    q.limit = 1000;
                    (void)s.list_cases(q);
                }
            } catch (const std::exception& e) {
                ADD_FAILURE() << "thread " << th << ": " << e.what();
                ++failures;
            }
        });
    }
    for (auto& th : threads) th.join();
    EXPECT_EQ(failures.load(), 0);
    CaseQuery q;
    q.limit = 1000;
    EXPECT_EQ(shared->list_cases(q).size(), static_cast<std::size_t>(kThreads * kEach));
    EXPECT_TRUE(shared->check_integrity().ok);
}
