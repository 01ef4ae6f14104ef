// The coordinator of a capture on several hosts, and the control channel's messages.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <thread>

#include "core/check_option.h"
#include "core/error.h"
#include "core/output.h"
#include "distributed/internal/capture_control_channel.h"
#include "distributed/node.h"

namespace holocap {
namespace control {

int64_t RealtimeNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

NodeConnection::NodeConnection(zmq::context_t& context, const std::string& address)
    : socket_(context, zmq::socket_type::req) {
  socket_.set(zmq::sockopt::linger, 0);
  // A request left unanswered must not wedge the socket: the next one goes out anyway, and a
  // late reply to the old one is told apart and dropped.
  socket_.set(zmq::sockopt::req_relaxed, 1);
  socket_.set(zmq::sockopt::req_correlate, 1);
  try {
    socket_.connect(address);
  } catch (const zmq::error_t& e) {
    Fail("bad node address '", address, "': ", e.what());
  }
}

std::optional<nlohmann::json> NodeConnection::Call(const nlohmann::json& request, int timeout_ms) {
  socket_.set(zmq::sockopt::sndtimeo, timeout_ms);
  socket_.set(zmq::sockopt::rcvtimeo, timeout_ms);
  try {
    if (!socket_.send(zmq::buffer(request.dump()), zmq::send_flags::none)) return std::nullopt;
    zmq::message_t reply;
    if (!socket_.recv(reply, zmq::recv_flags::none)) return std::nullopt;
    return nlohmann::json::parse(reply.to_string());
  } catch (const std::exception&) {
    return std::nullopt;
  }
}

nlohmann::json StatusToJson(const RecorderStatus& status) {
  nlohmann::json sensors = nlohmann::json::array();
  for (const auto& sensor : status.sensors)
    sensors.push_back({{"name", sensor.name}, {"fps", sensor.fps}, {"dropped", sensor.dropped}});
  return {{"elapsed_s", status.elapsed_s},         {"frame_sets", status.frame_sets},
          {"write_mb_s", status.write_mb_s},       {"spread_us_last", status.spread_us_last},
          {"spread_us_max", status.spread_us_max}, {"sensors", sensors}};
}

nlohmann::json SummaryToJson(const RecorderSummary& summary) {
  return {{"termination", ToString(summary.termination)},
          {"message", summary.message},
          {"usable", summary.IsUsable()},
          {"metrics", summary.Metrics()}};
}

nlohmann::json RecorderOptionsToJson(const RecorderOptions& o) {
  return {{"frames", o.frames},
          {"seconds", o.seconds},
          {"queue_frames", o.queue_frames},
          {"queue_sets", o.queue_sets},
          {"writer_threads", o.writer_threads},
          {"warmup_s", o.warmup_s},
          {"drain_s", o.drain_s},
          {"lost_after_periods", o.lost_after_periods},
          {"first_frame_s", o.first_frame_s},
          {"codec", o.codec},
          {"sync_tolerance_ns", o.sync_tolerance_ns},
          {"trigger_priority", o.trigger_priority},
          {"trigger_phase_s", o.trigger_phase_s},
          {"first_trigger_realtime_ns", o.first_trigger_realtime_ns},
          {"durable", o.take.durable},
          {"overwrite", o.take.overwrite}};
}

RecorderOptions RecorderOptionsFromJson(const nlohmann::json& json) {
  RecorderOptions o;
  o.frames = json.value("frames", o.frames);
  o.seconds = json.value("seconds", o.seconds);
  o.queue_frames = json.value("queue_frames", o.queue_frames);
  o.queue_sets = json.value("queue_sets", o.queue_sets);
  o.writer_threads = json.value("writer_threads", o.writer_threads);
  o.warmup_s = json.value("warmup_s", o.warmup_s);
  o.drain_s = json.value("drain_s", o.drain_s);
  o.lost_after_periods = json.value("lost_after_periods", o.lost_after_periods);
  o.first_frame_s = json.value("first_frame_s", o.first_frame_s);
  o.codec = json.value("codec", o.codec);
  o.sync_tolerance_ns = json.value("sync_tolerance_ns", o.sync_tolerance_ns);
  o.trigger_priority = json.value("trigger_priority", o.trigger_priority);
  o.trigger_phase_s = json.value("trigger_phase_s", o.trigger_phase_s);
  o.first_trigger_realtime_ns =
      json.value("first_trigger_realtime_ns", o.first_trigger_realtime_ns);
  o.take.durable = json.value("durable", o.take.durable);
  o.take.overwrite = json.value("overwrite", o.take.overwrite);
  return o;
}

}  // namespace control

void NodeCaptureOptions::Check() const {
  HOLOCAP_CHECK_OPTION(!out.empty(), out, "the take to write");
  HOLOCAP_CHECK_OPTION_GE(frames, 0);
  HOLOCAP_CHECK_OPTION_GE(seconds, 0);
  HOLOCAP_CHECK_OPTION(std::isfinite(seconds), seconds);
  HOLOCAP_CHECK_OPTION(frames != 0 || seconds != 0, frames, "give a frame count or a duration");
  HOLOCAP_CHECK_OPTION_GT(reply_timeout_s, 0);
  HOLOCAP_CHECK_OPTION_GT(start_lead_s, 0);
  HOLOCAP_CHECK_OPTION_GE(max_clock_offset_us, 0);
  HOLOCAP_CHECK_OPTION_IN(clock_probes, 1, 1000);
  HOLOCAP_CHECK_OPTION_GT(status_every_s, 0);
  merge.Check();
}

nlohmann::json NodeRecord::ToJson() const {
  return {{"name", name},
          {"address", address},
          {"state", state},
          {"message", message},
          {"clock", clock.ToJson()},
          {"part", part.string()},
          {"last_answer_s", last_answer_s},
          {"last_frame_sets", last_frame_sets},
          {"summary", summary}};
}

nlohmann::json NodeCaptureSummary::Metrics() const {
  nlohmann::json nodes_json = nlohmann::json::array();
  for (const auto& node : nodes) nodes_json.push_back(node.ToJson());
  return {{"nodes", nodes_json},
          {"merged", merged},
          {"merge", merged ? merge.Metrics() : nlohmann::json(nullptr)},
          {"merge_termination", ToString(merge.termination)},
          {"merge_message", merge.message}};
}

namespace {

using SteadyClock = std::chrono::steady_clock;

// One capture on several nodes as named steps; state in members.
class Coordinator {
 public:
  Coordinator(const RigDescription& rig, const NodeCaptureOptions& options,
              const std::atomic<bool>& stop,
              const std::function<void(const NodeCaptureStatus&)>& on_status, Report* report)
      : rig_(rig), options_(options), stop_(stop), on_status_(on_status), report_(report) {
    if (options_.parts.empty()) options_.parts = options_.out.string() + ".parts";
    options_.parts = std::filesystem::absolute(options_.parts);
    timeout_ms_ = static_cast<int>(std::lround(options_.reply_timeout_s * 1e3));
    frames_ = options_.frames > 0 ? options_.frames
                                  : static_cast<int64_t>(std::llround(options_.seconds * rig.fps));
  }

  NodeCaptureSummary Run() {
    if (rig_.hosts.empty()) Fail("capture: the rig names no hosts (a one-machine rig)");
    // Refused before any node records (the merge claims it again when it writes).
    ClaimTakeDirectory(options_.out, {"capture", options_.merge.overwrite, {}});
    Connect();
    ProbeClocks();
    StartNodes();
    Watch();
    Collect();
    MergeParts();
    Conclude();
    return summary_;
  }

 private:
  struct Node {
    NodeRecord record;
    std::unique_ptr<control::NodeConnection> connection;
    RigDescription part_rig;
    bool running = false;
  };

  double Elapsed() const {
    return std::chrono::duration<double>(SteadyClock::now() - start_).count();
  }

  void Connect() {
    for (const auto& [host, address] : rig_.hosts) {
      Node node;
      node.record.name = host;
      node.record.address = address;
      node.part_rig = rig_;
      node.part_rig.sensors.clear();
      for (const auto& spec : rig_.sensors)
        if (spec.host == host) node.part_rig.sensors.push_back(spec);
      node.connection = std::make_unique<control::NodeConnection>(context_, address);
      if (node.part_rig.sensors.empty()) {
        node.record.state = "unused";
        node.record.message = "no sensor of the rig names it";
      } else if (auto hello = node.connection->Call({{"cmd", "hello"}}, timeout_ms_)) {
        node.record.clock.daemon =
            ClockState::FromJson(hello->value("clock", nlohmann::json::object()));
        if (hello->value("busy", false)) {
          node.record.state = "refused";
          node.record.message = Cat("node at ", address, " is recording another take");
        } else {
          node.record.state = "answered";
        }
      } else {
        node.record.message =
            Cat("no answer from ", address, " within ", options_.reply_timeout_s, " s");
      }
      nodes_.push_back(std::move(node));
    }
  }

  void ProbeClocks() {
    for (Node& node : nodes_) {
      if (node.record.state != "answered") continue;
      NodeClock& clock = node.record.clock;
      clock.channel_rtt_ns = INT64_MAX;
      for (int i = 0; i < options_.clock_probes; ++i) {
        const int64_t sent = control::RealtimeNs();
        auto reply = node.connection->Call({{"cmd", "clock"}}, timeout_ms_);
        const int64_t received = control::RealtimeNs();
        if (!reply) continue;
        const int64_t rtt = received - sent;
        if (rtt < clock.channel_rtt_ns) {
          clock.channel_rtt_ns = rtt;
          clock.channel_offset_ns = reply->value("realtime_ns", int64_t{0}) - (sent + rtt / 2);
        }
      }
      if (clock.channel_rtt_ns == INT64_MAX) {
        node.record.state = "unreachable";
        node.record.message = "answered hello but no clock request";
        continue;
      }
      const ClockState& daemon = clock.daemon;
      if (daemon.synchronised && (daemon.source == "ptp" || daemon.source == "chrony")) {
        clock.offset_ns = daemon.offset_ns;
        clock.uncertainty_ns = std::max<int64_t>(daemon.error_ns, 0);
        clock.offset_source = daemon.source;
      } else {
        clock.offset_ns = clock.channel_offset_ns;
        clock.uncertainty_ns = clock.channel_rtt_ns / 2;
        clock.offset_source = "control-channel";
      }
      const int64_t worst = std::llabs(clock.offset_ns) + clock.uncertainty_ns;
      if (worst > options_.max_clock_offset_us * 1000) {
        node.record.state = "clock";
        node.record.message =
            Cat("clock offset ", clock.offset_ns / 1e3, " us (", clock.offset_source, ", +- ",
                clock.uncertainty_ns / 1e3, " us) exceeds the bound of ",
                options_.max_clock_offset_us, " us");
      }
    }
  }

  void StartNodes() {
    const int64_t period_ns = static_cast<int64_t>(std::llround(1e9 / rig_.fps));
    const int64_t lead_ns = static_cast<int64_t>(options_.start_lead_s * 1e9);
    first_trigger_ns_ = (control::RealtimeNs() + lead_ns + period_ns - 1) / period_ns * period_ns;
    start_ = SteadyClock::now();
    for (Node& node : nodes_) {
      if (node.record.state != "answered") continue;
      RecorderOptions recorder = options_.recorder;
      recorder.frames = frames_;
      recorder.seconds = 0;
      recorder.first_trigger_realtime_ns = first_trigger_ns_ + node.record.clock.offset_ns;
      node.record.part = options_.parts / node.record.name;
      nlohmann::json request = {{"cmd", "start"},
                                {"rig", node.part_rig.ToJson()},
                                {"part", node.record.part.string()},
                                {"options", control::RecorderOptionsToJson(recorder)},
                                {"clock", node.record.clock.ToJson()}};
      auto reply = node.connection->Call(request, static_cast<int>(lead_ns / 1000000));
      if (!reply) {
        node.record.state = "unreachable";
        node.record.message =
            Cat("no answer to the start request within ", options_.start_lead_s, " s");
      } else if (!reply->value("ok", false)) {
        node.record.state = "refused";
        node.record.message = Cat("could not start: ", reply->value("error", std::string()));
      } else {
        node.record.state = "recording";
        node.record.part = reply->value("part", node.record.part.string());
        node.record.last_answer_s = Elapsed();
        node.running = true;
      }
    }
  }

  NodeCaptureStatus::PerNode Poll(Node& node) {
    NodeCaptureStatus::PerNode line;
    line.name = node.record.name;
    line.frame_sets = node.record.last_frame_sets;
    auto reply = node.connection->Call({{"cmd", "status"}}, timeout_ms_);
    if (!reply || !reply->value("ok", false)) {
      line.answering = false;
      node.running = false;
      node.record.state = "lost";
      node.record.message =
          Cat("stopped answering mid-take: no status within ", options_.reply_timeout_s, " s, ",
              Elapsed() - node.record.last_answer_s, " s after its last answer (",
              node.record.last_frame_sets, " frame sets then)");
      return line;
    }
    node.record.last_answer_s = Elapsed();
    const nlohmann::json status = reply->value("status", nlohmann::json::object());
    line.frame_sets = node.record.last_frame_sets = status.value("frame_sets", int64_t{0});
    line.write_mb_s = status.value("write_mb_s", 0.0);
    line.spread_us_last = status.value("spread_us_last", 0.0);
    const nlohmann::json sensors = status.value("sensors", nlohmann::json::array());
    for (const auto& sensor : sensors) {
      line.fps += sensor.value("fps", 0.0) / sensors.size();
      line.dropped += sensor.value("dropped", int64_t{0});
    }
    if (reply->value("done", false)) node.running = false;
    return line;
  }

  void Watch() {
    bool stop_sent = false;
    int64_t poll = 0;
    while (std::any_of(nodes_.begin(), nodes_.end(), [](const Node& n) { return n.running; })) {
      if (stop_ && !stop_sent) {
        for (Node& node : nodes_)
          if (node.running) node.connection->Call({{"cmd", "stop"}}, timeout_ms_);
        stop_sent = true;
      }
      std::this_thread::sleep_for(std::chrono::duration<double>(options_.status_every_s));
      NodeCaptureStatus status;
      status.elapsed_s = Elapsed();
      for (Node& node : nodes_) {
        if (!node.running) continue;
        status.nodes.push_back(Poll(node));
        if (report_ != nullptr) {
          report_->AddPoint(node.record.name + ".frame_sets",
                            static_cast<double>(status.nodes.back().frame_sets), poll);
          report_->AddPoint(node.record.name + ".dropped",
                            static_cast<double>(status.nodes.back().dropped), poll);
        }
      }
      ++poll;
      if (on_status_) on_status_(status);
    }
  }

  void Collect() {
    for (Node& node : nodes_) {
      if (node.record.state != "recording") continue;
      auto reply = node.connection->Call({{"cmd", "result"}}, timeout_ms_);
      if (!reply || !reply->value("done", false)) {
        node.record.state = "lost";
        node.record.message = "no result after its take ended";
        continue;
      }
      const nlohmann::json summary = reply->value("summary", nlohmann::json::object());
      node.record.summary = summary.value("metrics", nlohmann::json::object());
      if (summary.value("usable", false)) {
        node.record.state = "recorded";
      } else {
        node.record.state = "failed";
        node.record.message = summary.value("message", std::string("its recorder failed"));
      }
    }
  }

  void MergeParts() {
    std::vector<std::filesystem::path> parts;
    std::string elsewhere;
    for (const Node& node : nodes_) {
      if (node.record.part.empty()) continue;
      if (std::filesystem::exists(node.record.part / "take.json")) {
        parts.push_back(node.record.part);
      } else if (node.record.state == "recorded") {
        // On the node's own disk (capture-node --root): a merge here would lack its sensors.
        elsewhere += Cat(elsewhere.empty() ? "" : ", ", node.record.name, " (",
                         node.record.part.string(), ")");
      }
    }
    if (!elsewhere.empty()) {
      summary_.merge.message = Cat("the parts of ", elsewhere,
                                   " are not visible here: copy them beside the others and run "
                                   "holocap merge");
      return;
    }
    if (parts.empty()) {
      summary_.merge.message = "no node recorded a part";
      return;
    }
    try {
      summary_.merge = holocap::MergeParts(parts, options_.out, options_.merge, report_);
      summary_.merged = true;
    } catch (const Error& e) {
      summary_.merge.message = e.what();
    }
  }

  void Conclude() {
    std::string problems;
    for (const Node& node : nodes_) {
      summary_.nodes.push_back(node.record);
      if (node.record.state == "recorded" || node.record.state == "unused") continue;
      problems += Cat(problems.empty() ? "" : "; ", "node '", node.record.name, "' (",
                      node.record.address, ") ", node.record.state, ": ", node.record.message);
    }
    if (!summary_.merged) {
      summary_.End(Termination::kFailure, Cat(problems, problems.empty() ? "" : "; ",
                                              "no merged take: ", summary_.merge.message));
    } else if (!problems.empty()) {
      summary_.End(Termination::kFailure, Cat(problems, "; ", summary_.merge.message));
    } else {
      summary_.End(summary_.merge.termination, summary_.merge.message);
    }
  }

  RigDescription rig_;
  NodeCaptureOptions options_;
  const std::atomic<bool>& stop_;
  std::function<void(const NodeCaptureStatus&)> on_status_;
  Report* report_;
  zmq::context_t context_{1};
  std::vector<Node> nodes_;
  int timeout_ms_ = 2000;
  int64_t frames_ = 0;
  int64_t first_trigger_ns_ = 0;
  SteadyClock::time_point start_ = SteadyClock::now();
  NodeCaptureSummary summary_;
};

}  // namespace

NodeCaptureSummary CaptureOnNodes(const RigDescription& rig, const NodeCaptureOptions& options,
                                  const std::atomic<bool>& stop,
                                  const std::function<void(const NodeCaptureStatus&)>& on_status,
                                  Report* report) {
  options.Check();
  rig.Check();
  return Coordinator(rig, options, stop, on_status, report).Run();
}

}  // namespace holocap
