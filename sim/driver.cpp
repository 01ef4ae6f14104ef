// The sim: HAL driver: sensors of the simulated rigs, rendering on demand.
#include <map>
#include <memory>
#include <mutex>

#include "core/error.h"
#include "sim/sim.h"
#include "sim/world.h"

namespace holocap {
namespace {

using Json = nlohmann::json;

template <typename T>
T Option(const Json& options, const char* key, T fallback, const std::string& uri) {
  if (!options.contains(key) || options[key].is_null()) return fallback;
  try {
    return options[key].get<T>();
  } catch (const Json::exception&) {
    Fail(uri, ": sim option '", key, "' has the wrong type (", options[key].dump(), ")");
  }
}

// Sensors opened with the same rig and settings share one world, so they see one scene.
std::shared_ptr<sim::SimWorld> SharedWorld(const SimOptions& options) {
  static std::mutex mutex;
  static std::map<std::string, std::weak_ptr<sim::SimWorld>> worlds;
  const std::string key = options.ToJson().dump();
  std::lock_guard lock(mutex);
  if (auto world = worlds[key].lock()) return world;
  auto world = std::make_shared<sim::SimWorld>(options);
  worlds[key] = world;
  return world;
}

class SimSensor : public Sensor {
 public:
  SimSensor(std::shared_ptr<sim::SimWorld> world, int index, int64_t frames)
      : world_(std::move(world)),
        index_(index),
        frames_(frames),
        stream_(world_->sensor(index).stream) {}

  const StreamInfo& stream() const override { return stream_; }
  void Start() override { started_ = true; }
  void Stop() override { started_ = false; }
  bool ended() const override { return ended_; }
  std::optional<CameraModel> known_model() const override { return world_->sensor(index_).model; }
  bool known_model_is_truth() const override { return true; }

  bool Grab(Frame* frame, std::chrono::milliseconds timeout) override {
    if (!started_ || ended_) return false;
    // A dropped frame never arrives: its sequence number is skipped.
    while (frames_ <= 0 || next_ < frames_) {
      const int64_t set = next_++;
      if (world_->Dropped(index_, set)) continue;
      const sim::SensorFrame rendered = world_->Render(index_, set, world_->options().threads);
      frame->sensor = stream_.name;
      frame->image = rendered.image;
      frame->timestamp_ns = rendered.timestamp_ns;
      frame->sequence = static_cast<uint64_t>(set);
      return true;
    }
    ended_ = true;
    return false;
  }

 private:
  std::shared_ptr<sim::SimWorld> world_;
  int index_;
  int64_t frames_;
  StreamInfo stream_;
  int64_t next_ = 0;
  bool started_ = false;
  bool ended_ = false;
};

class SimDriver : public Driver {
 public:
  std::string scheme() const override { return "sim"; }
  std::string description() const override {
    return "simulated rigs (studio8, single-rgbd, sim rig files) with exact lenses, poses and "
           "clocks";
  }

  std::vector<DeviceInfo> Enumerate() override {
    std::vector<DeviceInfo> devices;
    for (const std::string& name : BuiltinRigNames()) {
      const RigDescription rig = BuiltinRig(name);
      for (const SensorSpec& sensor : rig.sensors) {
        const CameraModel model = SimSensorModel(rig, sensor);
        devices.push_back({sensor.uri,
                           Cat(name, " ", sensor.name, ": simulated ", ToString(sensor.role), " ",
                               model.width(), "x", model.height(), " ", model.lensmodel()),
                           sensor.role});
      }
    }
    return devices;
  }

  std::unique_ptr<Sensor> Open(const SensorSpec& spec) override {
    const ParsedUri uri = ParseSensorUri(spec.uri);
    if (uri.path.empty() || uri.fragment.empty()) {
      Fail("sim URI '", spec.uri, "' must be sim:<rig>#<sensor>, e.g. sim:studio8#cam3");
    }
    const Json& o = spec.options;
    SimOptions options;
    options.rig = uri.path;
    options.scene = Option<std::string>(o, "scene", options.scene, spec.uri);
    options.seed = Option<uint64_t>(o, "seed", options.seed, spec.uri);
    options.image_width = Option<int>(o, "width", options.image_width, spec.uri);
    options.image_height = Option<int>(o, "height", options.image_height, spec.uri);
    options.noise = Option<bool>(o, "noise", options.noise, spec.uri);
    options.antialias = Option<int>(o, "antialias", options.antialias, spec.uri);
    options.drop_probability = Option<double>(o, "drop", options.drop_probability, spec.uri);
    const int64_t frames = Option<int64_t>(o, "frames", 0, spec.uri);
    if (frames < 0) Fail(spec.uri, ": sim option 'frames' must be >= 0 (0: endless)");
    std::shared_ptr<sim::SimWorld> world;
    try {
      world = SharedWorld(options);
    } catch (const Error& e) {
      Fail(spec.uri, ": ", e.what());
    }
    const int index = world->IndexOf(uri.fragment);
    if (index < 0) {
      std::string known;
      for (int i = 0; i < world->size(); ++i) known += (i ? ", " : "") + world->sensor(i).spec.name;
      Fail("sim URI '", spec.uri, "': rig '", world->rig().name, "' has no sensor '", uri.fragment,
           "' (sensors: ", known, ")");
    }
    return std::make_unique<SimSensor>(std::move(world), index, frames);
  }
};

}  // namespace

void RegisterSimDriver(DriverRegistry& registry) {
  registry.Register(std::make_unique<SimDriver>());
}

}  // namespace holocap
