// Unit tests of optimizer.hpp: the NLopt Nelder-Mead wrapper (per-parameter initial steps,
// tolerances, evaluation budget, cancellation, the evaluation count).
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <thread>
#include <vector>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/optimizer.hpp"
#include "cortexfuse/core/progress.hpp"

using namespace cf;

namespace {

const std::vector<double> kCentre = {3, -2, 5, 10, -7, 1.5};
const std::vector<double> kWeight = {1, 4, 0.5, 2, 1, 8};

/// A shifted, anisotropically scaled quadratic in 6 parameters, minimum 0.25 at kCentre;
/// records every point it is asked about.
struct Quadratic {
    std::vector<std::vector<double>> calls;
    double operator()(const std::vector<double>& x) {
        calls.push_back(x);
        double s = 0.25;
        for (size_t i = 0; i < x.size(); ++i) s += kWeight[i] * (x[i] - kCentre[i]) * (x[i] - kCentre[i]);
        return s;
    }
};

SimplexOptions options() {
    SimplexOptions o;
    o.initial_step = {2, 3, 4, 5, 6, 7};
    o.xtol_abs.assign(6, 1e-5);
    o.ftol_abs = 1e-12;
    o.max_evaluations = 5000;
    return o;
}

}  // namespace

TEST(NelderMead, FindsTheMinimumOfAShiftedQuadratic) {
    Quadratic q;
    const SimplexResult r = nelder_mead([&](const std::vector<double>& x) { return q(x); }, std::vector<double>(6, 0.0), options());
    ASSERT_EQ(r.x.size(), 6u);
    for (size_t i = 0; i < 6; ++i) EXPECT_NEAR(r.x[i], kCentre[i], 1e-3) << "parameter " << i;
    EXPECT_NEAR(r.f, 0.25, 1e-6);
    // The reported evaluations are the calls made, and the result is the best of them.
    EXPECT_EQ(r.evaluations, int(q.calls.size()));
    EXPECT_LT(r.evaluations, 5000) << "converged by tolerance, not by budget";
    double best = 1e300;
    for (const auto& x : q.calls) best = std::min(best, Quadratic{}(x));
    EXPECT_DOUBLE_EQ(r.f, best);
    EXPECT_DOUBLE_EQ(Quadratic{}(r.x), r.f);
}

TEST(NelderMead, TheFirstSimplexUsesThePerParameterSteps) {
    Quadratic q;
    const std::vector<double> x0 = {1, 1, 1, 1, 1, 1};
    const SimplexOptions o = options();
    nelder_mead([&](const std::vector<double>& x) { return q(x); }, x0, o);
    ASSERT_GE(q.calls.size(), 7u);
    EXPECT_EQ(q.calls[0], x0);
    // Then one vertex per parameter i: parameter i moved from x0 by its own step, the later
    // ones still at x0 (NLopt builds each vertex from the best point so far, so the earlier
    // parameters may have moved by their steps too).
    for (size_t c = 1; c <= 6; ++c) {
        const size_t i = c - 1;
        EXPECT_DOUBLE_EQ(std::abs(q.calls[c][i] - x0[i]), o.initial_step[i]) << "vertex " << c;
        for (size_t j = c; j < 6; ++j) EXPECT_EQ(q.calls[c][j], x0[j]) << "vertex " << c << " parameter " << j;
        for (size_t j = 0; j < i; ++j) {
            const double d = std::abs(q.calls[c][j] - x0[j]);
            EXPECT_TRUE(d == 0 || std::abs(d - o.initial_step[j]) < 1e-12) << "vertex " << c << " parameter " << j;
        }
    }
}

TEST(NelderMead, RespectsTheEvaluationBudget) {
    for (const int budget : {1, 7, 25, 60}) {
        Quadratic q;
        SimplexOptions o = options();
        o.max_evaluations = budget;
        const SimplexResult r = nelder_mead([&](const std::vector<double>& x) { return q(x); }, std::vector<double>(6, 0.0), o);
        EXPECT_LE(int(q.calls.size()), budget);
        EXPECT_EQ(r.evaluations, int(q.calls.size()));
        EXPECT_GE(r.evaluations, std::min(budget, 7)) << "far from the minimum it must use the budget";
        // Still the best point seen, not x0 blindly.
        double best = 1e300;
        for (const auto& x : q.calls) best = std::min(best, Quadratic{}(x));
        EXPECT_DOUBLE_EQ(r.f, best);
    }
}

TEST(NelderMead, LooseToleranceStopsEarlier) {
    Quadratic tight, loose;
    SimplexOptions o = options();
    nelder_mead([&](const std::vector<double>& x) { return tight(x); }, std::vector<double>(6, 0.0), o);
    o.xtol_abs.assign(6, 0.5);
    o.ftol_abs = 0.1;
    const SimplexResult r = nelder_mead([&](const std::vector<double>& x) { return loose(x); }, std::vector<double>(6, 0.0), o);
    EXPECT_LT(loose.calls.size(), tight.calls.size());
    EXPECT_LT(r.f, 2.0);  // still near the minimum
}

TEST(NelderMead, CancellationStopsItWithCancelled) {
    // Cancelled from inside the objective after 10 evaluations: no further evaluation runs.
    CancelToken token;
    Quadratic q;
    auto f = [&](const std::vector<double>& x) {
        const double v = q(x);
        if (q.calls.size() == 10) token.cancel();
        return v;
    };
    EXPECT_THROW(nelder_mead(f, std::vector<double>(6, 0.0), options(), &token), Cancelled);
    EXPECT_EQ(q.calls.size(), 10u);
    // Already cancelled: the objective is never called.
    Quadratic none;
    EXPECT_THROW(nelder_mead([&](const std::vector<double>& x) { return none(x); }, std::vector<double>(6, 0.0), options(), &token),
                 Cancelled);
    EXPECT_TRUE(none.calls.empty());
    // A token that is never cancelled changes nothing.
    CancelToken idle;
    Quadratic a, b;
    const SimplexResult ra = nelder_mead([&](const std::vector<double>& x) { return a(x); }, std::vector<double>(6, 0.0), options(), &idle);
    const SimplexResult rb = nelder_mead([&](const std::vector<double>& x) { return b(x); }, std::vector<double>(6, 0.0), options());
    EXPECT_EQ(ra.x, rb.x);
    EXPECT_EQ(ra.evaluations, rb.evaluations);
}

TEST(NelderMead, CancelFromAnotherThread) {
    CancelToken token;
    std::atomic<int> calls{0};
    std::atomic<bool> started{false};
    // An objective that never converges on its own in the ~20 ms before the cancel (1 ms an evaluation).
    auto f = [&](const std::vector<double>& x) {
        started = true;
        ++calls;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
        double s = 0;
        for (double v : x) s += std::abs(std::sin(v));
        return s;
    };
    SimplexOptions o = options();
    o.max_evaluations = 1000000;
    o.xtol_abs.assign(6, 0.0);
    o.ftol_abs = 0;
    std::thread canceller([&] {
        while (!started) std::this_thread::yield();
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        token.cancel();
    });
    EXPECT_THROW(nelder_mead(f, std::vector<double>(6, 0.5), o, &token), Cancelled);
    canceller.join();
    EXPECT_LT(calls.load(), 100000);
}
