#pragma once
// The HTTP server and the push channel, on civetweb (Debian's libcivetweb, C API).
//  - /api/...: the EndpointRegistry (JSON in, JSON or bytes out; errors as JSON with a 4xx).
//  - /api/ws : WebSocket. Client -> server: JSON-RPC 2.0 requests for any registry method
//              plus "push.subscribe"; server -> client: the replies and notifications
//              ("notify_tracker_frame", "notify_job", "notify_status").
//  - /...    : the UI's static files from http.ui_dir (GET/HEAD only; no path outside it).
//
// Thread contract: civetweb's connection threads (http.threads of them) call the registry
// concurrently. One push thread owns the outgoing notification queue and writes to every
// WebSocket client (mg_websocket_write locks each connection, so replies written by a
// connection thread and notifications never interleave within a frame). Each WebSocket client
// has a writer thread: the push thread only filters and queues per client, so a slow client
// never holds up the others. publish() may be called from any thread and only enqueues (the
// tracker's driver thread calls it per frame).
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <condition_variable>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/daemon/endpoints.hpp"

struct mg_context;
struct mg_connection;

namespace cf::daemon {

class HttpServer {
public:
    HttpServer(const DaemonConfig& c, const EndpointRegistry& registry);
    ~HttpServer();
    /// Binds and starts; throws std::runtime_error naming http.listen when it cannot.
    void start();
    /// Stops accepting, closes the WebSockets, joins all threads.
    void stop();
    int port() const { return port_; }
    /// Nice value of civetweb's connection threads (http.nice).
    int worker_nice() const { return cfg_.http_nice; }
    /// Resolves a bearer token (Authorization: Bearer T, or ?token=T on /api/ws) into the
    /// client's role and user; returns false for an unknown or expired token. Set before start().
    using Authenticator = std::function<bool(const std::string& token, Client& client)>;
    void set_authenticator(Authenticator a) { auth_ = std::move(a); }

    /// Enqueue a notification for the WebSocket clients. `topic`: "tracker", "jobs", "status".
    /// `t_ns`: the event's steady time (tracker frames are throttled per client on it).
    void publish(const std::string& topic, const std::string& method, const nlohmann::json& params, std::int64_t t_ns);
    nlohmann::json status_json() const;
    bool healthy() const;

    // civetweb callbacks (static trampolines call these).
    int handle_request(mg_connection* conn);
    int ws_connect(const mg_connection* conn);
    void ws_ready(mg_connection* conn);
    int ws_data(mg_connection* conn, int flags, char* data, std::size_t len);
    void ws_close(const mg_connection* conn);

private:
    /// One WebSocket client. Its own writer thread sends its notifications, so a client that
    /// reads slowly (a review workstation on a slow link) delays only itself; its queue keeps
    /// the newest `push.queue_frames` messages and counts what it drops.
    struct WsClient {
        mg_connection* conn = nullptr;
        Client client;
        double tracker_hz = 30;                // guarded by clients_mu_
        std::int64_t last_tracker_ns = 0;      // push thread only
        bool tracker = true, jobs = true, status = true;  // guarded by clients_mu_
        std::mutex mu;                         // guards the fields below
        std::condition_variable cv;
        std::deque<std::shared_ptr<const std::string>> out;
        bool closing = false, broken = false;
        std::uint64_t sent = 0, skipped = 0, dropped = 0;
        std::thread writer;
    };
    void writer_loop(WsClient& w);
    struct Message {
        std::string topic;
        std::shared_ptr<const std::string> text;
        std::int64_t t_ns = 0;
    };
    Client client_of(const mg_connection* conn) const;
    void serve_static(mg_connection* conn, const std::string& method, const std::string& uri, const std::string& raw_uri);
    void push_loop();
    std::string handle_rpc_text(mg_connection* conn, const char* data, std::size_t len);

    DaemonConfig cfg_;
    const EndpointRegistry& registry_;
    mg_context* ctx_ = nullptr;
    Authenticator auth_;
    int port_ = 0;

    mutable std::mutex clients_mu_;
    std::map<const mg_connection*, std::shared_ptr<WsClient>> clients_;

    mutable std::mutex q_mu_;
    std::condition_variable q_cv_;
    std::deque<Message> queue_;
    bool q_stop_ = false;
    std::uint64_t dropped_ = 0;
    std::thread push_thread_;
    std::atomic<bool> push_alive_{false};

    std::atomic<std::uint64_t> requests_{0}, errors_4xx_{0}, errors_5xx_{0}, ws_messages_{0};
};

}  // namespace cf::daemon
