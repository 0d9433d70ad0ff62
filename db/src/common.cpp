// Time, enumeration strings and the validation of inputs shared by the API and the importers.
#include <sodium.h>

#include <cmath>
#include <cstdio>
#include <ctime>
#include <set>

#include "store_impl.hpp"

namespace cf::db {

using K = StoreError::Kind;
using nlohmann::json;

UtcTime system_now_utc() {
    return std::chrono::time_point_cast<std::chrono::milliseconds>(std::chrono::system_clock::now());
}

std::string format_utc(UtcTime t) {
    const std::int64_t ms = t.time_since_epoch().count();
    std::int64_t secs = ms / 1000, rem = ms % 1000;
    if (rem < 0) {
        rem += 1000;
        secs -= 1;
    }
    const std::time_t tt = static_cast<std::time_t>(secs);
    std::tm tm{};
    gmtime_r(&tt, &tm);
    char buf[64];
    std::snprintf(buf, sizeof buf, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", tm.tm_year + 1900, tm.tm_mon + 1, tm.tm_mday,
                  tm.tm_hour, tm.tm_min, tm.tm_sec, static_cast<int>(rem));
    return buf;
}

UtcTime parse_utc(std::string_view text) {
    const std::string s(text);
    int Y, M, D, h, m, sec, ms;
    char z = 0;
    if (s.size() != 24 || std::sscanf(s.c_str(), "%4d-%2d-%2dT%2d:%2d:%2d.%3d%c", &Y, &M, &D, &h, &m, &sec, &ms, &z) != 8 ||
        z != 'Z' || M < 1 || M > 12 || D < 1 || D > 31 || h > 23 || m > 59 || sec > 60)
        throw StoreError(K::Invalid, "time '" + s.substr(0, 40) + "': expected UTC as YYYY-MM-DDTHH:MM:SS.mmmZ");
    std::tm tm{};
    tm.tm_year = Y - 1900;
    tm.tm_mon = M - 1;
    tm.tm_mday = D;
    tm.tm_hour = h;
    tm.tm_min = m;
    tm.tm_sec = sec;
    const std::int64_t secs = static_cast<std::int64_t>(timegm(&tm));
    return UtcTime(std::chrono::milliseconds(secs * 1000 + ms));
}

namespace {
constexpr const char* kStates[] = {"new", "planned", "patient_registered", "photo_captured",
                                   "landmarks", "roi", "registered", "reviewed"};
constexpr const char* kModalities[] = {"T1", "CT", "fMRI", "mask"};
constexpr const char* kRoles[] = {"surgeon", "technician", "reviewer", "admin"};
constexpr const char* kRegStatus[] = {"succeeded", "failed", "cancelled"};

template <class E, std::size_t N>
E from_string(std::string_view s, const char* const (&names)[N], const char* what) {
    for (std::size_t i = 0; i < N; ++i)
        if (s == names[i]) return static_cast<E>(i);
    std::string all;
    for (std::size_t i = 0; i < N; ++i) all += (i ? ", " : "") + std::string(names[i]);
    throw StoreError(K::Invalid, std::string(what) + " '" + std::string(s.substr(0, 40)) + "': expected one of " + all);
}
}  // namespace

const char* to_string(CaseState s) { return kStates[static_cast<int>(s)]; }
const char* to_string(Modality m) { return kModalities[static_cast<int>(m)]; }
const char* to_string(Role r) { return kRoles[static_cast<int>(r)]; }
const char* to_string(RegistrationStatus s) { return kRegStatus[static_cast<int>(s)]; }
CaseState case_state_from_string(std::string_view s) { return from_string<CaseState>(s, kStates, "case state"); }
Modality modality_from_string(std::string_view s) { return from_string<Modality>(s, kModalities, "modality"); }
Role role_from_string(std::string_view s) { return from_string<Role>(s, kRoles, "role"); }
RegistrationStatus registration_status_from_string(std::string_view s) {
    return from_string<RegistrationStatus>(s, kRegStatus, "registration status");
}

std::string random_hex(std::size_t bytes) {
    std::vector<unsigned char> b(bytes);
    randombytes_buf(b.data(), b.size());
    std::string s(2 * bytes, '0');
    static const char* d = "0123456789abcdef";
    for (std::size_t i = 0; i < bytes; ++i) {
        s[2 * i] = d[b[i] >> 4];
        s[2 * i + 1] = d[b[i] & 15];
    }
    return s;
}

namespace {
bool finite_number(const json& j) { return j.is_number() && std::isfinite(j.get<double>()); }
}  // namespace

void validate_intrinsics(const json& j, const std::string& what) {
    auto bad = [&](const std::string& p) { throw StoreError(K::Invalid, what + ": " + p); };
    if (!j.is_object()) bad("camera intrinsics must be a JSON object");
    for (const char* k : {"width", "height"}) {
        if (!j.contains(k) || !j[k].is_number_integer() || j[k].get<std::int64_t>() < 1 || j[k].get<std::int64_t>() > 100000)
            bad(std::string("\"") + k + "\" must be an integer 1..100000 (pixels)");
    }
    for (const char* k : {"fx", "fy"})
        if (!j.contains(k) || !finite_number(j[k]) || j[k].get<double>() <= 0) bad(std::string("\"") + k + "\" must be a positive number (pixels)");
    for (const char* k : {"cx", "cy"})
        if (!j.contains(k) || !finite_number(j[k])) bad(std::string("\"") + k + "\" must be a number (pixels)");
    if (j.contains("distortion")) {
        const auto& d = j["distortion"];
        if (!d.is_array() || d.size() > 14) bad("\"distortion\" must be an array of at most 14 numbers");
        for (const auto& v : d)
            if (!finite_number(v)) bad("\"distortion\" must hold numbers only");
    }
}

void validate_roi(const json& j, const std::string& what) {
    auto bad = [&](const std::string& p) { throw StoreError(K::Invalid, what + ": " + p); };
    if (!j.is_object()) bad("ROI must be a JSON object");
    if (!j.contains("type") || j["type"] != "closed-cardinal-spline") bad("\"type\" must be \"closed-cardinal-spline\"");
    if (j.contains("tension") && !finite_number(j["tension"])) bad("\"tension\" must be a number");
    if (!j.contains("points") || !j["points"].is_array() || j["points"].size() < 3 || j["points"].size() > 10000)
        bad("\"points\" must be an array of 3..10000 [u, v] pairs");
    for (const auto& p : j["points"])
        if (!p.is_array() || p.size() != 2 || !finite_number(p[0]) || !finite_number(p[1]))
            bad("\"points\" must hold [u, v] pairs of numbers");
}

void validate_landmarks(const std::vector<LandmarkPoint>& pts, const std::string& what) {
    if (pts.size() > 1000) throw StoreError(K::Invalid, what + ": more than 1000 landmarks");
    std::set<std::string> names;
    for (std::size_t i = 0; i < pts.size(); ++i) {
        const auto& p = pts[i];
        const std::string w = what + ": landmark " + std::to_string(i);
        if (p.name.empty() || p.name.size() > 64) throw StoreError(K::Invalid, w + ": name must be 1..64 characters");
        if (!names.insert(p.name).second) throw StoreError(K::Invalid, w + ": name '" + p.name + "' used twice");
        for (double v : p.world_mm)
            if (!std::isfinite(v)) throw StoreError(K::Invalid, w + ": world_mm must be finite numbers");
        for (double v : p.pixel)
            if (!std::isfinite(v)) throw StoreError(K::Invalid, w + ": pixel must be finite numbers");
    }
}

void validate_file_name(const std::string& name, const std::string& what) {
    if (name.empty() || name.size() > 255 || name == "." || name == ".." ||
        name.find_first_of(std::string("/\\\0", 3)) != std::string::npos)
        throw StoreError(K::Invalid, what + ": file name '" + name.substr(0, 80) +
                                         "' must be 1..255 characters without '/', '\\' or NUL, not . or ..");
}

void validate_result_input(const ResultInput& r, const std::string& what) {
    if (r.kind.empty() || r.kind.size() > 64) throw StoreError(K::Invalid, what + ": kind must be 1..64 characters");
    validate_file_name(r.name, what);
    if (r.media_type.empty() || r.media_type.size() > 128)
        throw StoreError(K::Invalid, what + ": media_type must be 1..128 characters");
    if (!r.params.is_object()) throw StoreError(K::Invalid, what + ": params must be a JSON object");
}

void validate_registration_input(const RegistrationInput& r, const std::string& what) {
    if (!r.params.is_object()) throw StoreError(K::Invalid, what + ": params must be a JSON object (RegistrationParams)");
    if (!r.stages.is_array()) throw StoreError(K::Invalid, what + ": stages must be a JSON array");
    for (const auto* pose : {&r.initial_pose, &r.final_pose})
        if (*pose && !((*pose)->is_object() || (*pose)->is_array()))
            throw StoreError(K::Invalid, what + ": a pose must be a JSON object or a 4x4 array");
    for (const auto& v : {r.nmi, r.seconds})
        if (v && !std::isfinite(*v)) throw StoreError(K::Invalid, what + ": nmi and seconds must be finite");
    if (r.evaluations && *r.evaluations < 0) throw StoreError(K::Invalid, what + ": evaluations must be >= 0");
    if (r.status == RegistrationStatus::succeeded && !r.final_pose)
        throw StoreError(K::Invalid, what + ": a succeeded registration needs its final pose");
    for (std::size_t i = 0; i < r.results.size(); ++i)
        validate_result_input(r.results[i], what + ": result " + std::to_string(i));
}

}  // namespace cf::db
