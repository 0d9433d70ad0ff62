#include "cortexfuse/core/optimizer.hpp"

#include <nlopt.hpp>

#include <limits>
#include <optional>
#include <stdexcept>

namespace cf {

namespace {
struct Ctx {
    const std::function<double(const std::vector<double>&)>* f;
    const CancelToken* cancel;
    int evals = 0;
    bool cancelled = false;
    nlopt::opt* opt;
    std::vector<double> best_x;
    double best_f = std::numeric_limits<double>::infinity();
};

double trampoline(const std::vector<double>& x, std::vector<double>&, void* data) {
    auto* c = static_cast<Ctx*>(data);
    if (c->cancel && c->cancel->cancelled()) {
        c->cancelled = true;
        c->opt->force_stop();
        return std::numeric_limits<double>::infinity();
    }
    ++c->evals;
    const double v = (*c->f)(x);
    if (v < c->best_f) {
        c->best_f = v;
        c->best_x = x;
    }
    return v;
}

/// NLopt's method for a SimplexOptions::algorithm name; nullopt for an unknown name.
std::optional<nlopt::algorithm> algorithm_of(const std::string& name) {
    if (name == "neldermead") return nlopt::LN_NELDERMEAD;
    if (name == "sbplx") return nlopt::LN_SBPLX;
    if (name == "bobyqa") return nlopt::LN_BOBYQA;
    return std::nullopt;
}
}  // namespace

bool simplex_algorithm_known(const std::string& name) { return algorithm_of(name).has_value(); }

SimplexResult nelder_mead(const std::function<double(const std::vector<double>&)>& f, const std::vector<double>& x0,
                          const SimplexOptions& o, const CancelToken* cancel) {
    const auto algo = algorithm_of(o.algorithm);
    if (!algo) throw std::invalid_argument("optimizer: unknown algorithm " + o.algorithm);
    nlopt::opt opt(*algo, unsigned(x0.size()));
    Ctx ctx{&f, cancel, 0, false, &opt, x0, std::numeric_limits<double>::infinity()};
    opt.set_min_objective(trampoline, &ctx);
    if (!o.initial_step.empty()) opt.set_initial_step(o.initial_step);
    if (!o.xtol_abs.empty()) opt.set_xtol_abs(o.xtol_abs);
    opt.set_ftol_abs(o.ftol_abs);
    opt.set_maxeval(std::max(1, o.max_evaluations));
    std::vector<double> x = x0;
    double fx = 0;
    try {
        opt.optimize(x, fx);
    } catch (const nlopt::forced_stop&) {
    } catch (const nlopt::roundoff_limited&) {
        // The simplex collapsed below double precision: the best point so far stands.
    }
    if (ctx.cancelled) throw Cancelled();
    return {ctx.best_x, ctx.best_f, ctx.evals};
}

}  // namespace cf
