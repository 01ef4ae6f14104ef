// The capture node: the recorder behind a ZeroMQ reply socket, and the host's clock state.
#include "distributed/node.h"

#include <sys/timex.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <memory>
#include <mutex>
#include <regex>
#include <thread>

#include "core/check_option.h"
#include "core/error.h"
#include "distributed/internal/capture_control_channel.h"

namespace holocap {

nlohmann::json ClockState::ToJson() const {
  return {{"host", host},           {"source", source},     {"synchronised", synchronised},
          {"offset_ns", offset_ns}, {"error_ns", error_ns}, {"detail", detail}};
}

ClockState ClockState::FromJson(const nlohmann::json& json) {
  ClockState state;
  state.host = json.value("host", "");
  state.source = json.value("source", "none");
  state.synchronised = json.value("synchronised", false);
  state.offset_ns = json.value("offset_ns", int64_t{0});
  state.error_ns = json.value("error_ns", int64_t{-1});
  state.detail = json.value("detail", "");
  return state;
}

nlohmann::json NodeClock::ToJson() const {
  return {{"daemon", daemon.ToJson()},        {"channel_offset_ns", channel_offset_ns},
          {"channel_rtt_ns", channel_rtt_ns}, {"offset_ns", offset_ns},
          {"uncertainty_ns", uncertainty_ns}, {"offset_source", offset_source}};
}

NodeClock NodeClock::FromJson(const nlohmann::json& json) {
  NodeClock clock;
  clock.daemon = ClockState::FromJson(json.value("daemon", nlohmann::json::object()));
  clock.channel_offset_ns = json.value("channel_offset_ns", int64_t{0});
  clock.channel_rtt_ns = json.value("channel_rtt_ns", int64_t{0});
  clock.offset_ns = json.value("offset_ns", int64_t{0});
  clock.uncertainty_ns = json.value("uncertainty_ns", int64_t{0});
  clock.offset_source = json.value("offset_source", "");
  return clock;
}

namespace {

// Whether a process of this name (its /proc/PID/comm) runs on the host.
bool ProcessRuns(const std::string& name) {
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator("/proc", ec)) {
    const std::string pid = entry.path().filename();
    if (pid.find_first_not_of("0123456789") != std::string::npos) continue;
    std::ifstream comm(entry.path() / "comm");
    std::string line;
    if (std::getline(comm, line) && line == name) return true;
  }
  return false;
}

// The output of a shell command ("" when it cannot run).
std::string CommandOutput(const std::string& command) {
  std::string output;
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) return output;
  char buffer[512];
  while (std::fgets(buffer, sizeof(buffer), pipe) != nullptr) output += buffer;
  pclose(pipe);
  return output;
}

std::string HostName() {
  char name[256] = {};
  gethostname(name, sizeof(name) - 1);
  return name;
}

void ReadPtp(ClockState* state) {
  state->source = "ptp";
  const std::string output = CommandOutput("pmc -u -b 0 'GET TIME_STATUS_NP'");
  std::smatch match;
  if (!std::regex_search(output, match, std::regex(R"(master_offset\s+(-?\d+))"))) {
    state->detail =
        Cat("ptp4l/phc2sys run, but pmc gave no master_offset: ", Printable(output.substr(0, 200)));
    return;
  }
  state->offset_ns = std::stoll(match[1]);
  state->synchronised = std::regex_search(output, std::regex(R"(gmPresent\s+true)"));
  state->detail = Cat("pmc TIME_STATUS_NP master_offset ", state->offset_ns, " ns");
}

void ReadChrony(ClockState* state) {
  state->source = "chrony";
  const std::string output = CommandOutput("chronyc tracking");
  std::smatch match;
  if (!std::regex_search(output, match,
                         std::regex(R"(System time\s*:\s*([0-9.]+) seconds (fast|slow))"))) {
    state->detail =
        Cat("chronyd runs, but chronyc tracking said: ", Printable(output.substr(0, 200)));
    return;
  }
  const double seconds = std::stod(match[1]);
  state->offset_ns =
      static_cast<int64_t>(std::llround(seconds * 1e9)) * (match[2] == "fast" ? 1 : -1);
  state->synchronised = output.find("Not synchronised") == std::string::npos;
  state->detail =
      Cat("chronyc tracking: system time ", match[1].str(), " s ", match[2].str(), " of NTP time");
}

void ReadAdjtimex(ClockState* state) {
  state->source = "adjtimex";
  timex tx{};
  const int result = adjtimex(&tx);
  if (result < 0) {
    state->source = "none";
    state->detail = "adjtimex failed";
    return;
  }
  const bool nano = (tx.status & STA_NANO) != 0;
  state->offset_ns = static_cast<int64_t>(tx.offset) * (nano ? 1 : 1000);
  state->error_ns = static_cast<int64_t>(tx.maxerror) * 1000;
  state->synchronised = result != TIME_ERROR && (tx.status & STA_UNSYNC) == 0;
  state->detail = Cat("adjtimex: state ", result, state->synchronised ? "" : " (unsynchronised)",
                      ", offset ", state->offset_ns, " ns, maxerror ", tx.maxerror, " us");
}

}  // namespace

ClockState ReadClockState() {
  ClockState state;
  state.host = HostName();
  if (ProcessRuns("ptp4l") || ProcessRuns("phc2sys")) {
    ReadPtp(&state);
  } else if (ProcessRuns("chronyd")) {
    ReadChrony(&state);
  } else {
    ReadAdjtimex(&state);
  }
  return state;
}

void CaptureNodeOptions::Check() const {
  HOLOCAP_CHECK_OPTION(!listen.empty(), listen, "a ZeroMQ endpoint, tcp://ADDR:PORT");
  HOLOCAP_CHECK_OPTION_GE(max_takes, 0);
}

namespace {

// One take on a node: the recorder, opened and run in a thread of its own, so that the channel
// answers while the sensors open.
class NodeTake {
 public:
  NodeTake(const RigDescription& rig, const std::filesystem::path& part, RecorderOptions options)
      : part_(part) {
    thread_ = std::thread([this, rig, options] { Record(rig, options); });
  }
  ~NodeTake() {
    Stop();
    if (thread_.joinable()) thread_.join();
  }
  void Stop() {
    std::lock_guard lock(mutex_);
    stop_ = true;
    if (recorder_) recorder_->RequestStop();
  }
  bool done() const { return done_; }
  nlohmann::json Status() {
    std::lock_guard lock(mutex_);
    return status_;
  }
  nlohmann::json Result() {
    std::lock_guard lock(mutex_);
    return result_;
  }
  const std::filesystem::path& part() const { return part_; }

 private:
  void Record(const RigDescription& rig, const RecorderOptions& options) {
    nlohmann::json result;
    try {
      auto recorder = std::make_unique<Recorder>(rig, part_, options);
      {
        std::lock_guard lock(mutex_);
        recorder_ = std::move(recorder);
        if (stop_) recorder_->RequestStop();
      }
      Report report("capture-node");
      RecorderSummary summary = recorder_->Run(
          [this](const RecorderStatus& status) {
            std::lock_guard lock(mutex_);
            status_ = control::StatusToJson(status);
          },
          &report);
      report.metrics() = summary.Metrics();
      report.SetSummary(summary);
      try {
        report.Write(part_ / "report.json");
      } catch (const Error&) {
        // The part itself is closed; its summary travels to the coordinator all the same.
      }
      result = control::SummaryToJson(summary);
    } catch (const std::exception& e) {
      result = {{"termination", ToString(Termination::kFailure)},
                {"message", e.what()},
                {"usable", false}};
    }
    std::lock_guard lock(mutex_);
    result_ = result;
    done_ = true;
  }

  std::filesystem::path part_;
  std::mutex mutex_;
  std::unique_ptr<Recorder> recorder_;
  bool stop_ = false;
  nlohmann::json status_ = nlohmann::json::object();
  nlohmann::json result_ = nlohmann::json::object();
  std::atomic<bool> done_{false};
  std::thread thread_;
};

nlohmann::json Failure(const std::string& message) { return {{"ok", false}, {"error", message}}; }

// The node's side of the channel: one request, one reply.
class NodeServer {
 public:
  explicit NodeServer(const CaptureNodeOptions& options) : options_(options) {
    name_ = options.name.empty() ? HostName() : options.name;
  }

  nlohmann::json Handle(const nlohmann::json& request,
                        const std::function<void(const std::string&)>& log) {
    const std::string command = request.value("cmd", "");
    if (command == "hello") {
      return {{"ok", true},      {"name", name_},  {"host", HostName()},
              {"pid", getpid()}, {"busy", busy()}, {"clock", ReadClockState().ToJson()}};
    }
    if (command == "clock") return {{"ok", true}, {"realtime_ns", control::RealtimeNs()}};
    if (command == "start") return Start(request, log);
    if (command == "status") {
      if (!take_) return Failure("no take was started");
      return {{"ok", true}, {"done", take_->done()}, {"status", take_->Status()}};
    }
    if (command == "stop") {
      if (take_) take_->Stop();
      return {{"ok", true}};
    }
    if (command == "result") {
      if (!take_) return Failure("no take was started");
      nlohmann::json reply = {{"ok", true}, {"done", take_->done()}, {"part", take_->part()}};
      if (take_->done()) {
        reply["summary"] = take_->Result();
        if (!finished_counted_) {
          finished_counted_ = true;
          ++takes_finished_;
          log(Cat("take finished: ", take_->part().string(), ": ",
                  reply["summary"].value("message", "")));
        }
      }
      return reply;
    }
    return Failure(Cat("unknown request '", command, "'"));
  }

  bool finished() const { return options_.max_takes > 0 && takes_finished_ >= options_.max_takes; }

 private:
  bool busy() const { return take_ && !take_->done(); }

  nlohmann::json Start(const nlohmann::json& request,
                       const std::function<void(const std::string&)>& log) {
    if (busy()) return Failure(Cat("node '", name_, "' is recording a take already"));
    try {
      const RigDescription rig = RigDescription::FromJson(request.at("rig"), "the start request");
      std::filesystem::path part = request.at("part").get<std::string>();
      if (!options_.root.empty()) part = options_.root / part.filename();
      RecorderOptions recorder = control::RecorderOptionsFromJson(request.at("options"));
      recorder.metadata = {{"node", {{"name", name_}, {"host", HostName()}}}};
      recorder.metadata["node"]["clock"] = request.value("clock", nlohmann::json::object());
      recorder.metadata["node"]["clock"]["at_start"] = ReadClockState().ToJson();
      recorder.take.command = "capture-node";
      recorder.Check();
      take_.reset();
      finished_counted_ = false;
      take_ = std::make_unique<NodeTake>(rig, part, recorder);
      log(Cat("take started: ", rig.sensors.size(), " sensors into ", part.string()));
      return {{"ok", true}, {"part", part}};
    } catch (const std::exception& e) {
      return Failure(e.what());
    }
  }

  CaptureNodeOptions options_;
  std::string name_;
  std::unique_ptr<NodeTake> take_;
  bool finished_counted_ = false;
  int takes_finished_ = 0;
};

}  // namespace

void ServeCaptureNode(const CaptureNodeOptions& options, const std::atomic<bool>& stop,
                      const std::function<void(const std::string&)>& log) {
  options.Check();
  auto say = [&](const std::string& line) {
    if (log) log(line);
  };
  zmq::context_t context(1);
  zmq::socket_t socket(context, zmq::socket_type::rep);
  socket.set(zmq::sockopt::linger, 0);
  try {
    socket.bind(options.listen);
  } catch (const zmq::error_t& e) {
    Fail("capture-node: cannot listen on '", options.listen, "': ", e.what());
  }
  say(Cat("listening on ", options.listen));
  NodeServer server(options);
  while (!stop && !server.finished()) {
    zmq::pollitem_t items[] = {{static_cast<void*>(socket), 0, ZMQ_POLLIN, 0}};
    try {
      zmq::poll(items, 1, std::chrono::milliseconds(100));
    } catch (const zmq::error_t& e) {
      if (e.num() == EINTR) continue;
      throw;
    }
    if ((items[0].revents & ZMQ_POLLIN) == 0) continue;
    zmq::message_t message;
    if (!socket.recv(message, zmq::recv_flags::none)) continue;
    nlohmann::json reply;
    try {
      reply = server.Handle(nlohmann::json::parse(message.to_string()), say);
    } catch (const std::exception& e) {
      reply = Failure(Cat("bad request: ", e.what()));
    }
    socket.send(zmq::buffer(reply.dump()), zmq::send_flags::none);
  }
}

}  // namespace holocap
