// holocap view: a site served on loopback (cpp-httplib), static files only.
#include <pthread.h>
#include <signal.h>

#include <atomic>
#include <chrono>
#include <thread>

#include "core/check_option.h"
#include "core/error.h"
#include "playback/playback.h"

// Last: <resolv.h>, which httplib.h includes, defines a macro `_res` that Eigen's headers use
// as a parameter name.
#include <httplib.h>

namespace holocap {
namespace {

// While alive, SIGINT and SIGTERM stop `server` instead of ending the process: they are blocked
// in every thread (httplib's workers inherit the mask) and a watcher thread waits for them.
class StopOnSignals {
 public:
  explicit StopOnSignals(httplib::Server* server) {
    sigemptyset(&signals_);
    sigaddset(&signals_, SIGINT);
    sigaddset(&signals_, SIGTERM);
    pthread_sigmask(SIG_BLOCK, &signals_, &previous_);
    watcher_ = std::thread([this, server] {
      const timespec poll{0, 100'000'000};
      constexpr std::chrono::milliseconds kPoll{10};
      while (!done_) {
        if (sigtimedwait(&signals_, nullptr, &poll) > 0) {
          stopped_ = true;
          // A signal may come before listen_after_bind() starts, and httplib's stop() stops a
          // running server only: wait until it runs (or the serving is over), then stop it.
          while (!done_ && !server->is_running()) std::this_thread::sleep_for(kPoll);
          server->stop();
          return;
        }
      }
    });
  }
  ~StopOnSignals() {
    done_ = true;
    watcher_.join();
    pthread_sigmask(SIG_SETMASK, &previous_, nullptr);
  }
  bool stopped() const { return stopped_; }

 private:
  sigset_t signals_, previous_;
  std::atomic<bool> done_{false}, stopped_{false};
  std::thread watcher_;
};

}  // namespace

void ViewServerOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(port, 0, 65535);
  HOLOCAP_CHECK_OPTION(IsOneOf(host, {"127.0.0.1", "localhost", "::1"}), host,
                       "holocap view serves on loopback only");
}

void ServeSite(const std::filesystem::path& site, const ViewServerOptions& options,
               const std::function<void(const std::string& url)>& listening) {
  options.Check();
  std::string why;
  if (!IsWebSite(site, &why)) Fail(why);
  httplib::Server server;
  const std::pair<const char*, const char*> types[] = {
      {"js", "text/javascript"},    {"mjs", "text/javascript"},
      {"json", "application/json"}, {"html", "text/html; charset=utf-8"},
      {"css", "text/css"},          {"hcc", "application/octet-stream"},
      {"png", "image/png"},
  };
  for (const auto& [extension, type] : types)
    server.set_file_extension_and_mimetype_mapping(extension, type);
  if (!server.set_mount_point("/", std::filesystem::absolute(site).string()))
    Fail("cannot serve '", site.string(), "'");
  // Chunks change when a site is exported again: the browser asks each time.
  server.set_post_routing_handler([](const httplib::Request&, httplib::Response& response) {
    response.set_header("Cache-Control", "no-cache");
  });
  // httplib's default also sets SO_REUSEPORT, which lets a second server bind a port in use.
  server.set_socket_options([](socket_t socket) {
    int yes = 1;
    setsockopt(socket, SOL_SOCKET, SO_REUSEADDR, reinterpret_cast<const void*>(&yes), sizeof(yes));
  });
  int port = options.port;
  if (port == 0) {
    port = server.bind_to_any_port(options.host);
    if (port < 0) Fail("cannot bind any port on ", options.host);
  } else if (!server.bind_to_port(options.host, port)) {
    Fail("port ", port, " on ", options.host,
         " is in use (or not permitted); pick another with --port");
  }
  const StopOnSignals stop(&server);
  listening("http://" + options.host + ":" + std::to_string(port) + "/");
  if (!server.listen_after_bind() && !stop.stopped()) Fail("serving on port ", port, " stopped");
}

}  // namespace holocap
