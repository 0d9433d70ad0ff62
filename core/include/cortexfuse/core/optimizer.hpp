#pragma once
// Downhill simplex (Nelder-Mead) through NLopt, with per-parameter initial steps,
// evaluation budget and cancellation.
#include <functional>
#include <string>
#include <vector>

#include "cortexfuse/core/progress.hpp"

namespace cf {

struct SimplexOptions {
    std::vector<double> initial_step;   // per parameter
    std::vector<double> xtol_abs;       // per parameter; stop when the simplex is this small
    double ftol_abs = 1e-5;
    int max_evaluations = 200;
    /// "neldermead", "sbplx" or "bobyqa" (NLopt's LN_* methods).
    std::string algorithm = "neldermead";
};

struct SimplexResult {
    std::vector<double> x;
    double f = 0;
    int evaluations = 0;
};

/// Minimises f from x0. Throws Cancelled if `cancel` fires (checked every evaluation).
/// Whether `name` is one of SimplexOptions::algorithm's values.
bool simplex_algorithm_known(const std::string& name);

SimplexResult nelder_mead(const std::function<double(const std::vector<double>&)>& f, const std::vector<double>& x0,
                          const SimplexOptions& opt, const CancelToken* cancel = nullptr);

}  // namespace cf
