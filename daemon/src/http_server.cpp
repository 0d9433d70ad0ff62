#include "http_server.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>

#include <civetweb.h>
#include <sodium.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/daemon/log.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"
#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using cf::tracker::steady_ns;

namespace {

int request_trampoline(mg_connection* c, void* self) { return static_cast<HttpServer*>(self)->handle_request(c); }
int ws_connect_trampoline(const mg_connection* c, void* self) { return static_cast<HttpServer*>(self)->ws_connect(c); }
void ws_ready_trampoline(mg_connection* c, void* self) { static_cast<HttpServer*>(self)->ws_ready(c); }
int ws_data_trampoline(mg_connection* c, int flags, char* data, size_t len, void* self) {
    return static_cast<HttpServer*>(self)->ws_data(c, flags, data, len);
}
void ws_close_trampoline(const mg_connection* c, void* self) { static_cast<HttpServer*>(self)->ws_close(c); }
int log_message_cb(const mg_connection*, const char* message) {
    log(LogLevel::warning, "http", message ? message : "(civetweb)");
    return 1;
}

const char* reason(int status) {
    switch (status) {
        case 200: return "OK";
        case 201: return "Created";
        case 202: return "Accepted";
        case 204: return "No Content";
        case 400: return "Bad Request";
        case 401: return "Unauthorized";
        case 403: return "Forbidden";
        case 404: return "Not Found";
        case 405: return "Method Not Allowed";
        case 409: return "Conflict";
        case 413: return "Payload Too Large";
        case 415: return "Unsupported Media Type";
        case 500: return "Internal Server Error";
        case 503: return "Service Unavailable";
    }
    return "Status";
}

void send(mg_connection* conn, int status, const std::string& mime, const std::string& body,
          const std::map<std::string, std::string>& headers = {}, bool head_only = false) {
    std::ostringstream h;
    h << "HTTP/1.1 " << status << " " << reason(status) << "\r\n"
      << "Content-Type: " << mime << "\r\n"
      << "Content-Length: " << body.size() << "\r\n"
      << "Cache-Control: no-store\r\n"
      << "X-Content-Type-Options: nosniff\r\n"
      << "Connection: close\r\n";
    for (const auto& [k, v] : headers) h << k << ": " << v << "\r\n";
    h << "\r\n";
    const std::string head = h.str();
    mg_write(conn, head.data(), head.size());
    if (!head_only && !body.empty()) mg_write(conn, body.data(), body.size());
}

void send_json(mg_connection* conn, int status, const nlohmann::json& j, const std::map<std::string, std::string>& headers = {}) {
    send(conn, status, "application/json", j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace), headers);
}

std::map<std::string, std::string> parse_query(const char* q) {
    std::map<std::string, std::string> out;
    if (!q) return out;
    std::string s(q);
    std::size_t i = 0;
    while (i <= s.size()) {
        std::size_t amp = s.find('&', i);
        if (amp == std::string::npos) amp = s.size();
        const std::string kv = s.substr(i, amp - i);
        if (!kv.empty()) {
            const std::size_t eq = kv.find('=');
            const std::string k = kv.substr(0, eq), v = eq == std::string::npos ? "" : kv.substr(eq + 1);
            std::vector<char> kb(k.size() + 1), vb(v.size() + 1);
            mg_url_decode(k.c_str(), int(k.size()), kb.data(), int(kb.size()), 1);
            mg_url_decode(v.c_str(), int(v.size()), vb.data(), int(vb.size()), 1);
            out[kb.data()] = vb.data();
        }
        i = amp + 1;
    }
    return out;
}

bool has_dotdot_segment(const std::string& p) {
    std::size_t i = 0;
    while (i <= p.size()) {
        std::size_t j = p.find_first_of("/\\", i);
        if (j == std::string::npos) j = p.size();
        if (p.compare(i, j - i, "..") == 0 && j - i == 2) return true;
        i = j + 1;
    }
    return false;
}

const char* kNoUiPage =
    "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>CortexFuse</title>"
    "<style>body{background:#111;color:#ddd;font:20px sans-serif;margin:3em}a{color:#8cf}</style></head><body>"
    "<h1>CortexFuse</h1><p>cortexfused is running, but the web UI is not built (no index.html in the configured "
    "<code>http.ui_dir</code>).</p><p>The API answers: <a href=\"/api/status\">/api/status</a>, "
    "<a href=\"/api/endpoints\">/api/endpoints</a>.</p></body></html>";

}  // namespace

HttpServer::HttpServer(const DaemonConfig& c, const EndpointRegistry& registry) : cfg_(c), registry_(registry) {}

HttpServer::~HttpServer() { stop(); }

namespace {
/// civetweb calls this on each of its new threads. Connection workers (type 1) get nice
/// `http.nice`, so under a saturated CPU the tracker's driver and the push thread (nice 0) are
/// scheduled before request handling (WebSocket writer threads, started from a worker, inherit it).
void* init_thread_cb(const mg_context* ctx, int thread_type) {
    const auto* server = static_cast<const HttpServer*>(mg_get_user_data(ctx));
    if (thread_type == 1 && server && server->worker_nice() > 0) {
        const id_t tid = id_t(::syscall(SYS_gettid));
        errno = 0;
        const int current = ::getpriority(PRIO_PROCESS, tid);
        if (errno == 0 && current < server->worker_nice()) ::setpriority(PRIO_PROCESS, tid, server->worker_nice());
    }
    return nullptr;
}
}  // namespace

void HttpServer::start() {
    static const unsigned features = mg_init_library(MG_FEATURES_WEBSOCKET);
    (void)features;
    if (!mg_check_feature(MG_FEATURES_WEBSOCKET)) throw std::runtime_error("http: this civetweb has no WebSocket support");
    const std::string threads = std::to_string(cfg_.http_threads), timeout = std::to_string(cfg_.request_timeout_ms);
    const char* options[] = {"listening_ports", cfg_.listen.c_str(),
                             "num_threads", threads.c_str(),
                             "request_timeout_ms", timeout.c_str(),
                             "websocket_timeout_ms", "3600000",
                             "enable_keep_alive", "no",
                             "enable_directory_listing", "no",
                             nullptr};
    mg_callbacks cb;
    std::memset(&cb, 0, sizeof cb);
    cb.log_message = log_message_cb;
    cb.init_thread = init_thread_cb;
    mg_init_data init{&cb, this, options};
    char err_text[256] = {0};
    unsigned err_code = 0;
    mg_error_data err{&err_code, err_text, sizeof err_text};
    ctx_ = mg_start2(&init, &err);
    if (!ctx_) throw std::runtime_error("http.listen " + cfg_.listen + ": cannot start the server: " + (err_text[0] ? err_text : "unknown error"));
    mg_server_port ports[4];
    const int n = mg_get_server_ports(ctx_, 4, ports);
    port_ = n > 0 ? ports[0].port : 0;
    mg_set_request_handler(ctx_, "/", request_trampoline, this);
    mg_set_websocket_handler(ctx_, "/api/ws", ws_connect_trampoline, ws_ready_trampoline, ws_data_trampoline, ws_close_trampoline, this);
    {
        std::lock_guard lk(q_mu_);
        q_stop_ = false;
    }
    push_alive_ = true;
    push_thread_ = std::thread([this] { push_loop(); });
}

void HttpServer::stop() {
    if (ctx_) {
        mg_stop(ctx_);  // closes connections (the close handlers run) and joins civetweb's threads
        ctx_ = nullptr;
    }
    {
        std::lock_guard lk(q_mu_);
        q_stop_ = true;
    }
    q_cv_.notify_all();
    if (push_thread_.joinable()) push_thread_.join();
    // Clients whose close handler civetweb did not run: end their writers (no writes follow).
    std::map<const mg_connection*, std::shared_ptr<WsClient>> left;
    {
        std::lock_guard lk(clients_mu_);
        left.swap(clients_);
    }
    for (auto& [c, w] : left) {
        {
            std::lock_guard lk(w->mu);
            w->closing = true;
        }
        w->cv.notify_all();
        if (w->writer.joinable()) w->writer.join();
    }
}

Client HttpServer::client_of(const mg_connection* conn) const {
    const mg_request_info* ri = mg_get_request_info(conn);
    Client c;
    c.address = ri ? ri->remote_addr : "";
    c.loopback = c.address.rfind("127.", 0) == 0 || c.address == "::1" || c.address.rfind("::ffff:127.", 0) == 0;
    // A bearer token (header, or ?token= for the WebSocket, which browsers open without
    // headers) names a session; without one, loopback is the kiosk on the cart.
    std::string token;
    if (const char* h = mg_get_header(conn, "Authorization"); h && std::strncmp(h, "Bearer ", 7) == 0) token = h + 7;
    else if (ri && ri->query_string) {
        const auto q = parse_query(ri->query_string);
        if (auto it = q.find("token"); it != q.end()) token = it->second;
    }
    if (!token.empty()) {
        c.token = token;
        if (!auth_ || !auth_(token, c)) {
            c.role.clear();  // an unknown or expired session is refused, also from loopback
            c.user.clear();
        }
        return c;
    }
    if (c.loopback || !cfg_.remote_requires_login) {
        c.role = "kiosk";
        c.user = "kiosk";
    }
    return c;
}

int HttpServer::handle_request(mg_connection* conn) {
    ++requests_;
    const mg_request_info* ri = mg_get_request_info(conn);
    const std::string method = ri->request_method ? ri->request_method : "";
    const std::string uri = ri->local_uri ? ri->local_uri : "/";
    const std::string raw_uri = ri->local_uri_raw ? ri->local_uri_raw : uri;
    const bool api = uri == "/api" || uri.rfind("/api/", 0) == 0;
    if (!api) {
        serve_static(conn, method, uri, raw_uri);
        return 1;
    }
    int status = 200;
    try {
        if (uri == "/api/ws") throw ApiError(400, "bad_request", "/api/ws: a WebSocket endpoint (send an Upgrade: websocket request)");
        Request req;
        req.method = method;
        req.path = uri;
        req.client = client_of(conn);
        req.params = parse_query(ri->query_string);
        // The body: refused above the limit without reading it; read to the limit otherwise.
        // Upload endpoints (raw_body) have their own limit (store.max_upload_bytes).
        const Endpoint* ep = registry_.find(method, uri);
        const bool raw = ep && ep->raw_body;
        const std::int64_t limit = ep && ep->max_body_bytes > 0 ? ep->max_body_bytes : cfg_.max_body_bytes;
        const std::string limit_key = ep && ep->max_body_bytes > 0 ? "store.max_upload_bytes" : "http.max_body_bytes";
        const long long declared = ri->content_length;
        if (declared > limit)
            throw ApiError(413, "payload_too_large",
                           "request body of " + std::to_string(declared) + " bytes is over the limit of " + std::to_string(limit) + " (" + limit_key + ")");
        std::string body;
        if (declared > 0) body.reserve(std::size_t(declared));
        if (declared != 0 && method != "GET" && method != "HEAD") {
            char buf[16384];
            for (;;) {
                const int n = mg_read(conn, buf, sizeof buf);
                if (n <= 0) break;
                body.append(buf, std::size_t(n));
                if (std::int64_t(body.size()) > limit)
                    throw ApiError(413, "payload_too_large", "request body is over the limit of " + std::to_string(limit) + " bytes (" + limit_key + ")");
            }
        }
        if (raw) {
            req.raw = std::move(body);
        } else if (!body.empty()) {
            try {
                req.body = nlohmann::json::parse(body);
            } catch (const nlohmann::json::parse_error& e) {
                throw ApiError(400, "bad_request", "request body is not valid JSON: " + std::string(e.what()));
            }
        }
        Response r = registry_.dispatch_http(std::move(req));
        status = r.status;
        if (!r.bytes.empty() || !r.mime.empty()) send(conn, r.status, r.mime, r.bytes, r.headers);
        else send_json(conn, r.status, r.json, r.headers);
    } catch (const ApiError& e) {
        status = e.status;
        send_json(conn, e.status, error_json(e.status, e.code, e.what()), e.headers);
    } catch (const cf::InputError& e) {
        status = 400;
        send_json(conn, 400, error_json(400, "bad_request", e.what()));
    } catch (const std::exception& e) {
        status = 500;
        log(LogLevel::error, "http", method + " " + uri + ": " + e.what());
        send_json(conn, 500, error_json(500, "internal", e.what()));
    }
    if (status >= 500) ++errors_5xx_;
    else if (status >= 400) ++errors_4xx_;
    return status;  // civetweb: a non-zero return means handled (its value is logged as the status)
}

void HttpServer::serve_static(mg_connection* conn, const std::string& method, const std::string& uri, const std::string& raw_uri) {
    if (method != "GET" && method != "HEAD") {
        ++errors_4xx_;
        send_json(conn, 405, error_json(405, "method_not_allowed", method + " " + uri + ": static files are GET or HEAD only"), {{"Allow", "GET, HEAD"}});
        return;
    }
    if (has_dotdot_segment(raw_uri) || has_dotdot_segment(uri) || uri.find('\0') != std::string::npos || uri.find('\\') != std::string::npos) {
        ++errors_4xx_;
        send_json(conn, 400, error_json(400, "bad_request", "path '" + raw_uri + "' leaves the UI folder"));
        return;
    }
    std::error_code ec;
    const fs::path root = cfg_.ui_dir.empty() ? fs::path() : fs::weakly_canonical(cfg_.ui_dir, ec);
    const bool ui_built = !root.empty() && fs::is_regular_file(root / "index.html", ec);
    const std::string rel = (uri == "/" || uri.empty()) ? "index.html" : uri.substr(1);
    if (!ui_built) {
        if (rel == "index.html") {
            send(conn, 200, "text/html; charset=utf-8", kNoUiPage, {}, method == "HEAD");
            return;
        }
        ++errors_4xx_;
        send_json(conn, 404, error_json(404, "not_found", uri + ": no such file (the UI is not built)"));
        return;
    }
    fs::path p = fs::weakly_canonical(root / rel, ec);
    const std::string ps = p.string(), rs = root.string();
    if (ec || ps.compare(0, rs.size(), rs) != 0 || (ps.size() > rs.size() && ps[rs.size()] != '/')) {
        ++errors_4xx_;
        send_json(conn, 400, error_json(400, "bad_request", "path '" + uri + "' leaves the UI folder"));
        return;
    }
    if (fs::is_directory(p, ec)) p /= "index.html";
    if (!fs::is_regular_file(p, ec)) {
        ++errors_4xx_;
        send_json(conn, 404, error_json(404, "not_found", uri + ": no such file"));
        return;
    }
    mg_send_mime_file(conn, p.c_str(), nullptr);
}

int HttpServer::ws_connect(const mg_connection* conn) {
    const Client c = client_of(conn);
    if (c.role.empty()) {
        log(LogLevel::notice, "http", "WebSocket from " + c.address + " refused: login needed");
        return 1;  // non-zero: civetweb refuses the upgrade
    }
    return 0;
}

void HttpServer::ws_ready(mg_connection* conn) {
    auto w = std::make_shared<WsClient>();
    w->conn = conn;
    w->client = client_of(conn);
    w->tracker_hz = cfg_.push_default_tracker_hz;
    WsClient* wp = w.get();
    w->writer = std::thread([this, wp] { writer_loop(*wp); });
    std::lock_guard lk(clients_mu_);
    clients_[conn] = std::move(w);
}

void HttpServer::ws_close(const mg_connection* conn) {
    std::shared_ptr<WsClient> w;
    {
        std::lock_guard lk(clients_mu_);
        auto it = clients_.find(conn);
        if (it == clients_.end()) return;
        w = it->second;
        clients_.erase(it);
    }
    {
        std::lock_guard lk(w->mu);
        w->closing = true;
    }
    w->cv.notify_all();
    // The connection stays valid until this handler returns, so the writer must be done first.
    if (w->writer.joinable()) w->writer.join();
}

void HttpServer::writer_loop(WsClient& w) {
    for (;;) {
        std::shared_ptr<const std::string> m;
        {
            std::unique_lock lk(w.mu);
            w.cv.wait(lk, [&] { return w.closing || !w.out.empty(); });
            if (w.closing) return;
            m = std::move(w.out.front());
            w.out.pop_front();
        }
        const int n = mg_websocket_write(w.conn, MG_WEBSOCKET_OPCODE_TEXT, m->data(), m->size());
        std::unique_lock lk(w.mu);
        if (n > 0) {
            ++w.sent;
            continue;
        }
        // The connection is going away: drop what is queued and wait for the close handler.
        w.broken = true;
        w.out.clear();
        w.cv.wait(lk, [&] { return w.closing; });
        return;
    }
}

int HttpServer::ws_data(mg_connection* conn, int flags, char* data, std::size_t len) {
    const int opcode = flags & 0x0f;
    if (opcode == MG_WEBSOCKET_OPCODE_CONNECTION_CLOSE) return 0;
    if (opcode != MG_WEBSOCKET_OPCODE_TEXT) return 1;  // pings are answered by civetweb; binary ignored
    ++ws_messages_;
    const std::string reply = handle_rpc_text(conn, data, len);
    if (!reply.empty()) mg_websocket_write(conn, MG_WEBSOCKET_OPCODE_TEXT, reply.data(), reply.size());
    return 1;
}

std::string HttpServer::handle_rpc_text(mg_connection* conn, const char* data, std::size_t len) {
    auto rpc_error = [](const nlohmann::json& id, int code, const std::string& reason_code, const std::string& message) {
        return nlohmann::json{{"jsonrpc", "2.0"}, {"id", id}, {"error", {{"code", code}, {"message", message}, {"data", {{"code", reason_code}}}}}}.dump();
    };
    if (std::int64_t(len) > cfg_.max_body_bytes)
        return rpc_error(nullptr, 413, "payload_too_large", "message of " + std::to_string(len) + " bytes is over http.max_body_bytes");
    nlohmann::json msg;
    try {
        msg = nlohmann::json::parse(data, data + len);
    } catch (const nlohmann::json::parse_error& e) {
        return rpc_error(nullptr, -32700, "parse_error", std::string("message is not valid JSON: ") + e.what());
    }
    if (!msg.is_object() || !msg.contains("method") || !msg["method"].is_string())
        return rpc_error(msg.is_object() && msg.contains("id") ? msg["id"] : nlohmann::json(nullptr), -32600, "invalid_request",
                         "a JSON-RPC 2.0 request object with a string 'method' is expected");
    const nlohmann::json id = msg.contains("id") ? msg["id"] : nlohmann::json(nullptr);
    const bool notification = !msg.contains("id");
    const std::string method = msg["method"].get<std::string>();
    const nlohmann::json params = msg.contains("params") ? msg["params"] : nlohmann::json(nullptr);
    nlohmann::json result;
    try {
        if (method == "push.subscribe") {
            if (!params.is_null() && !params.is_object()) throw ApiError(400, "bad_request", "push.subscribe: params must be an object");
            std::lock_guard lk(clients_mu_);
            auto it = clients_.find(conn);
            if (it == clients_.end()) throw ApiError(409, "conflict", "push.subscribe: connection not ready");
            WsClient& w = *it->second;
            if (params.is_object() && params.contains("tracker_hz")) {
                const auto& h = params["tracker_hz"];
                if (!h.is_number() || h.get<double>() < 0 || h.get<double>() > 1000)
                    throw ApiError(400, "bad_request", "push.subscribe tracker_hz: must be a number 0..1000 (0: every frame)");
                w.tracker_hz = h.get<double>();
            }
            if (params.is_object() && params.contains("topics")) {
                const auto& t = params["topics"];
                if (!t.is_array()) throw ApiError(400, "bad_request", "push.subscribe topics: must be a list of tracker, jobs, status");
                w.tracker = w.jobs = w.status = false;
                for (const auto& x : t) {
                    const std::string s = x.is_string() ? x.get<std::string>() : "";
                    if (s == "tracker") w.tracker = true;
                    else if (s == "jobs") w.jobs = true;
                    else if (s == "status") w.status = true;
                    else throw ApiError(400, "bad_request", "push.subscribe topics: '" + x.dump() + "' is not tracker, jobs or status");
                }
            }
            nlohmann::json topics = nlohmann::json::array();
            if (w.tracker) topics.push_back("tracker");
            if (w.jobs) topics.push_back("jobs");
            if (w.status) topics.push_back("status");
            result = {{"tracker_hz", w.tracker_hz}, {"topics", topics}};
        } else {
            Response r = registry_.dispatch_rpc(method, params, client_of(conn));
            if (!r.bytes.empty() || !r.mime.empty()) {
                // Binary results (rendered views) travel as base64 inside the JSON reply.
                const std::size_t n = r.bytes.size();
                std::string b64(sodium_base64_ENCODED_LEN(n, sodium_base64_VARIANT_ORIGINAL), '\0');
                sodium_bin2base64(b64.data(), b64.size(), reinterpret_cast<const unsigned char*>(r.bytes.data()), n,
                                  sodium_base64_VARIANT_ORIGINAL);
                b64.resize(std::strlen(b64.c_str()));
                result = {{"mime", r.mime}, {"base64", b64}};
                for (const auto& [k, v] : r.headers) result["headers"][k] = v;
            } else {
                result = r.json;
            }
        }
    } catch (const ApiError& e) {
        return notification ? std::string() : rpc_error(id, e.status, e.code, e.what());
    } catch (const cf::InputError& e) {
        return notification ? std::string() : rpc_error(id, 400, "bad_request", e.what());
    } catch (const std::exception& e) {
        log(LogLevel::error, "http", "rpc " + method + ": " + e.what());
        return notification ? std::string() : rpc_error(id, 500, "internal", e.what());
    }
    if (notification) return {};
    return nlohmann::json{{"jsonrpc", "2.0"}, {"id", id}, {"result", result}}.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

void HttpServer::publish(const std::string& topic, const std::string& method, const nlohmann::json& params, std::int64_t t_ns) {
    Message m{topic,
              std::make_shared<const std::string>(
                  nlohmann::json{{"jsonrpc", "2.0"}, {"method", method}, {"params", params}}.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace)),
              t_ns};
    {
        std::lock_guard lk(q_mu_);
        if (q_stop_) return;
        queue_.push_back(std::move(m));
        while (queue_.size() > std::size_t(cfg_.push_queue_frames)) {
            queue_.pop_front();
            ++dropped_;
        }
    }
    q_cv_.notify_one();
}

void HttpServer::push_loop() {
    for (;;) {
        Message m;
        {
            std::unique_lock lk(q_mu_);
            q_cv_.wait(lk, [&] { return q_stop_ || !queue_.empty(); });
            if (q_stop_) break;
            m = std::move(queue_.front());
            queue_.pop_front();
        }
        std::lock_guard lk(clients_mu_);
        for (auto& [c, wp] : clients_) {
            WsClient& w = *wp;
            if (m.topic == "tracker") {
                if (!w.tracker) continue;
                if (w.tracker_hz > 0 && w.last_tracker_ns != 0 && double(m.t_ns - w.last_tracker_ns) < 0.8e9 / w.tracker_hz) {
                    std::lock_guard l2(w.mu);
                    ++w.skipped;
                    continue;
                }
                w.last_tracker_ns = m.t_ns;
            } else if ((m.topic == "jobs" && !w.jobs) || (m.topic == "status" && !w.status)) {
                continue;
            }
            {
                std::lock_guard l2(w.mu);
                if (w.broken || w.closing) continue;
                w.out.push_back(m.text);  // shared: serialised once for all clients
                while (w.out.size() > std::size_t(cfg_.push_queue_frames)) {
                    w.out.pop_front();
                    ++w.dropped;
                }
            }
            w.cv.notify_one();
        }
    }
    push_alive_ = false;
}

nlohmann::json HttpServer::status_json() const {
    nlohmann::json clients = nlohmann::json::array();
    {
        std::lock_guard lk(clients_mu_);
        for (const auto& [c, wp] : clients_) {
            std::lock_guard l2(wp->mu);
            clients.push_back({{"address", wp->client.address}, {"tracker_hz", wp->tracker_hz}, {"sent", wp->sent}, {"skipped", wp->skipped},
                               {"queued", wp->out.size()}, {"dropped", wp->dropped}});
        }
    }
    std::uint64_t dropped;
    std::size_t queued;
    {
        std::lock_guard lk(q_mu_);
        dropped = dropped_;
        queued = queue_.size();
    }
    return {{"listen", cfg_.listen},
            {"port", port_},
            {"requests", requests_.load()},
            {"errors_4xx", errors_4xx_.load()},
            {"errors_5xx", errors_5xx_.load()},
            {"ws_messages", ws_messages_.load()},
            {"websocket_clients", clients},
            {"push_queued", queued},
            {"push_dropped", dropped}};
}

bool HttpServer::healthy() const { return ctx_ != nullptr && push_alive_.load(); }

}  // namespace cf::daemon
