// The built-in simulated rigs and the sensor models of sim rig files.
#include <cmath>
#include <numbers>

#include "core/error.h"
#include "sim/sim.h"

namespace holocap {
namespace {

using Json = nlohmann::json;

// The real wide-angle lens of shared/data/lenses/wide-4000x2200.opencv8.cameramodel (an mrcal
// LENSMODEL_OPENCV8 calibration of a 4000x2200 camera), embedded so that the rig needs no data
// files at run time. studio8's cam0 uses it rescaled to 640 px across (640x352).
constexpr int kWideLensWidth = 4000;
constexpr int kWideLensHeight = 2200;
const std::vector<double> kWideLensIntrinsics = {
    1761.181055,      1761.250444,     1965.706996,   1087.518797,   -0.01266096516, 0.03590794372,
    -0.0002547045941, 0.0005275929652, 0.01968883397, 0.01482863541, -0.0562239888,  0.0500223357};

Json ColorCamera(const std::string& rig, const std::string& name, const std::string& lens,
                 const std::vector<double>& intrinsics, int width, int height,
                 const Eigen::Vector3d& position, const Eigen::Vector3d& look_at) {
  return {{"name", name},
          {"uri", "sim:" + rig + "#" + name},
          {"role", "color"},
          {"options",
           {{"lens", lens},
            {"intrinsics", intrinsics},
            {"size", {width, height}},
            {"position", {position.x(), position.y(), position.z()}},
            {"look_at", {look_at.x(), look_at.y(), look_at.z()}}}}};
}

Json DepthCamera(const std::string& rig, const std::string& name, const std::string& paired_with,
                 const std::vector<double>& intrinsics, const Rt& depth_from_color) {
  return {{"name", name},
          {"uri", "sim:" + rig + "#" + name},
          {"role", "depth"},
          {"paired_with", paired_with},
          {"options",
           {{"lens", "LENSMODEL_OPENCV4"},
            {"intrinsics", intrinsics},
            {"size", {640, 480}},
            {"depth_from_color", depth_from_color}}}};
}

RigDescription Studio8() {
  const std::string rig = "studio8";
  Json sensors = Json::array();
  const CameraModel wide =
      CameraModel("LENSMODEL_OPENCV8", kWideLensIntrinsics, kWideLensWidth, kWideLensHeight)
          .Scaled(640.0 / kWideLensWidth);
  struct Lens {
    std::string model;
    std::vector<double> intrinsics;
    int width, height;
  };
  const std::vector<Lens> lenses = {
      {"LENSMODEL_OPENCV8", wide.intrinsics(), wide.width(), wide.height()},
      // Stereographic r = 2 f tan(theta / 2): 112 degrees across 640 px.
      {"LENSMODEL_STEREOGRAPHIC", {300.0, 300.0, 318.2, 241.1}, 640, 480},
      {"LENSMODEL_OPENCV4", {520.3, 519.1, 322.4, 236.9, -0.082, 0.031, 0.0006, -0.0004}, 640, 480},
      {"LENSMODEL_OPENCV5",
       {561.7, 560.2, 316.8, 243.5, -0.121, 0.094, -0.0003, 0.0007, -0.021},
       640,
       480},
      {"LENSMODEL_OPENCV8",
       {498.6, 499.4, 321.0, 238.2, 0.35, -0.05, 0.0004, 0.0002, 0.01, 0.42, -0.02, 0.015},
       640,
       480},
      {"LENSMODEL_OPENCV4", {612.5, 611.8, 318.9, 240.7, -0.05, 0.012, 0.0002, 0.0001}, 640, 480},
      {"LENSMODEL_OPENCV5",
       {478.9, 479.6, 320.3, 239.0, -0.15, 0.11, 0.0005, -0.0002, -0.03},
       640,
       480},
      {"LENSMODEL_OPENCV8",
       {541.2, 540.5, 317.5, 242.8, -0.2, 0.05, -0.0003, 0.0004, 0.0, 0.1, 0.02, 0.0},
       640,
       480},
  };
  for (int i = 0; i < 8; ++i) {
    const double azimuth = (22.5 + 45.0 * i) * std::numbers::pi / 180;
    const double radius = 3.0 + 0.1 * (i % 3);
    const double height = i % 2 == 0 ? 1.45 : 2.1;
    const Eigen::Vector3d position(radius * std::cos(azimuth), radius * std::sin(azimuth), height);
    const Eigen::Vector3d look_at(0.05 * std::sin(3.0 * i), 0.05 * std::cos(3.0 * i),
                                  i % 2 == 0 ? 1.0 : 0.9);
    const Lens& lens = lenses[i];
    sensors.push_back(ColorCamera(rig, "cam" + std::to_string(i), lens.model, lens.intrinsics,
                                  lens.width, lens.height, position, look_at));
    // The wide stereographic lens is calibrated with the splined model (knots every ~17 degrees).
    if (lens.model == "LENSMODEL_STEREOGRAPHIC") {
      sensors.back()["options"]["calib_lensmodel"] =
          "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=8_Ny=6_fov_x_deg=120";
    }
  }
  sensors.push_back(DepthCamera(rig, "depth0", "cam2",
                                {570.3, 570.9, 319.2, 241.6, 0.01, -0.02, 0.0002, -0.0001},
                                {0.003, -0.004, 0.002, -0.025, 0.0005, 0.001}));
  sensors.push_back(DepthCamera(rig, "depth1", "cam6",
                                {568.1, 567.4, 322.0, 238.8, 0.015, -0.025, -0.0001, 0.0002},
                                {-0.002, 0.003, -0.001, -0.026, -0.0004, 0.0012}));
  return RigDescription::FromJson(
      {{"name", rig}, {"sync", "hardware"}, {"fps", 30}, {"sensors", sensors}}, rig);
}

RigDescription SingleRgbd() {
  const std::string rig = "single-rgbd";
  Json sensors = Json::array();
  sensors.push_back(ColorCamera(rig, "cam0", "LENSMODEL_OPENCV5",
                                {535.4, 534.8, 320.6, 238.3, 0.08, -0.18, 0.0004, -0.0002, 0.09},
                                640, 480, Eigen::Vector3d(2.4, -1.3, 1.15),
                                Eigen::Vector3d(0, 0, 0.95)));
  sensors.push_back(DepthCamera(rig, "depth0", "cam0",
                                {570.3, 570.9, 319.2, 241.6, 0.01, -0.02, 0.0002, -0.0001},
                                {0.0015, -0.002, 0.001, -0.045, 0.0002, 0.0008}));
  return RigDescription::FromJson(
      {{"name", rig}, {"sync", "hardware"}, {"fps", 30}, {"sensors", sensors}}, rig);
}

// `count` pinhole colour cameras (800x800, 40 degrees across) spread evenly over the sphere of
// radius 2 m around the object scene's knot, from 20 degrees below its equator to its top:
// lower, the pedestal and the floor hide the knot. Each looks at the sphere's centre, as the
// 100 views of an object capture spread over a dome do. They lie on one spiral from the
// bottom up (equal areas, steps of one spacing along it; Saff and Kuijlaars), so that
// consecutive cameras are neighbours: the board take's shared poses link them.
RigDescription Sphere(int count) {
  const std::string rig = Cat("sphere", count);
  const Eigen::Vector3d centre(0, 0, 1.0);
  const double radius = 2.0;
  const double focal = 400 / std::tan(20 * std::numbers::pi / 180);
  const double lowest = std::sin(-20 * std::numbers::pi / 180);  // of the elevation's sine
  // The spacing of `count` points on the cap, in radians of arc.
  const double spacing = std::sqrt(2 * std::numbers::pi * (1 - lowest) / count);
  Json sensors = Json::array();
  double azimuth = 0;
  for (int i = 0; i < count; ++i) {
    // Equal steps in the elevation's sine are equal areas of the sphere; never the very top,
    // where the view direction would be parallel to up.
    const double sine = lowest + (1 - lowest) * (i + 0.5) / count;
    const double cosine = std::sqrt(1 - sine * sine);
    if (i > 0) azimuth += spacing / std::max(cosine, spacing);
    const Eigen::Vector3d position =
        centre +
        radius * Eigen::Vector3d(cosine * std::cos(azimuth), cosine * std::sin(azimuth), sine);
    sensors.push_back(ColorCamera(rig, "cam" + std::to_string(i), "LENSMODEL_PINHOLE",
                                  {focal, focal, 399.5, 399.5}, 800, 800, position, centre));
  }
  return RigDescription::FromJson(
      {{"name", rig}, {"sync", "hardware"}, {"fps", 30}, {"sensors", sensors}}, rig);
}

// The N of a rig named sphereN (2 to 1000 cameras); 0 for any other name.
int SphereCount(const std::string& name) {
  if (name.rfind("sphere", 0) != 0 || name.size() == 6 || name.size() > 10) return 0;
  for (size_t i = 6; i < name.size(); ++i) {
    if (name[i] < '0' || name[i] > '9') return 0;
  }
  const int count = std::stoi(name.substr(6));
  return count >= 2 && count <= 1000 ? count : 0;
}

Eigen::Vector3d Vector3(const Json& options, const char* key, const std::string& where) {
  const Json& value = options.at(key);
  if (!value.is_array() || value.size() != 3) Fail(where, ": '", key, "' must be [x, y, z]");
  return Eigen::Vector3d(value[0].get<double>(), value[1].get<double>(), value[2].get<double>());
}

// The same lens rendered at width x height: scaled by the width ratio, then cropped or padded
// symmetrically in height.
CameraModel Resized(const CameraModel& model, int width, int height) {
  if (width <= 0 || width == model.width()) {
    if (height <= 0 || height == model.height()) return model;
  }
  CameraModel scaled = width > 0 ? model.Scaled(static_cast<double>(width) / model.width()) : model;
  if (height <= 0 || height == scaled.height()) return scaled;
  std::vector<double> intrinsics = scaled.intrinsics();
  intrinsics[3] += 0.5 * (height - scaled.height());
  return CameraModel(scaled.lensmodel(), intrinsics, scaled.width(), height,
                     scaled.cam_from_world());
}

}  // namespace

std::vector<std::string> BuiltinRigNames() { return {"studio8", "single-rgbd"}; }

RigDescription BuiltinRig(const std::string& name) {
  if (name == "studio8") return Studio8();
  if (name == "single-rgbd") return SingleRgbd();
  if (const int count = SphereCount(name); count > 0) return Sphere(count);
  Fail("unknown built-in sim rig '", name, "' (known: studio8, single-rgbd, sphereN)");
}

RigDescription LoadSimRig(const std::string& name_or_path) {
  for (const std::string& name : BuiltinRigNames()) {
    if (name == name_or_path) return BuiltinRig(name);
  }
  if (SphereCount(name_or_path) > 0) return Sphere(SphereCount(name_or_path));
  if (!std::filesystem::exists(name_or_path)) {
    Fail("sim rig '", name_or_path,
         "' is neither built in (studio8, single-rgbd, sphereN with N from 2 to 1000) nor a file");
  }
  return RigDescription::Load(name_or_path);
}

CameraModel SimSensorModel(const RigDescription& rig, const SensorSpec& sensor, int width,
                           int height, const std::filesystem::path& base_dir) {
  const std::string where = Cat("sim rig '", rig.name, "' sensor '", sensor.name, "'");
  const Json& options = sensor.options;
  try {
    CameraModel model;
    bool has_pose = false;
    if (options.contains("cameramodel")) {
      std::filesystem::path file = options.at("cameramodel").get<std::string>();
      if (file.is_relative() && !base_dir.empty()) file = base_dir / file;
      model = CameraModel::Read(file);
      has_pose = true;
    } else {
      for (const char* key : {"lens", "intrinsics", "size"}) {
        if (!options.contains(key)) Fail(where, ": options need '", key, "' (or 'cameramodel')");
      }
      const Json& size = options.at("size");
      if (!size.is_array() || size.size() != 2) Fail(where, ": 'size' must be [width, height]");
      model = CameraModel(options.at("lens").get<std::string>(),
                          options.at("intrinsics").get<std::vector<double>>(), size[0].get<int>(),
                          size[1].get<int>());
    }
    if (options.contains("depth_from_color")) {
      if (sensor.paired_with.empty()) {
        Fail(where, ": 'depth_from_color' needs paired_with to name the colour sensor");
      }
      const Rt rt = options.at("depth_from_color").get<Rt>();
      const CameraModel color = SimSensorModel(rig, rig.sensor(sensor.paired_with), 0, 0, base_dir);
      model.set_cam_from_world(PoseFromRt(rt) * color.cam_from_world());
    } else if (options.contains("position")) {
      if (!options.contains("look_at")) Fail(where, ": 'position' needs 'look_at'");
      model.set_cam_from_world(CamFromWorldLookAt(Vector3(options, "position", where),
                                                  Vector3(options, "look_at", where)));
    } else if (!has_pose) {
      Fail(where, ": options need 'position' and 'look_at' (or 'depth_from_color')");
    }
    return Resized(model, width, height);
  } catch (const Json::exception& e) {
    Fail(where, ": ", e.what());
  }
}

}  // namespace holocap
