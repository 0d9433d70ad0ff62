#include "cortexfuse/core/transfer_function.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>

#include "cortexfuse/core/error.hpp"

namespace cf {

using nlohmann::json;

void TransferFunction::validate(const std::string& context) const {
    if (colour.empty() || opacity.empty()) throw InputError(context, "transfer function needs colour and opacity points");
    auto check = [&](const char* what, auto const& pts, int n) {
        double prev = -1e300;
        for (const auto& p : pts) {
            for (int i = 0; i < n; ++i)
                if (!std::isfinite(p[i])) throw InputError(context, std::string(what) + " holds a non-finite number");
            if (p[0] < prev) throw InputError(context, std::string(what) + " points must be sorted by x");
            prev = p[0];
            for (int i = 1; i < n; ++i)
                if (p[i] < 0 || p[i] > 1) throw InputError(context, std::string(what) + " values must lie in [0, 1]");
        }
    };
    check("colour", colour, 4);
    check("opacity", opacity, 2);
    double prev = -1e300;
    for (const auto& p : gradient_opacity) {
        if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || p[0] < prev || p[1] < 0 || p[1] > 1)
            throw InputError(context, "gradient_opacity points must be finite, sorted, values in [0, 1]");
        prev = p[0];
    }
}

TransferFunction transfer_function_from_json(const json& j, const std::string& context) {
    TransferFunction tf;
    try {
        if (!j.is_object()) throw InputError(context, "transfer function must be a JSON object");
        tf.name = j.value("name", std::string("custom"));
        const std::string units = j.value("units", std::string("normalized"));
        if (units != "normalized" && units != "absolute")
            throw InputError(context, "units must be \"normalized\" or \"absolute\"");
        tf.normalized = units == "normalized";
        for (const auto& p : j.at("colour")) tf.colour.push_back({p.at(0).get<double>(), p.at(1).get<double>(), p.at(2).get<double>(), p.at(3).get<double>()});
        for (const auto& p : j.at("opacity")) tf.opacity.push_back({p.at(0).get<double>(), p.at(1).get<double>()});
        if (j.contains("gradient_opacity"))
            for (const auto& p : j.at("gradient_opacity")) tf.gradient_opacity.push_back({p.at(0).get<double>(), p.at(1).get<double>()});
    } catch (const json::exception& e) {
        throw InputError(context, std::string("malformed transfer function: ") + e.what());
    }
    tf.validate(context);
    return tf;
}

json to_json(const TransferFunction& tf) {
    json j;
    j["name"] = tf.name;
    j["units"] = tf.normalized ? "normalized" : "absolute";
    j["colour"] = tf.colour;
    j["opacity"] = tf.opacity;
    if (!tf.gradient_opacity.empty()) j["gradient_opacity"] = tf.gradient_opacity;
    return j;
}

TransferFunction load_transfer_function(const std::filesystem::path& path) {
    std::ifstream in(path);
    if (!in) throw InputError(path.string(), "cannot open transfer function file");
    json j;
    try {
        j = json::parse(in);
    } catch (const json::exception& e) {
        throw InputError(path.string(), std::string("not valid JSON: ") + e.what());
    }
    return transfer_function_from_json(j, path.string());
}

std::vector<std::string> preset_names() { return {"surface_white", "cortex_t1", "skin", "ct_bone", "fmri_hot"}; }

TransferFunction preset_transfer_function(const std::string& name) {
    TransferFunction tf;
    tf.name = name;
    if (name == "surface_white") {
        // An opaque white surface where grey matter starts: only the shape of the cortex is
        // shown, lit by the headlight (registration-lessons: this peaks at the true pose).
        tf.colour = {{0, 1, 1, 1}, {1, 1, 1, 1}};
        // The level sits between CSF and grey matter of a T1 inside the brain mask (0.38-0.46 of
        // the robust range): lower levels render the CSF/arachnoid envelope, whose similarity
        // to the photo peaked away from the truth in `cortexfuse landscape`.
        tf.opacity = {{0, 0}, {0.38, 0}, {0.46, 1}, {1, 1}};
    } else if (name == "cortex_t1") {
        // The seed's look: the T1 intensity just under the brain surface, tissue colours.
        tf.colour = {{0, 0.3, 0.1, 0.1}, {0.3, 0.75, 0.45, 0.4}, {0.55, 0.95, 0.75, 0.7}, {1, 1, 0.95, 0.9}};
        tf.opacity = {{0, 0}, {0.22, 0}, {0.35, 0.6}, {0.6, 1}, {1, 1}};
    } else if (name == "skin") {
        tf.colour = {{0, 0.8, 0.6, 0.5}, {1, 0.95, 0.8, 0.7}};
        tf.opacity = {{0, 0}, {0.08, 0}, {0.15, 1}, {1, 1}};
    } else if (name == "ct_bone") {
        tf.normalized = false;
        tf.colour = {{-1024, 0, 0, 0}, {150, 0.9, 0.8, 0.7}, {1000, 1, 1, 0.95}, {3000, 1, 1, 1}};
        tf.opacity = {{-1024, 0}, {150, 0}, {350, 0.8}, {3000, 1}};
    } else if (name == "fmri_hot") {
        tf.normalized = false;
        tf.colour = {{0, 0.5, 0, 0}, {3, 1, 0, 0}, {6, 1, 1, 0}, {12, 1, 1, 1}};
        tf.opacity = {{0, 0}, {2.9, 0}, {3.1, 0.5}, {12, 0.9}};
    } else {
        std::string known;
        for (const auto& n : preset_names()) known += (known.empty() ? "" : ", ") + n;
        throw InputError("transfer function \"" + name + "\"", "no such preset (known: " + known + ")");
    }
    return tf;
}

namespace {
template <size_t N>
std::array<double, N - 1> interp(const std::vector<std::array<double, N>>& pts, double x) {
    std::array<double, N - 1> out{};
    if (x <= pts.front()[0]) {
        for (size_t i = 1; i < N; ++i) out[i - 1] = pts.front()[i];
        return out;
    }
    if (x >= pts.back()[0]) {
        for (size_t i = 1; i < N; ++i) out[i - 1] = pts.back()[i];
        return out;
    }
    const auto it = std::upper_bound(pts.begin(), pts.end(), x, [](double v, const auto& p) { return v < p[0]; });
    const auto& b = *it;
    const auto& a = *(it - 1);
    const double w = b[0] > a[0] ? (x - a[0]) / (b[0] - a[0]) : 1.0;
    for (size_t i = 1; i < N; ++i) out[i - 1] = a[i] + w * (b[i] - a[i]);
    return out;
}
}  // namespace

float BakedTransferFunction::gradient_factor(float g) const {
    if (gradient_opacity.empty()) return 1.f;
    return float(interp(gradient_opacity, g)[0]);
}

BakedTransferFunction bake(const TransferFunction& tf, double range_lo, double range_hi, int size) {
    tf.validate("transfer function \"" + tf.name + "\"");
    BakedTransferFunction b;
    auto to_units = [&](double x) { return tf.normalized ? range_lo + x * (range_hi - range_lo) : x; };
    // The table spans the volume's range so every voxel maps inside it.
    b.lo = range_lo;
    b.hi = range_hi > range_lo ? range_hi : range_lo + 1;
    std::vector<std::array<double, 4>> col;
    std::vector<std::array<double, 2>> op;
    for (auto p : tf.colour) col.push_back({to_units(p[0]), p[1], p[2], p[3]});
    for (auto p : tf.opacity) op.push_back({to_units(p[0]), p[1]});
    const double scale = tf.normalized ? (range_hi - range_lo) : 1.0;
    for (auto p : tf.gradient_opacity) b.gradient_opacity.push_back({p[0] * scale, p[1]});
    b.rgba.resize(size_t(size));
    for (int i = 0; i < size; ++i) {
        const double x = b.lo + (b.hi - b.lo) * i / (size - 1);
        const auto c = interp(col, x);
        const auto o = interp(op, x);
        b.rgba[size_t(i)] = {float(c[0]), float(c[1]), float(c[2]), float(o[0])};
    }
    return b;
}

std::array<double, 2> robust_range(const Volume& v, const LabelVolume* mask) {
    // Percentiles of the non-zero voxels: background air does not dilute the range.
    std::vector<float> vals;
    vals.reserve(v.voxels.size() / 2);
    for (size_t i = 0; i < v.voxels.size(); i += 3)  // every third voxel is plenty
        if ((!mask || mask->voxels[i]) && v.voxels[i] != 0.f) vals.push_back(v.voxels[i]);
    if (vals.size() < 16) return {0.0, 1.0};
    auto pct = [&](double q) {
        const size_t idx = std::min(vals.size() - 1, size_t(q * double(vals.size() - 1)));
        std::nth_element(vals.begin(), vals.begin() + long(idx), vals.end());
        return double(vals[idx]);
    };
    const double lo = std::min(0.0, pct(0.01));
    const double hi = pct(0.995);
    return {lo, hi > lo ? hi : lo + 1};
}

std::array<double, 3> three_class_means(const std::vector<float>& values) {
    if (values.empty()) return {0.0, 0.0, 0.0};
    std::vector<float> v = values;
    std::sort(v.begin(), v.end());
    auto pct = [&](double p) { return double(v[size_t(p * double(v.size() - 1))]); };
    std::array<double, 3> m{pct(0.1), pct(0.45), pct(0.85)};
    // Histogram-based Lloyd iterations.
    const double lo = pct(0.001), hi = std::max(pct(0.999), pct(0.001) + 1e-6);
    constexpr int nb = 512;
    std::vector<double> hist(nb, 0.0);
    for (float x : v) {
        const int b = std::clamp(int((x - lo) / (hi - lo) * nb), 0, nb - 1);
        hist[size_t(b)] += 1;
    }
    for (int it = 0; it < 50; ++it) {
        std::array<double, 3> s{0, 0, 0}, c{0, 0, 0};
        for (int b = 0; b < nb; ++b) {
            const double x = lo + (b + 0.5) * (hi - lo) / nb;
            int best = 0;
            for (int q = 1; q < 3; ++q)
                if (std::abs(x - m[size_t(q)]) < std::abs(x - m[size_t(best)])) best = q;
            s[size_t(best)] += x * hist[size_t(b)];
            c[size_t(best)] += hist[size_t(b)];
        }
        for (int q = 0; q < 3; ++q)
            if (c[size_t(q)] > 0) m[size_t(q)] = s[size_t(q)] / c[size_t(q)];
        std::sort(m.begin(), m.end());
    }
    return m;
}

}  // namespace cf
