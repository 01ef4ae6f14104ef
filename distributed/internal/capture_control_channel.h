// The control channel's pieces shared by the node (node.cpp) and the coordinator
// (capture_control.cpp): JSON messages over ZeroMQ request/reply sockets.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <zmq.hpp>

#include "capture/recorder.h"

namespace holocap::control {

// CLOCK_REALTIME now, in ns.
int64_t RealtimeNs();

// A request socket to one node. A request not answered within the timeout returns nullopt and
// leaves the socket ready for the next one (a node that comes back answers again).
class NodeConnection {
 public:
  NodeConnection(zmq::context_t& context, const std::string& address);
  std::optional<nlohmann::json> Call(const nlohmann::json& request, int timeout_ms);

 private:
  zmq::socket_t socket_;
};

// The recorder's live status and summary as the channel carries them.
nlohmann::json StatusToJson(const RecorderStatus& status);
nlohmann::json SummaryToJson(const RecorderSummary& summary);

// The fields of RecorderOptions a coordinator sets on its nodes.
nlohmann::json RecorderOptionsToJson(const RecorderOptions& options);
RecorderOptions RecorderOptionsFromJson(const nlohmann::json& json);

}  // namespace holocap::control
