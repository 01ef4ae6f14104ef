// Capture on several hosts: each capture host runs a node (`holocap capture-node`) that records
// its own sensors with the recorder (capture/recorder.h) into its own part of the take; a
// coordinator (`holocap capture --rig` on a rig whose sensors name hosts) starts, watches and
// stops the nodes over a ZeroMQ request/reply control channel, then merges the parts into one
// take (distributed/merge.h).
//
//   coordinator ──REQ──► node A (REP, tcp://hostA:5601) ─► Recorder ─► PARTS/A (a take)
//               ──REQ──► node B (REP, tcp://hostB:5601) ─► Recorder ─► PARTS/B (a take)
//               merge(PARTS/A, PARTS/B) ─► TAKE
//
// Every message is one JSON object; every request gets one reply {"ok": bool, "error": ...}.
//   hello                   -> node name, host name, pid, busy, the host's clock state
//   clock                   -> the node's CLOCK_REALTIME (the coordinator's offset probe)
//   start {rig, part, ...}  -> opens the sensors, records in the background
//   status                  -> live per-sensor fps, drops, sync spread, sets written
//   stop                    -> asks the recorder to end the take early
//   result                  -> done or not; the recorder's summary once done
//
// Clocks. Software triggers fire on CLOCK_REALTIME, so nodes whose clocks agree trigger their
// cameras together; each node's offset to the coordinator is measured over the channel (the
// reply with the shortest round trip, uncertainty half of it), and its time daemon's own state
// is read: PTP (ptp4l/phc2sys running: `pmc`'s master offset), chrony (`chronyc tracking`), or
// the kernel's NTP discipline (adjtimex) otherwise. A synchronised daemon's offset corrects the
// node's timestamps; otherwise the channel's. A node whose offset (plus its uncertainty)
// exceeds the bound is left out and named.
#pragma once

#include <atomic>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "capture/recorder.h"
#include "core/report.h"
#include "core/rig.h"
#include "distributed/merge.h"

namespace holocap {

// What a host's time daemon says of its clock.
struct ClockState {
  std::string host;  // the host name
  // "ptp" (ptp4l or phc2sys running), "chrony" (chronyd running), "adjtimex" (the kernel's NTP
  // discipline, whoever drives it), "none" (nothing could be read).
  std::string source = "none";
  bool synchronised = false;  // the source says the clock follows its reference
  int64_t offset_ns = 0;      // this clock minus the reference, as the source last measured
  int64_t error_ns = -1;      // the source's error bound (adjtimex maxerror), -1: not given
  std::string detail;         // what was read, or why nothing could be

  nlohmann::json ToJson() const;
  static ClockState FromJson(const nlohmann::json& json);
};

// Reads this host's clock state: PTP where ptp4l/phc2sys run, else chrony where chronyd runs,
// else adjtimex. Never throws; what could not be read is said in `detail`.
ClockState ReadClockState();

// A node's clock against the coordinator's, and the offset its timestamps are corrected by.
struct NodeClock {
  ClockState daemon;              // the node host's own time daemon
  int64_t channel_offset_ns = 0;  // node CLOCK_REALTIME minus the coordinator's, measured
  int64_t channel_rtt_ns = 0;     // round trip of that measurement
  int64_t offset_ns = 0;          // what corrects its timestamps (see offset_source)
  int64_t uncertainty_ns = 0;     // how far offset_ns may be off
  std::string offset_source;      // "ptp", "chrony" (synchronised daemon) or "control-channel"

  nlohmann::json ToJson() const;
  static NodeClock FromJson(const nlohmann::json& json);
};

struct CaptureNodeOptions {
  std::string listen = "tcp://127.0.0.1:5601";  // ZeroMQ endpoint the node binds
  std::string name;                             // the node's name in replies ("": host name)
  // Where parts are written: "" writes each at the path the coordinator gives (a filesystem the
  // hosts share); otherwise under this folder, by the part's folder name.
  std::filesystem::path root;
  int max_takes = 0;  // exit after this many takes; 0: serve until SIGINT/SIGTERM

  void Check() const;  // throws Error explaining a bad value
};

// Serves the control channel until `stop` turns true (checked every 100 ms) or max_takes takes
// are recorded. `log` receives one line per event (start, end of a take). Throws Error when the
// endpoint cannot be bound.
void ServeCaptureNode(const CaptureNodeOptions& options, const std::atomic<bool>& stop,
                      const std::function<void(const std::string&)>& log = {});

struct NodeCaptureOptions {
  std::filesystem::path out;           // the merged take
  std::filesystem::path parts;         // where nodes write their parts ("": OUT.parts)
  int64_t frames = 0;                  // frame sets (triggers) per node; or
  double seconds = 0;                  // how long (frames = seconds x fps)
  double reply_timeout_s = 2;          // a node silent this long is declared lost (or unreachable)
  double start_lead_s = 3;             // from the start request to the first trigger on every node
  int64_t max_clock_offset_us = 1000;  // a node whose |offset| + uncertainty exceeds it is left out
  int clock_probes = 8;                // clock requests per node; the shortest round trip counts
  double status_every_s = 0.5;         // how often nodes are asked for their status
  RecorderOptions recorder;            // each node's recorder (frames, seconds, start: set here)
  MergeOptions merge;                  // how the parts are joined at the end

  void Check() const;  // throws Error explaining a bad value
};

// What happened to one node.
struct NodeRecord {
  std::string name;     // its host name in the rig
  std::string address;  // its control endpoint
  // "recorded", "unreachable", "clock" (offset beyond the bound), "refused" (start failed),
  // "lost" (stopped answering mid-take), "failed" (its recorder ended in failure).
  std::string state = "unreachable";
  std::string message;
  NodeClock clock;
  std::filesystem::path part;
  nlohmann::json summary = nlohmann::json::object();  // its recorder's metrics, once known
  double last_answer_s = -1;  // seconds after the start request of its last reply
  int64_t last_frame_sets = 0;

  nlohmann::json ToJson() const;
};

// Live numbers for a display.
struct NodeCaptureStatus {
  double elapsed_s = 0;
  struct PerNode {
    std::string name;
    bool answering = true;
    int64_t frame_sets = 0;
    double fps = 0;  // mean over its sensors
    int64_t dropped = 0;
    double spread_us_last = 0;
    double write_mb_s = 0;
  };
  std::vector<PerNode> nodes;
};

struct NodeCaptureSummary : Summary {
  std::vector<NodeRecord> nodes;
  MergeSummary merge;
  bool merged = false;  // the take at `out` was written

  nlohmann::json Metrics() const;
};

// Records a take from a rig whose sensors name their hosts. Returns SUCCESS only when every
// node recorded its part and the merge succeeded; a node that did not answer, was refused, was
// left out for its clock or was lost mid-take makes it FAILURE naming the node, with the other
// nodes' parts kept and merged. `stop` ends the take early on every node.
NodeCaptureSummary CaptureOnNodes(const RigDescription& rig, const NodeCaptureOptions& options,
                                  const std::atomic<bool>& stop,
                                  const std::function<void(const NodeCaptureStatus&)>& on_status,
                                  Report* report);

}  // namespace holocap
