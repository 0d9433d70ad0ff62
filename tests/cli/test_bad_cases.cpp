// Data-driven bad-case suite for `cortexfuse register` (regression cases as data, as in DuckDB's
// sqllogictest): every folder under tests/cli/cases/ is one case. It is built from a copy of a
// small valid base case (base_case.hpp), changed by the files the folder holds (copied over the
// base) and by its `steps` file, then `cortexfuse register CASE --out OUT/result.json` runs and
// its `expect` file is checked. See tests/cli/README.md for the two file formats.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <regex>
#include <sstream>

#include "base_case.hpp"
#include "cortexfuse/core/volume.hpp"
#include "process.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

std::string slurp(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

void spit(const fs::path& p, const std::string& text) {
    std::ofstream out(p, std::ios::binary | std::ios::trunc);
    out << text;
    if (!out) throw std::runtime_error("cannot write " + p.string());
}

std::vector<std::string> split_ws(const std::string& line, size_t max_fields) {
    // The first max_fields-1 fields are whitespace separated; the last takes the rest of the line.
    std::vector<std::string> f;
    size_t i = 0;
    while (i < line.size() && f.size() + 1 < max_fields) {
        while (i < line.size() && std::isspace(static_cast<unsigned char>(line[i]))) ++i;
        size_t j = i;
        while (j < line.size() && !std::isspace(static_cast<unsigned char>(line[j]))) ++j;
        if (j > i) f.push_back(line.substr(i, j - i));
        i = j;
    }
    while (i < line.size() && std::isspace(static_cast<unsigned char>(line[i]))) ++i;
    if (i < line.size()) f.push_back(line.substr(i));
    return f;
}

std::string regex_escape(const std::string& s) {
    static const std::regex special(R"([.^$|()\[\]{}*+?\\])");
    return std::regex_replace(s, special, R"(\$&)");
}

struct Expect {
    std::string base = "small";
    int exit_code = 1;
    std::string stderr_regex;  // must match the one stderr line (regex_search); ${CASE} = the case folder
    bool result_written = false;
    bool skip_if_root = false;
    std::vector<std::string> extra_args;
    std::string out;  // --out instead of OUT/result.json
};

Expect read_expect(const fs::path& file) {
    Expect e;
    std::istringstream in(slurp(file));
    std::string line;
    while (std::getline(in, line)) {
        if (line.empty() || line[0] == '#') continue;
        const auto f = split_ws(line, 2);
        if (f.empty()) continue;
        const std::string& key = f[0];
        const std::string val = f.size() > 1 ? f[1] : "";
        if (key == "base") e.base = val;
        else if (key == "exit") e.exit_code = std::stoi(val);
        else if (key == "stderr") e.stderr_regex = val;
        else if (key == "result") e.result_written = (val == "written");
        else if (key == "skip-if-root") e.skip_if_root = true;
        else if (key == "out") e.out = val;
        else if (key == "args") {
            std::istringstream a(val);
            for (std::string t; a >> t;) e.extra_args.push_back(t);
        } else throw std::runtime_error(file.string() + ": unknown key \"" + key + "\"");
    }
    return e;
}

// Patches fields of an uncompressed NIfTI-1 header in place (little endian, as ITK writes it).
void nifti_set(const fs::path& p, const std::string& field, const std::vector<double>& v) {
    std::string b = slurp(p);
    if (b.size() < 348) throw std::runtime_error(p.string() + ": not a NIfTI-1 file");
    if (field == "dim") {  // dim[1..]
        for (size_t i = 0; i < v.size(); ++i) {
            const int16_t x = int16_t(v[i]);
            std::memcpy(&b[40 + 2 * (1 + i)], &x, 2);
        }
    } else if (field == "pixdim") {  // pixdim[1..]
        for (size_t i = 0; i < v.size(); ++i) {
            const float x = float(v[i]);
            std::memcpy(&b[76 + 4 * (1 + i)], &x, 4);
        }
    } else if (field == "first-voxel") {  // float32 data assumed
        float off;
        std::memcpy(&off, &b[108], 4);
        const float x = float(v.at(0));
        std::memcpy(&b[size_t(off)], &x, 4);
    } else {
        throw std::runtime_error("nifti-set: unknown field " + field);
    }
    spit(p, b);
}

std::vector<double> numbers(const std::string& s) {
    std::vector<double> v;
    std::istringstream in(s);
    for (std::string t; in >> t;) v.push_back(t == "nan" ? std::nan("") : std::stod(t));
    return v;
}

// One line of a `steps` file, applied inside the case folder `dir`.
void apply_step(const fs::path& dir, const std::string& line) {
    const auto f = split_ws(line, 4);
    const std::string& op = f.at(0);
    auto arg = [&](size_t i) -> const std::string& {
        if (f.size() <= i) throw std::runtime_error("step \"" + line + "\": missing argument");
        return f[i];
    };
    if (op == "remove") {  // remove FILE ("." removes the case folder itself)
        fs::remove_all(arg(1) == "." ? dir : dir / arg(1));
    } else if (op == "truncate") {  // keep a fraction of the bytes
        const std::string b = slurp(dir / arg(1));
        spit(dir / arg(1), b.substr(0, size_t(double(b.size()) * std::stod(arg(2)))));
    } else if (op == "make-dir") {  // a folder where a file should be
        fs::remove_all(dir / arg(1));
        fs::create_directories(dir / arg(1));
    } else if (op == "chmod") {
        fs::permissions(dir / arg(1), fs::perms(std::stoi(arg(2), nullptr, 8)));
    } else if (op == "set-json" || op == "set-json-raw") {
        // set-json FILE /json/pointer VALUE (VALUE is JSON); set-json-raw writes VALUE as raw text
        // (NaN, 1e999, ...), which no JSON library would write.
        json j = json::parse(slurp(dir / arg(1)));
        const std::string placeholder = "@@RAW@@";
        j[json::json_pointer(arg(2))] = op == "set-json" ? json::parse(arg(3)) : json(placeholder);
        std::string text = j.dump(2);
        if (op == "set-json-raw") text.replace(text.find("\"" + placeholder + "\""), placeholder.size() + 2, arg(3));
        spit(dir / arg(1), text + "\n");
    } else if (op == "remove-json") {
        json j = json::parse(slurp(dir / arg(1)));
        const json::json_pointer ptr(arg(2));
        j[ptr.parent_pointer()].erase(ptr.back());
        spit(dir / arg(1), j.dump(2) + "\n");
    } else if (op == "convert-volume") {  // convert-volume SRC DST (format by extension)
        cf::save_volume(cf::load_volume(dir / arg(1)), dir / arg(2));
    } else if (op == "nifti-set") {  // nifti-set FILE.nii dim|pixdim|first-voxel NUMBERS
        nifti_set(dir / arg(1), arg(2), numbers(arg(3)));
    } else if (op == "shift-volume") {  // shift-volume FILE "DX DY DZ" (mm, LPS)
        cf::Volume v = cf::load_volume(dir / arg(1));
        const auto d = numbers(arg(2) + (f.size() > 3 ? " " + f[3] : ""));
        v.geom.origin_mm += Eigen::Vector3d(d.at(0), d.at(1), d.at(2));
        cf::save_volume(v, dir / arg(1));
    } else if (op == "convert-photo") {  // convert-photo SRC DST (format by extension)
        const cv::Mat img = cv::imread((dir / arg(1)).string(), cv::IMREAD_COLOR);
        if (img.empty() || !cv::imwrite((dir / arg(2)).string(), img)) throw std::runtime_error("cannot convert " + arg(1));
    } else if (op == "resize-image") {  // resize-image FILE "W H"
        const auto wh = numbers(arg(2) + (f.size() > 3 ? " " + f[3] : ""));
        cv::Mat img = cv::imread((dir / arg(1)).string(), cv::IMREAD_COLOR), out;
        cv::resize(img, out, cv::Size(int(wh.at(0)), int(wh.at(1))), 0, 0, cv::INTER_AREA);
        if (!cv::imwrite((dir / arg(1)).string(), out)) throw std::runtime_error("cannot write " + arg(1));
    } else {
        throw std::runtime_error("unknown step \"" + op + "\"");
    }
}

void copy_overlay(const fs::path& from, const fs::path& to) {
    for (const auto& e : fs::directory_iterator(from)) {
        const std::string name = e.path().filename().string();
        if (name == "expect" || name == "steps" || name == "README.md") continue;
        fs::copy(e.path(), to / name, fs::copy_options::recursive | fs::copy_options::overwrite_existing);
    }
}

std::vector<std::string> case_names() {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(CF_CLI_CASES_DIR))
        if (e.is_directory() && fs::exists(e.path() / "expect")) names.push_back(e.path().filename().string());
    std::sort(names.begin(), names.end());
    return names;
}

fs::path fresh_dir(const std::string& name) {
    const fs::path p = fs::temp_directory_path() / ("cf_cli_" + name + "_" + std::to_string(::getpid()));
    fs::remove_all(p);
    fs::create_directories(p);
    return p;
}

class RegisterCase : public testing::TestWithParam<std::string> {};

}  // namespace

TEST_P(RegisterCase, BehavesAsExpected) {
    const fs::path src = fs::path(CF_CLI_CASES_DIR) / GetParam();
    const Expect ex = read_expect(src / "expect");
    if (ex.skip_if_root && ::geteuid() == 0) GTEST_SKIP() << "file permissions do not stop root";
    const fs::path work = fresh_dir(GetParam());
    const fs::path case_dir = work / "case", out_dir = work / "out";
    fs::copy(cf::test::base_cases() / ex.base, case_dir, fs::copy_options::recursive);
    fs::create_directories(out_dir);
    copy_overlay(src, case_dir);
    if (fs::exists(src / "steps")) {
        std::istringstream in(slurp(src / "steps"));
        std::string line;
        while (std::getline(in, line))
            if (!line.empty() && line[0] != '#') apply_step(case_dir, line);
    }

    std::vector<std::string> argv{cf::test::cortexfuse_exe(), "register", case_dir.string(), "--out",
                                  ex.out.empty() ? (out_dir / "result.json").string() : ex.out};
    for (std::string a : ex.extra_args) {
        for (size_t at; (at = a.find("${CASE}")) != std::string::npos;) a.replace(at, 7, case_dir.string());
        argv.push_back(a);
    }
    const auto r = cf::test::run_process(argv, 120.0);
    std::error_code ec;
    if (fs::exists(case_dir, ec))
        for (const auto& e : fs::recursive_directory_iterator(case_dir, ec))
            fs::permissions(e.path(), fs::perms::owner_all, fs::perm_options::add, ec);

    ASSERT_FALSE(r.timed_out) << "cortexfuse register did not finish";
    EXPECT_EQ(r.exit_code, ex.exit_code) << "stderr: " << r.err;
    std::vector<std::string> lines;
    {
        std::istringstream in(r.err);
        for (std::string l; std::getline(in, l);)
            if (!l.empty()) lines.push_back(l);
    }
    if (!ex.stderr_regex.empty()) {
        std::string pattern = ex.stderr_regex;
        for (size_t at; (at = pattern.find("${CASE}")) != std::string::npos;)
            pattern.replace(at, 7, regex_escape(case_dir.string()));
        ASSERT_EQ(lines.size(), 1u) << "expected one line on stderr, got:\n" << r.err;
        EXPECT_TRUE(std::regex_search(lines[0], std::regex(pattern))) << "stderr: " << lines[0] << "\nregex:  " << pattern;
    }
    // Nothing half-written: the result is whole (and parses) or absent, and no temporary is left.
    std::vector<std::string> left;
    for (const auto& e : fs::directory_iterator(out_dir)) left.push_back(e.path().filename().string());
    if (ex.result_written) {
        ASSERT_EQ(left, std::vector<std::string>{"result.json"});
        const json res = json::parse(slurp(out_dir / "result.json"));
        EXPECT_EQ(res.at("format"), "cortexfuse-result/1");
        EXPECT_EQ(res.at("T_camera_from_world").size(), 4u);
    } else {
        EXPECT_TRUE(left.empty()) << "written although the case is bad: " << left.front();
    }
    if (!ex.out.empty()) {
        EXPECT_FALSE(fs::exists(ex.out, ec)) << ex.out;
    }
    fs::remove_all(work);
}

INSTANTIATE_TEST_SUITE_P(Cases, RegisterCase, testing::ValuesIn(case_names()),
                         [](const testing::TestParamInfo<std::string>& param) {
                             std::string n = param.param;
                             for (auto& c : n)
                                 if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
                             return n;
                         });
