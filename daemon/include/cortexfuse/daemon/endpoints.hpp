#pragma once
// One registry of API endpoints (Moonraker style): each endpoint is a method, a path pattern
// ("/api/jobs/{id}"), a JSON-RPC method name ("jobs.get"), the access it needs and a handler
// taking a JSON request and returning JSON or bytes. The HTTP server and the JSON-RPC 2.0
// calls over the WebSocket (/api/ws) both dispatch through it, so every endpoint exists in
// both with the same checks and the same errors.
//
// Errors: a handler throws ApiError(status, code, message); the HTTP side answers that status
// with {"error":{"code","status","message"}}, the RPC side a JSON-RPC error whose code is the
// HTTP status (as Moonraker does) with the same code string in data.
//
// Thread contract: endpoints are added before the server starts; dispatch() is then called
// from any number of connection threads at once (the registry is read-only by then; handlers
// must be thread-safe).
#include <functional>
#include <cstdint>
#include <map>
#include <optional>
#include <nlohmann/json.hpp>
#include <stdexcept>
#include <string>
#include <vector>

namespace cf::daemon {

class ApiError : public std::runtime_error {
public:
    ApiError(int http_status, std::string code, const std::string& message)
        : std::runtime_error(message), status(http_status), code(std::move(code)) {}
    int status;
    std::string code;  ///< "bad_request", "not_found", "method_not_allowed", "payload_too_large", ...
    std::map<std::string, std::string> headers;  ///< e.g. Allow with a 405
};

/// Who may call an endpoint. Loopback clients (the kiosk on the cart) have every access; other
/// hosts need a session with a role (reviewer: read; surgeon, technician: write; admin).
enum class Access { open, read, write, admin };
const char* access_name(Access a);

struct Client {
    bool loopback = false;
    std::string address;  ///< remote IP as text
    std::string role;     ///< "" without a session; "kiosk" for loopback without a token; else the session user's role
    std::string user;     ///< the session's user name ("kiosk" for loopback without a token)
    std::optional<std::int64_t> user_id;
    std::string token;    ///< the bearer token presented, if any
};

struct Request {
    std::string method;                          ///< GET, POST, DELETE (RPC: the endpoint's)
    std::string path;                            ///< as requested
    std::map<std::string, std::string> params;   ///< from the path pattern, then the query string
    nlohmann::json body;                         ///< parsed JSON body or RPC params (null when none)
    std::string raw;                             ///< raw_body endpoints: the body's bytes (RPC: params.base64 decoded)
    Client client;
};

struct Response {
    int status = 200;
    nlohmann::json json;            ///< used when bytes is empty
    std::string bytes;              ///< binary body (images)
    std::string mime;               ///< for bytes
    std::map<std::string, std::string> headers;
    static Response binary(std::string b, std::string mime_type) {
        Response r;
        r.bytes = std::move(b);
        r.mime = std::move(mime_type);
        return r;
    }
};

using Handler = std::function<Response(const Request&)>;

struct Endpoint {
    std::string method;   ///< "GET", "POST", "DELETE"
    std::string path;     ///< "/api/jobs/{id}": {name} matches one non-empty segment
    std::string rpc;      ///< "jobs.get"
    Access access = Access::read;
    std::string summary;  ///< one line, listed by GET /api/endpoints
    Handler handler;
    /// The body is a file (an upload), not JSON: it arrives in Request::raw, unparsed. Over
    /// JSON-RPC the bytes come base64-encoded in params.base64.
    bool raw_body = false;
    /// Largest body this endpoint takes (413 above it); 0: http.max_body_bytes.
    std::int64_t max_body_bytes = 0;
};

class EndpointRegistry {
public:
    void add(Endpoint e);
    /// HTTP: finds the endpoint for (method, path); 404 unknown path, 405 known path with
    /// another method (the Allow header names the methods), 401/403 on access. Runs it.
    Response dispatch_http(Request req) const;
    /// JSON-RPC: by method name; params must be an object (or absent). Path parameters are
    /// taken from params ({"id": ...}).
    Response dispatch_rpc(const std::string& rpc, const nlohmann::json& params, const Client& client) const;
    nlohmann::json list() const;
    /// The endpoint (method, path) would dispatch to, or nullptr; no access check. The HTTP
    /// server asks before reading a body (its limit, raw or JSON).
    const Endpoint* find(const std::string& method, const std::string& path) const;
    const std::vector<Endpoint>& endpoints() const { return endpoints_; }

private:
    void check_access(const Endpoint& e, const Client& c) const;
    std::vector<Endpoint> endpoints_;
};

/// Splits "/a/b" into segments and matches a pattern; false when it does not match.
bool match_path(const std::string& pattern, const std::string& path, std::map<std::string, std::string>& params);

/// {"error":{"code":..,"status":..,"message":..}}
nlohmann::json error_json(int status, const std::string& code, const std::string& message);

}  // namespace cf::daemon
