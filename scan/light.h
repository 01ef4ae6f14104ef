// The light a scan was seen in, and the scan's colours with it divided out (albedo).
//
// A subject turning before a fixed sensor is lit by the room, which does not turn with it: a
// patch of skin is brighter when it faces the lamp than when it faces away, and a scan's fused
// colours hold whichever shading the sensor saw (the side facing the sensor, mostly). Composed
// into a view from behind, those colours are the front's light on the back. Each patch is seen
// under several orientations as the subject turns, so the ratios of its intensities tell the
// light apart from its albedo: a Lambertian ambient + directional model,
//   shading(n) = 1 + max(0, n . light),
// with n the unit normal in the depth sensor's camera frame and `light` the directional light's
// direction times its strength relative to the ambient, is fitted to the log intensities of
// every patch seen at least twice (each patch's albedo eliminated), and each vertex's albedo is
// its colours over the shading they were seen in. Colours are taken as linear in the light.
//
// A sensor circling a still subject sees each patch under one light only: the fit then finds
// no light that explains the intensities better than none, and says so (`observed` false,
// albedo = the colours as seen).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/mesh.h"

namespace holocap {

struct ScanLight {
  bool observed = false;  // a directional light explains the intensities (see above)
  Eigen::Vector3d light = Eigen::Vector3d::Zero();  // in the depth sensor's camera frame
  int64_t views = 0;                                // colour frames read
  int64_t vertices = 0;      // vertices fitted (seen at least twice, off the floor)
  int64_t observations = 0;  // their sightings
  double rms_flat = 0;       // RMS of the log-intensity residuals under ambient light alone
  double rms_lit = 0;        // ... under the fitted light
  std::string why;           // not observed: the reason

  // The shading of a unit normal given in the depth sensor's camera frame (>= 1).
  double Shading(const Eigen::Vector3d& normal_in_sensor) const {
    return 1 + std::max(0.0, normal_in_sensor.dot(light));
  }
  nlohmann::json ToJson() const;
  static ScanLight FromJson(const nlohmann::json& json);  // throws Error when malformed
};

// One colour frame of the scan: its camera (posed in the scan's world), the depth sensor's
// rotation cam_from_world at that frame, and the image (CV_8UC3 BGR).
struct LitView {
  CameraModel camera;
  Eigen::Matrix3d sensor_from_world = Eigen::Matrix3d::Identity();
  cv::Mat bgr;
};

struct ScanLightOptions {
  int64_t max_fit_vertices = 30000;  // vertices sampled evenly for the fit
  double min_cos_view = 0.25;        // sightings more grazing than this are not used
  double depth_tolerance_m = 0.01;   // a vertex is seen where the mesh's own depth is its depth
  double min_intensity = 0.03;       // darker or saturated sightings are not used
  double max_intensity = 0.97;
  // The light is `observed` when it lowers the RMS of the log residuals by this fraction.
  double min_improvement = 0.05;
  double min_strength = 0.1;  // ... and is at least this strong
  int64_t min_vertices = 200;
};

// Fits the light to the views of `mesh` (with normals) and returns it; `albedo` receives the
// mesh with every vertex's albedo as its colour (a vertex no view sees keeps its colour divided
// by the median shading of the sightings). `fit[v]` false leaves vertex v out of the fit (the
// floor, which does not turn with the subject).
ScanLight EstimateScanLight(const Mesh& mesh, const std::vector<LitView>& views,
                            const std::vector<bool>& fit, const ScanLightOptions& options,
                            Mesh* albedo);

}  // namespace holocap
