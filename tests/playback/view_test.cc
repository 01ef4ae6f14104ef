// `holocap view` against a hostile client on this machine: a small site written here (no
// training), probed over raw sockets for paths out of the site (`..`, encoded or not, symbolic
// links out), files that are not regular (a folder, a FIFO), foreign Host headers (a page of
// another site reading it through a DNS name rebound to 127.0.0.1), Range headers that multiply
// the answer, a hundred idle connections; SIGTERM and SIGINT. Then `view TAKE` (a tiny simulated
// take with a reconstruction and a splat model) stopped during its export and while it serves,
// and a folder or a link prepared at the temporary site's former fixed name.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/time.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "core/error.h"
#include "core/fs.h"
#include "playback/playback.h"
#include "tests/playback/view_server.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;
using testing::RunCli;
using testing::TempDir;
using testing::ViewServer;
using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// A connected TCP socket to 127.0.0.1:port whose reads give up after `timeout_s`; -1 on failure.
int Connect(int port, double timeout_s) {
  const int socket = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (socket < 0) return -1;
  timeval timeout{};
  timeout.tv_sec = static_cast<time_t>(timeout_s);
  timeout.tv_usec =
      static_cast<suseconds_t>((timeout_s - static_cast<double>(timeout.tv_sec)) * 1e6);
  setsockopt(socket, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(socket, reinterpret_cast<const sockaddr*>(&address), sizeof(address)) != 0) {
    close(socket);
    return -1;
  }
  return socket;
}

struct Answer {
  int status = 0;                             // 0: no answer (refused, timed out, cut)
  std::map<std::string, std::string> header;  // names in lower case
  std::string body;
  size_t bytes = 0;  // everything read, the head included
  std::string Header(const std::string& lowercase_name) const {
    const auto found = header.find(lowercase_name);
    return found == header.end() ? "" : found->second;
  }
};

// Sends `request` (raw text) on a new connection and reads until the server closes it, at most
// `max_bytes` and `timeout_s` between two reads.
Answer Ask(int port, const std::string& request, double timeout_s = 10,
           size_t max_bytes = 64u << 20) {
  Answer answer;
  const int socket = Connect(port, timeout_s);
  if (socket < 0) return answer;
  std::string received;
  if (send(socket, request.data(), request.size(), MSG_NOSIGNAL) ==
      static_cast<ssize_t>(request.size())) {
    char buffer[1 << 16];
    ssize_t read = 0;
    while (received.size() < max_bytes && (read = recv(socket, buffer, sizeof(buffer), 0)) > 0)
      received.append(buffer, static_cast<size_t>(read));
  }
  close(socket);
  answer.bytes = received.size();
  const size_t head_end = received.find("\r\n\r\n");
  if (received.rfind("HTTP/1.1 ", 0) != 0 || head_end == std::string::npos) return answer;
  answer.status = std::stoi(received.substr(9, 3));
  for (size_t at = received.find("\r\n") + 2; at < head_end;) {
    const size_t end = received.find("\r\n", at);
    const std::string line = received.substr(at, end - at);
    const size_t colon = line.find(':');
    std::string name = line.substr(0, colon);
    for (char& c : name) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    answer.header[name] = line.substr(line.find_first_not_of(' ', colon + 1));
    at = end + 2;
  }
  answer.body = received.substr(head_end + 4);
  return answer;
}

// A request that closes its connection: `method target`, the Host header (none when empty),
// then `extra` header lines.
std::string Request(const std::string& target, const std::string& host,
                    const std::string& extra = "", const std::string& method = "GET") {
  return method + " " + target + " HTTP/1.1\r\n" + (host.empty() ? "" : "Host: " + host + "\r\n") +
         extra + "Connection: close\r\n\r\n";
}

// The most resident memory a process has had so far (VmHWM), MB.
double PeakResidentMb(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(status, line);)
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  return -1;
}

constexpr const char* kIndex = "<!doctype html><title>site</title>\n";
constexpr size_t kChunkBytes = 1u << 20;
constexpr const char* kAllowedHost = "viewer.test";

// A site as export web lays it out (a manifest of the current version, index.html, one chunk of
// 1 MB), and beside it what must never be served: a file outside it, links out of it, a folder,
// a FIFO.
class ViewTest : public ::testing::Test {
 protected:
  void SetUp() override {
    fs::create_directories(Site() / "streams" / "mesh-medium");
    fs::create_directories(Site() / "folder");
    WriteFileAtomic(Site() / "manifest.json", R"({"format": "holocap-stream", "version": )" +
                                                  std::to_string(kWebStreamFormatVersion) + "}");
    WriteFileAtomic(Site() / "index.html", kIndex);
    WriteFileAtomic(Site() / "folder" / "file.txt", "in a folder");
    for (size_t i = 0; i < kChunkBytes; ++i) chunk_ += static_cast<char>((i * 2654435761u) >> 24);
    WriteFileAtomic(Chunk(), chunk_);
    WriteFileAtomic(dir_.path() / "outside.txt", "outside the site");
    fs::create_directory_symlink("/", Site() / "root");
    fs::create_symlink("../outside.txt", Site() / "out");
    fs::create_symlink(Chunk(), Site() / "inside.hcc");
    ASSERT_EQ(mkfifo((Site() / "fifo").c_str(), 0600), 0);
  }
  fs::path Site() const { return dir_.path() / "site"; }
  fs::path Chunk() const { return Site() / "streams" / "mesh-medium" / "000000.hcc"; }
  // `holocap view SITE --port 0 --host viewer.test`, up to its URL.
  std::unique_ptr<ViewServer> Serve() const {
    auto server = std::make_unique<ViewServer>(
        ViewServer::Start{{Site().string(), "--port", "0", "--host", kAllowedHost}, {}, {}});
    server->WaitForUrl();
    return server;
  }
  static std::string Host(const ViewServer& server) {
    return "127.0.0.1:" + std::to_string(server.port());
  }

  TempDir dir_{"holocap-view"};
  std::string chunk_;
};

TEST_F(ViewTest, ServesRegularFilesInsideTheSiteOnly) {
  const auto server = Serve();
  ASSERT_GT(server->port(), 0) << server->printed();
  const int port = server->port();
  const std::string host = Host(*server);

  Answer index = Ask(port, Request("/", host));
  EXPECT_EQ(index.status, 200);
  EXPECT_EQ(index.body, kIndex);
  EXPECT_EQ(index.Header("content-type"), "text/html; charset=utf-8");
  EXPECT_EQ(index.Header("cache-control"), "no-cache");
  Answer head = Ask(port, Request("/", host, "", "HEAD"));
  EXPECT_EQ(head.status, 200);
  EXPECT_EQ(head.Header("content-length"), std::to_string(std::string(kIndex).size()));
  EXPECT_TRUE(head.body.empty());
  EXPECT_EQ(Ask(port, Request("/manifest.json", host)).Header("content-type"), "application/json");
  Answer chunk = Ask(port, Request("/streams/mesh-medium/000000.hcc", host));
  EXPECT_EQ(chunk.status, 200);
  EXPECT_TRUE(chunk.body == chunk_) << chunk.body.size() << " bytes";
  // A link to a file inside the site is served; one out of it is not, nor is a path through
  // `..`, written plainly or percent-encoded.
  Answer linked = Ask(port, Request("/inside.hcc", host));
  EXPECT_EQ(linked.status, 200);
  EXPECT_TRUE(linked.body == chunk_) << linked.body.size() << " bytes";
  for (const std::string target :
       {"/root/etc/passwd", "/root/etc/hostname", "/out", "/../outside.txt", "/../../etc/passwd",
        "/%2e%2e/outside.txt", "/%2E%2E/%2e%2e/etc/passwd", "/streams/..%2f..%2foutside.txt",
        "/streams/%2e%2e/%2e%2e/outside.txt", "/folder/../../outside.txt"}) {
    const Answer answer = Ask(port, Request(target, host));
    EXPECT_EQ(answer.status, 404) << target << ": " << answer.body.substr(0, 200);
    EXPECT_EQ(answer.body.find("root:"), std::string::npos) << target;
    EXPECT_EQ(answer.body.find("outside the site"), std::string::npos) << target;
  }
  // Only regular files: not a folder (nor its index.html, which it has not), not a FIFO (no
  // wait for a writer), not a missing file, not a name cut by a NUL.
  for (const std::string target :
       {"/folder", "/folder/", "/streams", "/fifo", "/missing.json", "/index.html%00.png"}) {
    const auto start = Clock::now();
    EXPECT_EQ(Ask(port, Request(target, host), 5).status, 404) << target;
    EXPECT_LT(SecondsSince(start), 2.0) << target;
  }
  EXPECT_EQ(Ask(port, Request("/folder/file.txt", host)).body, "in a folder");
  const Answer post = Ask(port, Request("/", host, "Content-Length: 5\r\n", "POST") + "hello");
  EXPECT_EQ(post.status, 405);
  EXPECT_EQ(post.Header("allow"), "GET, HEAD");
}

TEST_F(ViewTest, AnswersLoopbackHostsAndTheOneNamedByHostOnly) {
  const auto server = Serve();
  ASSERT_GT(server->port(), 0) << server->printed();
  const int port = server->port();
  const std::string own = ":" + std::to_string(port);
  for (const std::string& host :
       {"127.0.0.1" + own, "localhost" + own, "[::1]" + own, std::string("127.0.0.1"),
        std::string("LocalHost"), std::string(kAllowedHost) + own, std::string(kAllowedHost)}) {
    const Answer answer = Ask(port, Request("/", host));
    EXPECT_EQ(answer.status, 200) << host;
    EXPECT_EQ(answer.body, kIndex) << host;
  }
  // A page of another site whose DNS name now resolves to 127.0.0.1 sends its own name.
  for (const std::string& host :
       {"evil.example" + own, std::string("evil.example"), "127.0.0.1.evil.example" + own,
        "localhost.evil.example" + own, std::string("localhost:1"),
        "viewer.test.evil.example" + own, std::string("")}) {
    const Answer answer = Ask(port, Request("/manifest.json", host, "Range: bytes=0-9,20-29\r\n"));
    EXPECT_EQ(answer.status, 403) << "Host: " << host;
    EXPECT_NE(answer.body.find("answers Host 127.0.0.1, localhost or [::1] only"),
              std::string::npos)
        << answer.body;
    EXPECT_EQ(answer.body.find("holocap-stream"), std::string::npos) << host;
  }
  testing::ExpectOneLineError(RunCli("view '" + Site().string() + "' --host 'bad/name'"),
                              "--host bad/name");
}

TEST_F(ViewTest, RefusesRangesBeyondTheFileBeforeAnswering) {
  const auto server = Serve();
  ASSERT_GT(server->port(), 0) << server->printed();
  const int port = server->port();
  const std::string host = Host(*server);
  const std::string target = "/streams/mesh-medium/000000.hcc";
  const std::string size = std::to_string(kChunkBytes);
  const auto ranges = [&](const std::string& ranges) {
    return Ask(port, Request(target, host, "Range: bytes=" + ranges + "\r\n"), 10, 8u << 20);
  };
  const auto repeated = [](const std::string& range, int count) {
    std::string ranges = range;
    for (int i = 1; i < count; ++i) ranges += "," + range;
    return ranges;
  };
  // What a player or a download asks for is answered, an end past the file cut to it.
  Answer one = ranges("10-19");
  EXPECT_EQ(one.status, 206);
  EXPECT_EQ(one.Header("content-range"), "bytes 10-19/" + size);
  EXPECT_EQ(one.body, chunk_.substr(10, 10));
  Answer to_end = ranges("1048000-99999999");
  EXPECT_EQ(to_end.status, 206);
  EXPECT_EQ(to_end.Header("content-range"), "bytes 1048000-1048575/" + size);
  EXPECT_EQ(to_end.body, chunk_.substr(1048000));
  EXPECT_EQ(ranges("-16").body, chunk_.substr(kChunkBytes - 16));
  Answer two = ranges("0-9,100-109");
  EXPECT_EQ(two.status, 206);
  EXPECT_NE(two.body.find("Content-Range: bytes 100-109/" + size), std::string::npos) << two.body;
  EXPECT_NE(two.body.find(chunk_.substr(100, 10)), std::string::npos);

  const double before_mb = PeakResidentMb(server->pid());
  const ViewServerOptions options;
  for (const std::string& asked :
       {repeated("0-", 300), repeated("0-", 100), repeated("0-", 2), repeated("0-0", 9),
        std::string("0-9,") + size + "-", size + "-", std::string("-0")}) {
    const auto start = Clock::now();
    const Answer answer = ranges(asked);
    const double seconds = SecondsSince(start);
    EXPECT_EQ(answer.status, 416) << asked.substr(0, 40) << ": " << answer.bytes << " bytes";
    EXPECT_EQ(answer.Header("content-range"), "bytes */" + size);
    EXPECT_LT(answer.bytes, 1000u);
    std::printf("Range: bytes=%s%s (%zu bytes) -> %d, %zu bytes, %.3f s\n",
                asked.substr(0, 24).c_str(), asked.size() > 24 ? "..." : "", asked.size(),
                answer.status, answer.bytes, seconds);
  }
  const double after_mb = PeakResidentMb(server->pid());
  std::printf(
      "server peak RSS %.1f MB before the refused ranges, %.1f MB after (at most %d ranges)\n",
      before_mb, after_mb, options.max_ranges);
  EXPECT_LT(after_mb - before_mb, 32.0);
  EXPECT_EQ(Ask(port, Request("/", host)).status, 200) << "the server no longer answers";
}

TEST_F(ViewTest, AnswersBehindAHundredIdleConnections) {
  const auto server = Serve();
  ASSERT_GT(server->port(), 0) << server->printed();
  const int port = server->port();
  // Each idle connection holds a worker until it times out; a request queued behind them waits
  // at most a timeout per round of the pool it takes to reach it (rounded up), and the 1 s more
  // allowed here is for answering it.
  const ViewServerOptions options;
  constexpr int kIdle = 100;
  const int rounds = (kIdle + 1 + options.workers - 1) / options.workers;
  const double bound_s = options.idle_timeout_s * rounds + 1.0;
  std::vector<int> idle;
  const auto opened = Clock::now();
  for (int i = 0; i < kIdle; ++i) {
    const int socket = Connect(port, 2 * bound_s);
    ASSERT_GE(socket, 0) << "connection " << i;
    idle.push_back(socket);
  }
  // Accepted as they come: none waited for its SYN to be sent again (1 s at least).
  const double connecting_s = SecondsSince(opened);
  EXPECT_LT(connecting_s, 1.0);
  const auto start = Clock::now();
  const Answer answer = Ask(port, Request("/", Host(*server)), 2 * bound_s);
  const double seconds = SecondsSince(start);
  std::printf(
      "a request behind %d idle connections (opened in %.2f s) answered in %.2f s (bound %.1f "
      "s)\n",
      kIdle, connecting_s, seconds, bound_s);
  EXPECT_EQ(answer.status, 200);
  EXPECT_LT(seconds, bound_s);
  // The server closes every idle connection, the last one queued within the same bound.
  int closed = 0;
  for (int socket : idle) {
    char byte = 0;
    closed += recv(socket, &byte, 1, 0) == 0 ? 1 : 0;
    close(socket);
  }
  EXPECT_EQ(closed, kIdle);
  EXPECT_LT(SecondsSince(start), bound_s);
}

TEST_F(ViewTest, StopsOnSigtermAndSigintAndSaysSo) {
  for (int signal : {SIGTERM, SIGINT}) {
    const auto server = Serve();
    ASSERT_GT(server->port(), 0) << server->printed();
    const int status = server->Stop(signal);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0)
        << strsignal(signal) << ": status " << status << "\n"
        << server->printed();
    EXPECT_NE(server->printed().find("\nstopped\n"), std::string::npos) << server->printed();
  }
}

// `view TAKE` on a take of one frame set with its reconstruction and a splat model of a few
// iterations (whose export starts OpenMP threads), TMPDIR pointed at a folder of the test.
class ViewTakeTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new TempDir("holocap-view-take");
    const std::string take = "'" + Take().string() + "'";
    auto sim =
        RunCli("sim --rig studio8 --frames 2 --clean-plate 1 --size 64 --seed 3 --out " + take);
    ASSERT_EQ(sim.exit_code, 0) << sim.output;
    auto recon = RunCli("reconstruct " + take + " --ground-truth-cameras --voxel 8mm --no-sweep");
    ASSERT_EQ(recon.exit_code, 0) << recon.output;
    auto splat = RunCli(
        "train splat " + take +
        " --ground-truth-cameras --iterations 20 --width 64 --seed-points 500 --eval-every 1000");
    ASSERT_TRUE(fs::exists(Take() / "models" / "splat" / "model.json")) << splat.output;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  void SetUp() override {
    fs::remove_all(Tmp());
    fs::create_directories(Tmp());
  }
  static fs::path Take() { return dir_->path() / "take"; }
  static fs::path Tmp() { return dir_->path() / "tmp"; }
  // What TMPDIR holds of `view`'s temporary sites.
  static std::vector<std::string> TemporaryFolders() {
    std::vector<std::string> names;
    for (const auto& entry : fs::directory_iterator(Tmp()))
      if (entry.path().filename().string().starts_with("holocap-view-"))
        names.push_back(entry.path().filename().string());
    return names;
  }
  // Whether a temporary site's export has begun (its run.json is written first of all).
  static bool ExportStarted() {
    std::error_code error;
    for (const auto& entry : fs::directory_iterator(Tmp(), error))
      for (const fs::path& run : {entry.path() / "run.json", entry.path() / "site" / "run.json"})
        if (fs::exists(run, error)) return true;
    return false;
  }
  static ViewServer::Start ViewTake(std::function<void(pid_t)> before_exec = {}) {
    return {
        {Take().string(), "--ground-truth-cameras", "--port", "0"}, Tmp(), std::move(before_exec)};
  }
  static TempDir* dir_;
};
TempDir* ViewTakeTest::dir_ = nullptr;

TEST_F(ViewTakeTest, StoppedDuringTheExportLeavesNothingAndExitsZero) {
  for (int signal : {SIGTERM, SIGINT}) {
    ViewServer server(ViewTake());
    const auto start = Clock::now();
    while (!ExportStarted() && !server.Ended() && SecondsSince(start) < 60)
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    ASSERT_TRUE(ExportStarted()) << "the export did not start";
    const int status = server.Stop(signal);
    const std::string& printed = server.printed();
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0)
        << strsignal(signal) << ": status " << status << "\n"
        << printed;
    EXPECT_EQ(printed.find("serving on"), std::string::npos) << "not stopped during the export";
    EXPECT_NE(printed.find("stopped during the export"), std::string::npos) << printed;
    EXPECT_EQ(TemporaryFolders(), std::vector<std::string>{}) << strsignal(signal);
  }
}

TEST_F(ViewTakeTest, StoppedWhileServingLeavesNothingAndExitsZero) {
  for (int signal : {SIGTERM, SIGINT}) {
    ViewServer server(ViewTake());
    ASSERT_TRUE(server.WaitForUrl()) << server.printed();
    EXPECT_EQ(Ask(server.port(), Request("/", "localhost:" + std::to_string(server.port()))).status,
              200);
    EXPECT_EQ(TemporaryFolders().size(), 1u);
    const int status = server.Stop(signal);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0)
        << strsignal(signal) << ": status " << status << "\n"
        << server.printed();
    EXPECT_NE(server.printed().find("\nstopped"), std::string::npos) << server.printed();
    EXPECT_EQ(TemporaryFolders(), std::vector<std::string>{}) << strsignal(signal);
  }
}

// The temporary site was TMPDIR/holocap-view-<pid>, reused when it existed: a folder prepared
// there lost its files, a link there had the export write into its target.
TEST_F(ViewTakeTest, NeverWritesIntoAFolderOrALinkAtAPredictableName) {
  const fs::path victim = dir_->path() / "victim";
  fs::create_directories(victim);
  WriteFileAtomic(victim / "index.html", "mine");
  WriteFileAtomic(victim / "manifest.json", "mine");
  for (const bool link : {false, true}) {
    fs::path prepared;
    ViewServer server(ViewTake([&](pid_t pid) {
      prepared = Tmp() / ("holocap-view-" + std::to_string(pid));
      if (link) {
        fs::create_directory_symlink(victim, prepared);
      } else {
        fs::create_directories(prepared);
        WriteFileAtomic(prepared / "keep.txt", "kept");
      }
    }));
    ASSERT_TRUE(server.WaitForUrl()) << server.printed();
    const int status = server.Stop(SIGTERM);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << server.printed();
    EXPECT_EQ(TemporaryFolders(), std::vector<std::string>{prepared.filename().string()});
    if (link) {
      EXPECT_TRUE(fs::is_symlink(prepared));
      EXPECT_EQ(ReadFileToString(victim / "index.html"), "mine");
      EXPECT_EQ(ReadFileToString(victim / "manifest.json"), "mine");
      EXPECT_EQ(std::distance(fs::directory_iterator(victim), fs::directory_iterator()), 2);
      fs::remove(prepared);
    } else {
      ASSERT_TRUE(fs::exists(prepared / "keep.txt")) << "the prepared folder lost its file";
      EXPECT_EQ(ReadFileToString(prepared / "keep.txt"), "kept");
      EXPECT_EQ(std::distance(fs::directory_iterator(prepared), fs::directory_iterator()), 1);
      fs::remove_all(prepared);
    }
  }
}

}  // namespace
}  // namespace holocap
