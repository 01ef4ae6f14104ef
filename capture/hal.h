// The hardware-abstraction layer: drivers registered by URI scheme, each opening sensors that
// deliver timestamped frames. A simulated rig and a recorded take are drivers like any camera.
#pragma once

#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/rig.h"
#include "core/take.h"

namespace holocap {

// What a sensor knows about frames it lost before they reached Grab(). Drivers that cannot
// tell leave these at zero; the recorder also counts gaps in Frame::sequence.
struct SensorStats {
  uint64_t frames_delivered = 0;  // handed out by Grab()
  uint64_t frames_lost = 0;       // incomplete, timed out or overrun inside the driver
  nlohmann::json details = nlohmann::json::object();  // driver-specific (packets resent, PTP, ...)
};

// A sensor a driver can open, as `holocap devices` lists it.
struct DeviceInfo {
  std::string uri;          // what a rig file names it by
  std::string description;  // model, serial, resolution, ...
  SensorRole role = SensorRole::kColor;
};

class Sensor {
 public:
  virtual ~Sensor() = default;
  // How its frames are stored (size, pixel format, clock). Valid after opening.
  virtual const StreamInfo& stream() const = 0;
  virtual void Start() = 0;
  virtual void Stop() = 0;
  // Called instead of Stop() once the recorder has declared the sensor lost: let go of the
  // device without waiting for answers it may never give (a camera that was unplugged). The
  // default stops it.
  virtual void Abandon() { Stop(); }
  // Waits up to `timeout` for the next frame. Returns false on timeout or when the stream
  // has ended (see ended()). Throws Error when the device is lost.
  virtual bool Grab(Frame* frame, std::chrono::milliseconds timeout) = 0;
  // True once a finite source (a replayed take, a simulated sequence) has no more frames.
  virtual bool ended() const { return false; }
  // Software trigger, for sensors that support it.
  virtual bool supports_software_trigger() const { return false; }
  virtual void Trigger() {}
  // The exact lens and pose, where the driver knows them (simulation, replayed calibration).
  virtual std::optional<CameraModel> known_model() const { return std::nullopt; }
  // True when known_model() is a simulation's truth rather than a calibration: it may measure
  // or be used when asked for, never pass as a calibration (written into a take's calib/).
  virtual bool known_model_is_truth() const { return false; }
  // Counters since Start(). Thread-safe: the recorder reads them while Grab() runs.
  virtual SensorStats stats() const { return {}; }
};

class Driver {
 public:
  virtual ~Driver() = default;
  virtual std::string scheme() const = 0;  // "sim", "replay", "aravis", ...
  virtual std::string description() const = 0;
  // Sensors present now. May be empty; never throws for "no device".
  virtual std::vector<DeviceInfo> Enumerate() = 0;
  // Opens one sensor. Throws Error naming the URI when it cannot (unknown device, busy, ...).
  virtual std::unique_ptr<Sensor> Open(const SensorSpec& spec) = 0;
};

class DriverRegistry {
 public:
  // The process-wide registry; the CLI fills it with every driver compiled in.
  static DriverRegistry& Global();

  void Register(std::unique_ptr<Driver> driver);  // replaces a driver of the same scheme
  // Throws Error "unknown URI scheme 'x' in 'x:...' (known: ...)" for an unregistered scheme,
  // or "malformed sensor URI" when there is no scheme.
  Driver& ForUri(const std::string& uri);
  std::unique_ptr<Sensor> Open(const SensorSpec& spec);
  std::vector<Driver*> drivers() const;
  bool has(const std::string& scheme) const;

 private:
  std::map<std::string, std::unique_ptr<Driver>> drivers_;
};

// Splits "scheme:rest#fragment" (fragment optional). Throws Error for a missing scheme.
struct ParsedUri {
  std::string scheme;
  std::string path;
  std::string fragment;
};
ParsedUri ParseSensorUri(const std::string& uri);

}  // namespace holocap
