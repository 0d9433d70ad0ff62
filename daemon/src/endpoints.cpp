#include "cortexfuse/daemon/endpoints.hpp"

#include <set>
#include <sodium.h>

namespace cf::daemon {

const char* access_name(Access a) {
    switch (a) {
        case Access::open: return "open";
        case Access::read: return "read";
        case Access::write: return "write";
        case Access::admin: return "admin";
    }
    return "?";
}

namespace {
std::vector<std::string> segments(const std::string& p) {
    std::vector<std::string> out;
    size_t i = 0;
    while (i < p.size()) {
        if (p[i] == '/') {
            ++i;
            continue;
        }
        const size_t j = p.find('/', i);
        out.push_back(p.substr(i, j == std::string::npos ? std::string::npos : j - i));
        if (j == std::string::npos) break;
        i = j;
    }
    return out;
}

bool role_allows(const std::string& role, Access a) {
    if (a == Access::open) return true;
    if (role == "kiosk" || role == "admin") return true;
    if (role == "surgeon" || role == "technician") return a == Access::read || a == Access::write;
    if (role == "reviewer") return a == Access::read;
    return false;
}
}  // namespace

bool match_path(const std::string& pattern, const std::string& path, std::map<std::string, std::string>& params) {
    const auto ps = segments(pattern), xs = segments(path);
    if (ps.size() != xs.size()) return false;
    std::map<std::string, std::string> got;
    for (size_t i = 0; i < ps.size(); ++i) {
        if (ps[i].size() > 2 && ps[i].front() == '{' && ps[i].back() == '}') {
            if (xs[i].empty()) return false;
            got[ps[i].substr(1, ps[i].size() - 2)] = xs[i];
        } else if (ps[i] != xs[i]) {
            return false;
        }
    }
    for (auto& [k, v] : got) params[k] = v;
    return true;
}

nlohmann::json error_json(int status, const std::string& code, const std::string& message) {
    return {{"error", {{"code", code}, {"status", status}, {"message", message}}}};
}

void EndpointRegistry::add(Endpoint e) {
    for (const auto& x : endpoints_) {
        if (x.rpc == e.rpc) throw std::logic_error("endpoint rpc name registered twice: " + e.rpc);
        if (x.method == e.method && x.path == e.path) throw std::logic_error("endpoint registered twice: " + e.method + " " + e.path);
    }
    endpoints_.push_back(std::move(e));
}

void EndpointRegistry::check_access(const Endpoint& e, const Client& c) const {
    if (role_allows(c.role, e.access)) return;
    if (c.role.empty() && !c.token.empty())
        throw ApiError(401, "unauthorized", e.method + " " + e.path + ": the session token is unknown or expired; log in again");
    if (c.role.empty())
        throw ApiError(401, "unauthorized",
                       e.method + " " + e.path + " needs a login from " + (c.address.empty() ? "a remote host" : c.address) +
                           " (access '" + access_name(e.access) + "')");
    throw ApiError(403, "forbidden", "role '" + c.role + "' may not " + e.method + " " + e.path);
}

Response EndpointRegistry::dispatch_http(Request req) const {
    std::set<std::string> allowed;
    for (const auto& e : endpoints_) {
        std::map<std::string, std::string> params;
        if (!match_path(e.path, req.path, params)) continue;
        if (e.method != req.method) {
            allowed.insert(e.method);
            continue;
        }
        check_access(e, req.client);
        for (auto& [k, v] : params) req.params[k] = v;  // path parameters win over the query
        return e.handler(req);
    }
    if (!allowed.empty()) {
        std::string allow;
        for (const auto& m : allowed) allow += (allow.empty() ? "" : ", ") + m;
        ApiError err(405, "method_not_allowed", req.method + " " + req.path + ": method not allowed (allowed: " + allow + ")");
        err.headers["Allow"] = allow;
        throw err;
    }
    throw ApiError(404, "not_found", req.path + ": no such endpoint (GET /api/endpoints lists them)");
}

const Endpoint* EndpointRegistry::find(const std::string& method, const std::string& path) const {
    for (const auto& e : endpoints_) {
        std::map<std::string, std::string> params;
        if (e.method == method && match_path(e.path, path, params)) return &e;
    }
    return nullptr;
}

Response EndpointRegistry::dispatch_rpc(const std::string& rpc, const nlohmann::json& params, const Client& client) const {
    for (const auto& e : endpoints_) {
        if (e.rpc != rpc) continue;
        check_access(e, client);
        Request req;
        req.method = e.method;
        req.path = e.path;
        req.client = client;
        if (!params.is_null() && !params.is_object()) throw ApiError(400, "bad_request", rpc + ": params must be an object");
        // Path parameters and simple query-like parameters come from params; the body is params.
        if (params.is_object())
            for (auto it = params.begin(); it != params.end(); ++it) {
                if (it.value().is_string()) req.params[it.key()] = it.value().get<std::string>();
                else if (it.value().is_number_integer()) req.params[it.key()] = std::to_string(it.value().get<long long>());
            }
        req.body = params;
        if (e.raw_body) {
            // The file comes base64-encoded (standard alphabet, padding optional).
            if (!params.is_object() || !params.contains("base64") || !params["base64"].is_string())
                throw ApiError(400, "bad_request", rpc + " base64: missing (the file's bytes, base64-encoded)");
            const std::string& b64 = params["base64"].get_ref<const std::string&>();
            std::string bin(b64.size() / 4 * 3 + 3, '\0');
            std::size_t n = 0;
            if (sodium_base642bin(reinterpret_cast<unsigned char*>(bin.data()), bin.size(), b64.data(), b64.size(), "\r\n ", &n, nullptr,
                                  sodium_base64_VARIANT_ORIGINAL) != 0 &&
                sodium_base642bin(reinterpret_cast<unsigned char*>(bin.data()), bin.size(), b64.data(), b64.size(), "\r\n ", &n, nullptr,
                                  sodium_base64_VARIANT_ORIGINAL_NO_PADDING) != 0)
                throw ApiError(400, "bad_request", rpc + " base64: not valid base64");
            bin.resize(n);
            const std::int64_t limit = e.max_body_bytes;
            if (limit > 0 && std::int64_t(n) > limit)
                throw ApiError(413, "payload_too_large", rpc + ": file of " + std::to_string(n) + " bytes is over the limit of " + std::to_string(limit));
            req.raw = std::move(bin);
            req.body = nlohmann::json::object();
            for (auto it = params.begin(); it != params.end(); ++it)
                if (it.key() != "base64") req.body[it.key()] = it.value();
        }
        return e.handler(req);
    }
    throw ApiError(404, "not_found", rpc + ": no such method (GET /api/endpoints lists them)");
}

nlohmann::json EndpointRegistry::list() const {
    nlohmann::json a = nlohmann::json::array();
    for (const auto& e : endpoints_)
    {
        nlohmann::json x{{"method", e.method}, {"path", e.path}, {"rpc", e.rpc}, {"access", access_name(e.access)}, {"summary", e.summary}};
        if (e.raw_body) x["body"] = "file";
        a.push_back(std::move(x));
    }
    return a;
}

}  // namespace cf::daemon
