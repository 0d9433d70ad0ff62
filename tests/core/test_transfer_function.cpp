// Unit tests of transfer_function.hpp: presets, validation, JSON (in memory and on disk),
// baking of the piecewise-linear functions into tables, gradient-magnitude modulation.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <unistd.h>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/transfer_function.hpp"

namespace fs = std::filesystem;
using namespace cf;
using nlohmann::json;

namespace {

TransferFunction absolute_tf() {
    TransferFunction tf;
    tf.name = "t";
    tf.normalized = false;
    tf.colour = {{0, 0, 0, 0}, {100, 1, 0.5, 0}, {200, 0, 1, 0.25}};
    tf.opacity = {{0, 0}, {50, 0}, {100, 1}};
    return tf;
}

/// Runs `f`, expects an InputError whose input is `input` and whose message contains `problem`.
template <class F>
void expect_input_error(F&& f, const std::string& input, const std::string& problem) {
    try {
        f();
        ADD_FAILURE() << "no InputError; expected \"" << problem << "\"";
    } catch (const InputError& e) {
        EXPECT_EQ(e.input(), input) << e.what();
        EXPECT_NE(std::string(e.what()).find(problem), std::string::npos) << e.what();
    }
}

json valid_json() {
    return json{{"name", "mine"},
                {"units", "absolute"},
                {"colour", {{0, 0, 0, 0}, {10, 1, 1, 1}}},
                {"opacity", {{0, 0}, {10, 1}}}};
}

}  // namespace

TEST(TransferFunction, EveryListedPresetLoadsValidatesAndBakes) {
    const auto names = preset_names();
    for (const char* expected : {"cortex_t1", "surface_white", "skin", "ct_bone", "fmri_hot"})
        EXPECT_NE(std::find(names.begin(), names.end(), expected), names.end()) << expected;
    for (const auto& n : names) {
        const TransferFunction tf = preset_transfer_function(n);
        EXPECT_EQ(tf.name, n);
        EXPECT_NO_THROW(tf.validate(n));
        for (const int size : {2, 256, 1024}) {
            const BakedTransferFunction b = bake(tf, tf.normalized ? 10.0 : -1024.0, tf.normalized ? 500.0 : 3000.0, size);
            ASSERT_EQ(b.rgba.size(), size_t(size)) << n;
            for (const auto& e : b.rgba)
                for (const float x : e) EXPECT_TRUE(x >= 0.f && x <= 1.f) << n;
        }
        // Default size.
        EXPECT_EQ(bake(tf, 0, 1).rgba.size(), 1024u);
        // Every preset shows something: opacity reaches 1 or close to it at the top.
        const BakedTransferFunction b = bake(tf, 0, tf.normalized ? 1.0 : 3000.0, 64);
        EXPECT_GT(b.rgba.back()[3], 0.8f) << n;
        EXPECT_EQ(b.rgba.front()[3], 0.f) << n;
    }
    EXPECT_FALSE(preset_transfer_function("ct_bone").normalized);  // Hounsfield units
    EXPECT_TRUE(preset_transfer_function("cortex_t1").normalized);
}

TEST(TransferFunction, UnknownPresetIsAnInputErrorNamingIt) {
    expect_input_error([] { preset_transfer_function("bone_ct"); }, "transfer function \"bone_ct\"", "no such preset");
    try {
        preset_transfer_function("nope");
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("cortex_t1"), std::string::npos) << "lists the known presets: " << e.what();
    }
}

TEST(TransferFunction, BakeInterpolatesLinearlyBetweenAndExactlyAtControlPoints) {
    const TransferFunction tf = absolute_tf();
    // Entry i sits at intensity lo + (hi - lo) * i / (size - 1) = i here.
    const BakedTransferFunction b = bake(tf, 0, 250, 251);
    EXPECT_DOUBLE_EQ(b.lo, 0);
    EXPECT_DOUBLE_EQ(b.hi, 250);
    auto near = [](const std::array<float, 4>& e, std::array<float, 4> want) {
        for (int i = 0; i < 4; ++i) EXPECT_NEAR(e[size_t(i)], want[size_t(i)], 1e-6) << "channel " << i;
    };
    near(b.rgba[0], {0, 0, 0, 0});
    near(b.rgba[25], {0.25f, 0.125f, 0, 0});
    near(b.rgba[50], {0.5f, 0.25f, 0, 0});
    near(b.rgba[75], {0.75f, 0.375f, 0, 0.5f});
    near(b.rgba[100], {1, 0.5f, 0, 1});
    near(b.rgba[150], {0.5f, 0.75f, 0.125f, 1});
    near(b.rgba[200], {0, 1, 0.25f, 1});
    near(b.rgba[250], {0, 1, 0.25f, 1});  // beyond the last point: held
}

TEST(TransferFunction, NormalizedPointsMapOntoTheGivenRange) {
    TransferFunction tf;
    tf.colour = {{0, 0, 0, 0}, {1, 1, 1, 1}};
    tf.opacity = {{0, 0}, {0.25, 0}, {0.75, 1}, {1, 1}};
    const BakedTransferFunction b = bake(tf, 100, 300, 201);  // entry i at 100 + i
    EXPECT_NEAR(b.rgba[0][0], 0.f, 1e-6);
    EXPECT_NEAR(b.rgba[100][0], 0.5f, 1e-6);
    EXPECT_NEAR(b.rgba[200][0], 1.f, 1e-6);
    EXPECT_NEAR(b.rgba[50][3], 0.f, 1e-6);   // 0.25 of the range
    EXPECT_NEAR(b.rgba[100][3], 0.5f, 1e-6);
    EXPECT_NEAR(b.rgba[150][3], 1.f, 1e-6);  // 0.75 of the range
    // Absolute units ignore the range.
    tf.normalized = false;
    const BakedTransferFunction a = bake(tf, 0, 2, 201);  // entry i at i / 100
    EXPECT_NEAR(a.rgba[50][0], 0.5f, 1e-6);
    EXPECT_NEAR(a.rgba[100][0], 1.f, 1e-6);
    EXPECT_NEAR(a.rgba[50][3], 0.5f, 1e-6);
}

TEST(TransferFunction, GradientMagnitudeModulatesOpacity) {
    TransferFunction tf = absolute_tf();
    EXPECT_FALSE(bake(tf, 0, 200).uses_gradient());
    EXPECT_FLOAT_EQ(bake(tf, 0, 200).gradient_factor(123.f), 1.f);
    tf.gradient_opacity = {{0, 0}, {2, 0}, {10, 1}};
    BakedTransferFunction b = bake(tf, 0, 200);
    EXPECT_TRUE(b.uses_gradient());
    EXPECT_FLOAT_EQ(b.gradient_factor(0.f), 0.f);
    EXPECT_FLOAT_EQ(b.gradient_factor(2.f), 0.f);
    EXPECT_NEAR(b.gradient_factor(6.f), 0.5f, 1e-6);
    EXPECT_FLOAT_EQ(b.gradient_factor(10.f), 1.f);
    EXPECT_FLOAT_EQ(b.gradient_factor(1000.f), 1.f);
    // Normalized: x is in units of the range per mm, so it scales with the range.
    tf.normalized = true;
    tf.colour = {{0, 1, 1, 1}, {1, 1, 1, 1}};
    tf.opacity = {{0, 1}, {1, 1}};
    tf.gradient_opacity = {{0, 0}, {0.1, 1}};
    b = bake(tf, 0, 1000);
    EXPECT_NEAR(b.gradient_factor(50.f), 0.5f, 1e-6);
    EXPECT_FLOAT_EQ(b.gradient_factor(100.f), 1.f);
    b = bake(tf, 0, 10);
    EXPECT_NEAR(b.gradient_factor(0.5f), 0.5f, 1e-6);
}

TEST(TransferFunction, JsonRoundTripInMemoryAndThroughAFile) {
    TransferFunction tf = absolute_tf();
    tf.name = "round trip";
    tf.gradient_opacity = {{0, 0.25}, {3.5, 1}};
    const TransferFunction back = transfer_function_from_json(to_json(tf), "mem");
    EXPECT_EQ(back.name, tf.name);
    EXPECT_EQ(back.normalized, tf.normalized);
    EXPECT_EQ(back.colour, tf.colour);
    EXPECT_EQ(back.opacity, tf.opacity);
    EXPECT_EQ(back.gradient_opacity, tf.gradient_opacity);
    for (const auto& n : preset_names()) {
        const TransferFunction p = preset_transfer_function(n);
        const TransferFunction q = transfer_function_from_json(json::parse(to_json(p).dump()), n);
        EXPECT_EQ(q.normalized, p.normalized) << n;
        EXPECT_EQ(q.colour, p.colour) << n;
        EXPECT_EQ(q.opacity, p.opacity) << n;
        EXPECT_EQ(q.gradient_opacity, p.gradient_opacity) << n;
    }
    const fs::path dir = fs::temp_directory_path() / ("cf_test_tf_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const fs::path file = dir / "tf.json";
    std::ofstream(file) << to_json(tf).dump(2);
    const TransferFunction f = load_transfer_function(file);
    EXPECT_EQ(f.colour, tf.colour);
    EXPECT_EQ(f.opacity, tf.opacity);
    EXPECT_EQ(f.gradient_opacity, tf.gradient_opacity);
    // Defaults: no name -> "custom", no units -> normalized.
    json j = valid_json();
    j.erase("name");
    j.erase("units");
    const TransferFunction d = transfer_function_from_json(j, "mem");
    EXPECT_EQ(d.name, "custom");
    EXPECT_TRUE(d.normalized);
    fs::remove_all(dir);
}

TEST(TransferFunction, MalformedJsonIsAnInputErrorNamingTheProblem) {
    auto from = [](json j) { return [j] { transfer_function_from_json(j, "tf.json"); }; };
    expect_input_error(from(json::array({1, 2})), "tf.json", "must be a JSON object");
    json j = valid_json();
    j.erase("opacity");
    expect_input_error(from(j), "tf.json", "malformed transfer function");
    j = valid_json();
    j["colour"] = {{0, 1, 1}};  // three numbers where four belong
    expect_input_error(from(j), "tf.json", "malformed transfer function");
    j = valid_json();
    j["opacity"] = {{0, "opaque"}};
    expect_input_error(from(j), "tf.json", "malformed transfer function");
    j = valid_json();
    j["units"] = "percent";
    expect_input_error(from(j), "tf.json", "units must be");
    j = valid_json();
    j["colour"] = json::array();
    expect_input_error(from(j), "tf.json", "needs colour and opacity");
    // Control points out of order.
    j = valid_json();
    j["opacity"] = {{0, 0}, {10, 1}, {5, 1}};
    expect_input_error(from(j), "tf.json", "opacity points must be sorted");
    j = valid_json();
    j["colour"] = {{5, 0, 0, 0}, {1, 1, 1, 1}};
    expect_input_error(from(j), "tf.json", "colour points must be sorted");
    j = valid_json();
    j["gradient_opacity"] = {{1, 0}, {0, 1}};
    expect_input_error(from(j), "tf.json", "gradient_opacity");
    // Values outside [0, 1].
    j = valid_json();
    j["opacity"] = {{0, 0}, {10, 1.5}};
    expect_input_error(from(j), "tf.json", "opacity values must lie in [0, 1]");
    j = valid_json();
    j["colour"] = {{0, -0.1, 0, 0}, {10, 1, 1, 1}};
    expect_input_error(from(j), "tf.json", "colour values must lie in [0, 1]");
    j = valid_json();
    j["gradient_opacity"] = {{0, 0}, {1, 2}};
    expect_input_error(from(j), "tf.json", "gradient_opacity");
}

TEST(TransferFunction, ValidateRejectsNonFiniteNumbersAndBakeValidates) {
    TransferFunction tf = absolute_tf();
    EXPECT_NO_THROW(tf.validate("ok"));
    tf.opacity[1][0] = std::numeric_limits<double>::quiet_NaN();
    expect_input_error([&] { tf.validate("ctx"); }, "ctx", "non-finite");
    tf = absolute_tf();
    tf.colour[2][0] = std::numeric_limits<double>::infinity();
    expect_input_error([&] { tf.validate("ctx"); }, "ctx", "non-finite");
    tf = absolute_tf();
    tf.opacity = {{0, 0}, {100, 1.01}};
    EXPECT_THROW(bake(tf, 0, 1), InputError);
}

TEST(TransferFunction, LoadingABadFileNamesTheFile) {
    const fs::path dir = fs::temp_directory_path() / ("cf_test_tfbad_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const fs::path missing = dir / "missing.json";
    expect_input_error([&] { load_transfer_function(missing); }, missing.string(), "cannot open");
    const fs::path broken = dir / "broken.json";
    std::ofstream(broken) << "{\"colour\": [[0, 1, 1, 1]";
    expect_input_error([&] { load_transfer_function(broken); }, broken.string(), "not valid JSON");
    const fs::path unsorted = dir / "unsorted.json";
    std::ofstream(unsorted) << R"({"colour": [[0, 1, 1, 1]], "opacity": [[1, 0], [0, 1]]})";
    expect_input_error([&] { load_transfer_function(unsorted); }, unsorted.string(), "sorted");
    fs::remove_all(dir);
}

namespace {
/// 30^3 voxels: every 7th is 0 (background), the others cycle through 101..1100.
Volume uniform_volume() {
    Volume v;
    v.geom.dims = {30, 30, 30};
    v.voxels.resize(v.geom.voxel_count());
    for (size_t i = 0; i < v.voxels.size(); ++i) v.voxels[i] = i % 7 == 0 ? 0.f : float(101 + i % 1000);
    return v;
}
}  // namespace

TEST(TransferFunction, RobustRangeTopIsThe995thPercentileOfNonZeroVoxels) {
    const Volume v = uniform_volume();
    const auto r = robust_range(v);
    EXPECT_NEAR(r[1], 101 + 0.995 * 999, 6);
    EXPECT_LE(r[0], 101 + 0.01 * 999 + 6);  // at most the 1st percentile (see the DISABLED test below)
    // Only inside a mask.
    LabelVolume m;
    m.geom = v.geom;
    m.voxels.resize(v.voxels.size());
    for (size_t i = 0; i < m.voxels.size(); ++i) m.voxels[i] = v.voxels[i] < 501.f;
    EXPECT_NEAR(robust_range(v, &m)[1], 101 + 0.995 * 399, 6);
    // Negative values (CT): the bottom follows the data.
    Volume ct = v;
    for (auto& x : ct.voxels)
        if (x != 0.f) x -= 1100.f;  // -999..0
    EXPECT_NEAR(robust_range(ct)[0], -999 + 0.01 * 999, 6);
    // Almost nothing non-zero: the unit range.
    Volume empty = v;
    std::fill(empty.voxels.begin(), empty.voxels.end(), 0.f);
    EXPECT_EQ(robust_range(empty), (std::array<double, 2>{0.0, 1.0}));
}

// The bottom of the range is min(0, 1st percentile): 0 for an all-positive MRI, so that the
// presets' x = 0 is "no signal" on every scan (the header says so).
TEST(TransferFunction, RobustRangeBottomIsZeroForAPositiveVolume) {
    EXPECT_EQ(robust_range(uniform_volume())[0], 0.0);
}
