// holocap view: a site served on loopback (cpp-httplib), its regular files only.
#include <fcntl.h>
#include <pthread.h>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <string_view>
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

namespace fs = std::filesystem;

// The content type of a site's file, by its extension.
const char* ContentType(const fs::path& file) {
  static constexpr std::pair<std::string_view, const char*> kTypes[] = {
      {".js", "text/javascript"},    {".mjs", "text/javascript"},
      {".json", "application/json"}, {".html", "text/html; charset=utf-8"},
      {".css", "text/css"},          {".hcc", "application/octet-stream"},
      {".png", "image/png"},
  };
  const std::string extension = file.extension().string();
  for (const auto& [suffix, type] : kTypes)
    if (extension == suffix) return type;
  return "application/octet-stream";
}

std::string Lowercase(std::string text) {
  for (char& c : text) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return text;
}

// What --host accepts: a name, an IPv4 or a bracketed IPv6 address, an optional :PORT (a DNS
// name has 253 characters at most).
bool IsHostName(const std::string& name) {
  if (name.size() > 253 + std::string_view(":65535").size()) return false;
  return std::all_of(name.begin(), name.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '.' || c == '-' || c == ':' ||
           c == '[' || c == ']';
  });
}

// Whether a request's Host header names this server: 127.0.0.1, localhost, [::1] or `allowed`,
// alone or followed by this server's port.
bool IsAnsweredHost(const std::string& header, const std::string& allowed, int port) {
  const std::string host = Lowercase(header);
  const std::string own_port = Cat(":", port);
  const std::string name =
      host.ends_with(own_port) ? host.substr(0, host.size() - own_port.size()) : host;
  for (const std::string& known : {std::string("127.0.0.1"), std::string("localhost"),
                                   std::string("[::1]"), Lowercase(allowed)})
    if (!known.empty() && (name == known || host == known)) return true;
  return false;
}

// Whether `path` is `root` or lies under it (both canonical).
bool IsInside(const fs::path& path, const fs::path& root) {
  return std::mismatch(root.begin(), root.end(), path.begin(), path.end()).first == root.end();
}

// The regular file inside `root` (a canonical folder) that a request's path names, opened for
// reading; -1 when there is none. A path with a `..` segment names none; every symbolic link is
// resolved and what it resolves to must lie inside `root`; the file opened is the one checked
// (same device and inode, no link followed at the last step), and opening never waits (a FIFO
// swapped in is not regular and is refused).
int OpenSiteFile(const fs::path& root, const std::string& url_path, uint64_t* size) {
  if (url_path.empty() || url_path.front() != '/' || url_path.find('\0') != std::string::npos)
    return -1;
  fs::path relative;
  for (size_t begin = 1; begin <= url_path.size();) {
    const size_t end = std::min(url_path.find('/', begin), url_path.size());
    const std::string_view segment(url_path.data() + begin, end - begin);
    if (segment == "..") return -1;
    if (!segment.empty() && segment != ".") relative /= segment;
    begin = end + 1;
  }
  if (url_path.back() == '/') relative /= "index.html";
  std::error_code error;
  const fs::path resolved = fs::canonical(root / relative, error);
  struct stat checked {};
  if (error || !IsInside(resolved, root) || ::stat(resolved.c_str(), &checked) != 0 ||
      !S_ISREG(checked.st_mode))
    return -1;
  const int fd =
      ::open(resolved.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK | O_NOCTTY);
  if (fd < 0) return -1;
  struct stat opened {};
  if (::fstat(fd, &opened) != 0 || !S_ISREG(opened.st_mode) || opened.st_dev != checked.st_dev ||
      opened.st_ino != checked.st_ino) {
    ::close(fd);
    return -1;
  }
  *size = static_cast<uint64_t>(opened.st_size);
  return fd;
}

// Reads `body->size()` bytes of `fd` from its start into `body`.
bool ReadWhole(int fd, std::string* body) {
  for (size_t done = 0; done < body->size();) {
    const ssize_t read =
        ::pread(fd, body->data() + done, body->size() - done, static_cast<off_t>(done));
    if (read <= 0) return false;
    done += static_cast<size_t>(read);
  }
  return true;
}

// A Range header's ranges (as httplib parses them: -1 where a bound is absent) made the first and
// last byte of each range of a file of `size` bytes, ends past the file cut to it; false when
// there are more than `max_ranges`, one starts past the end, or together they are longer than
// the file (which bounds what a multipart answer makes).
bool ResolveRanges(httplib::Ranges* ranges, uint64_t size, int max_ranges) {
  if (ranges->size() > static_cast<size_t>(max_ranges) || size == 0) return false;
  const auto bytes = static_cast<ssize_t>(size);
  ssize_t total = 0;
  for (auto& [first, last] : *ranges) {
    if (first < 0 && last <= 0) return false;  // "bytes=-" or "bytes=-0"
    const ssize_t begin = first < 0 ? std::max<ssize_t>(0, bytes - last) : first;
    const ssize_t end = first < 0 || last < 0 ? bytes - 1 : std::min(last, bytes - 1);
    if (begin >= bytes) return false;
    total += end - begin + 1;
    if (total > bytes) return false;
    first = begin;
    last = end;
  }
  return true;
}

// Answers every request before httplib's routing, so that nothing of httplib reads a body, opens
// a file or cuts an answer to a range first (see ServeSite in playback.h).
class SiteAnswers {
 public:
  SiteAnswers(fs::path root, const ViewServerOptions& options, int port)
      : root_(std::move(root)), options_(options), port_(port) {}

  void operator()(const httplib::Request& request, httplib::Response& response) const {
    // httplib cuts whatever is answered to request.ranges and trusts their ends: they are taken
    // out here, and given back checked and cut to the file only with the file. The request is
    // httplib's own object, handed to this handler as const.
    auto& ranges = const_cast<httplib::Ranges&>(request.ranges);
    httplib::Ranges asked;
    asked.swap(ranges);
    if (!IsAnsweredHost(request.get_header_value("Host"), options_.allowed_host, port_))
      return Refuse(response, 403,
                    "holocap view answers Host 127.0.0.1, localhost or [::1] only (--host NAME "
                    "adds one)");
    if (request.method != "GET" && request.method != "HEAD") {
      response.set_header("Allow", "GET, HEAD");
      return Refuse(response, 405, "holocap view answers GET and HEAD only");
    }
    uint64_t size = 0;
    const int fd = OpenSiteFile(root_, request.path, &size);
    if (fd < 0) return Refuse(response, 404, "not found");
    if (!asked.empty() && !ResolveRanges(&asked, size, options_.max_ranges)) {
      ::close(fd);
      response.set_header("Content-Range", "bytes */" + std::to_string(size));
      return Refuse(response, 416,
                    Cat("range not satisfiable: at most ", options_.max_ranges,
                        " ranges inside the file, together no longer than the file"));
    }
    ranges.swap(asked);
    const char* type = ContentType(request.path.ends_with('/') ? "index.html" : request.path);
    if (size == 0 || ranges.size() > 1) {
      // httplib's multipart answer from a content provider says "/0" for the file's size in
      // each part's Content-Range, from a body the right size; the ranges are checked to be no
      // longer than the file together, so such an answer stays within twice its size.
      std::string body(size, '\0');
      const bool read = ReadWhole(fd, &body);
      ::close(fd);
      if (!read) return Refuse(response, 500, "cannot read the file");
      response.set_content(body, type);
      return;
    }
    response.set_content_provider(
        size, type,
        [fd](size_t offset, size_t length, httplib::DataSink& sink) {
          char buffer[1 << 16];
          const ssize_t read =
              ::pread(fd, buffer, std::min(length, sizeof(buffer)), static_cast<off_t>(offset));
          return read > 0 && sink.write(buffer, static_cast<size_t>(read));
        },
        [fd](bool) { ::close(fd); });
  }

 private:
  static void Refuse(httplib::Response& response, int status, const std::string& text) {
    response.status = status;
    response.set_content(text + "\n", "text/plain; charset=utf-8");
  }

  fs::path root_;
  ViewServerOptions options_;
  int port_;
};

}  // namespace

void ViewServerOptions::Check() const {
  HOLOCAP_CHECK_OPTION_IN(port, 0, 65535);
  HOLOCAP_CHECK_OPTION(IsOneOf(host, {"127.0.0.1", "localhost", "::1"}), host,
                       "holocap view serves on loopback only");
  HOLOCAP_CHECK_OPTION(IsHostName(allowed_host), allowed_host,
                       "a Host header's value: a name or an address, an optional :PORT");
  HOLOCAP_CHECK_OPTION_IN(idle_timeout_s, 1, 3600);
  HOLOCAP_CHECK_OPTION_IN(workers, 1, 4096);
  HOLOCAP_CHECK_OPTION_IN(max_ranges, 1, 1000);
}

void ServeSite(const std::filesystem::path& site, const ViewServerOptions& options,
               const std::function<void(const std::string& url)>& listening) {
  options.Check();
  std::string why;
  if (!IsWebSite(site, &why)) Fail(why);
  httplib::Server server;
  // Each connection holds a worker until it is closed; one that stays silent is closed after
  // idle_timeout_s (waiting for its first or next request, or inside one).
  server.new_task_queue = [workers = static_cast<size_t>(options.workers)] {
    return new httplib::ThreadPool(workers);
  };
  server.set_keep_alive_timeout(options.idle_timeout_s);
  server.set_read_timeout(options.idle_timeout_s);
  // Chunks change when a site is exported again: the browser asks each time.
  server.set_post_routing_handler([](const httplib::Request&, httplib::Response& response) {
    response.set_header("Cache-Control", "no-cache");
  });
  // httplib's default also sets SO_REUSEPORT, which lets a second server bind a port in use.
  socket_t listening_socket = INVALID_SOCKET;
  server.set_socket_options([&listening_socket](socket_t socket) {
    int yes = 1;
    setsockopt(socket, SOL_SOCKET, SO_REUSEADDR, reinterpret_cast<const void*>(&yes), sizeof(yes));
    listening_socket = socket;
  });
  int port = options.port;
  if (port == 0) {
    port = server.bind_to_any_port(options.host);
    if (port < 0) Fail("cannot bind any port on ", options.host);
  } else if (!server.bind_to_port(options.host, port)) {
    Fail("port ", port, " on ", options.host,
         " is in use (or not permitted); pick another with --port");
  }
  // httplib listens with a backlog of 5: a burst of connections waiting to be accepted has the
  // next ones dropped and their SYN sent again 1, 3, 7 s later. listen() again sets a larger one.
  ::listen(listening_socket, SOMAXCONN);
  const SiteAnswers answers(fs::canonical(site), options, port);
  server.set_pre_routing_handler(
      [&answers](const httplib::Request& request, httplib::Response& response) {
        answers(request, response);
        return httplib::Server::HandlerResponse::Handled;
      });
  const StopOnSignals stop(&server);
  listening("http://" + options.host + ":" + std::to_string(port) + "/");
  if (!server.listen_after_bind() && !stop.stopped()) Fail("serving on port ", port, " stopped");
}

}  // namespace holocap
