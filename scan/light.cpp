#include "scan/light.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>

#include "core/error.h"
#include "core/projector.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

using Json = nlohmann::json;

Json ScanLight::ToJson() const {
  return {{"model",
           "shading(n) = 1 + max(0, n . light), n in the depth sensor's camera frame; albedo = "
           "colour / shading"},
          {"observed", observed},
          {"light", {light.x(), light.y(), light.z()}},
          {"strength", light.norm()},
          {"views", views},
          {"vertices", vertices},
          {"observations", observations},
          {"rms_flat", rms_flat},
          {"rms_lit", rms_lit},
          {"why", why}};
}

ScanLight ScanLight::FromJson(const Json& json) {
  ScanLight out;
  try {
    out.observed = json.at("observed").get<bool>();
    const Json& l = json.at("light");
    if (!l.is_array() || l.size() != 3) Fail("'light' must be [x, y, z]");
    out.light = Eigen::Vector3d(l[0].get<double>(), l[1].get<double>(), l[2].get<double>());
    out.views = json.value("views", int64_t{0});
    out.vertices = json.value("vertices", int64_t{0});
    out.observations = json.value("observations", int64_t{0});
    out.rms_flat = json.value("rms_flat", 0.0);
    out.rms_lit = json.value("rms_lit", 0.0);
    out.why = json.value("why", std::string());
  } catch (const Json::exception& e) {
    Fail("scan light: ", e.what());
  }
  if (!out.light.allFinite() || out.light.norm() > 100) {
    Fail("scan light: 'light' must be finite and at most 100 times the ambient");
  }
  return out;
}

namespace {

// One view's sighting of a vertex: its linear RGB and its normal in the depth sensor's frame.
struct Sighting {
  Eigen::Vector3f rgb;
  Eigen::Vector3f normal;
  float weight = 0;  // the cosine of the view's incidence
};

Eigen::Vector3f Bilinear(const cv::Mat& bgr, float u, float v) {
  const float x = std::clamp(u, 0.0f, static_cast<float>(bgr.cols - 1));
  const float y = std::clamp(v, 0.0f, static_cast<float>(bgr.rows - 1));
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const int x1 = std::min(x0 + 1, bgr.cols - 1), y1 = std::min(y0 + 1, bgr.rows - 1);
  const float fx = x - static_cast<float>(x0), fy = y - static_cast<float>(y0);
  const float w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
  const cv::Vec3b* p[4] = {&bgr.at<cv::Vec3b>(y0, x0), &bgr.at<cv::Vec3b>(y0, x1),
                           &bgr.at<cv::Vec3b>(y1, x0), &bgr.at<cv::Vec3b>(y1, x1)};
  float rgb[3] = {0, 0, 0};
  for (int k = 0; k < 4; ++k) {
    for (int c = 0; c < 3; ++c) rgb[c] += w[k] * static_cast<float>((*p[k])[2 - c]);
  }
  return Eigen::Vector3f(rgb[0], rgb[1], rgb[2]) / 255.0f;
}

// Every usable sighting of the vertices `wanted` says (all when empty) in every view, appended
// per vertex: sightings[v].
class Sightings {
 public:
  Sightings(const Mesh& mesh, const std::vector<LitView>& views, const ScanLightOptions& options)
      : mesh_(mesh), views_(views), options_(options) {
    for (const LitView& view : views) depth_.push_back(RenderDepth(mesh, view.camera));
  }

  template <typename Visit>  // Visit(vertex, const Sighting&)
  void ForEach(const std::vector<int>& vertices, Visit visit) const {
    for (size_t k = 0; k < views_.size(); ++k) {
      const LitView& view = views_[k];
      const FastProjector projector(view.camera);
      const Eigen::Matrix3f to_camera = view.camera.cam_from_world().linear().cast<float>();
      const Eigen::Matrix3f to_sensor = view.sensor_from_world.cast<float>();
      const cv::Mat& depth = depth_[k];
      for (int v : vertices) {
        const Eigen::Vector3f p = projector.ToCamera(mesh_.vertices[v]);
        float u, w;
        if (!projector.Project(p, &u, &w)) continue;
        const int x = static_cast<int>(std::lround(u)), y = static_cast<int>(std::lround(w));
        if (x < 0 || y < 0 || x >= depth.cols || y >= depth.rows) continue;
        const float z = depth.at<float>(y, x);
        if (!(std::abs(z - p.z()) < options_.depth_tolerance_m)) continue;
        const Eigen::Vector3f n = to_camera * mesh_.normals[v];
        const float cos_view = -n.dot(p.normalized());
        if (cos_view < options_.min_cos_view) continue;
        Sighting s;
        s.rgb = Bilinear(view.bgr, u, w);
        const float grey = s.rgb.mean();
        if (grey < options_.min_intensity || s.rgb.maxCoeff() > options_.max_intensity) continue;
        s.normal = to_sensor * mesh_.normals[v];
        s.weight = cos_view;
        visit(v, s);
      }
    }
  }

 private:
  const Mesh& mesh_;
  const std::vector<LitView>& views_;
  const ScanLightOptions& options_;
  std::vector<cv::Mat> depth_;
};

// The fit's data: per vertex (offsets into the flat arrays) the log grey levels and normals.
struct FitData {
  std::vector<size_t> start;  // vertex i's sightings: [start[i], start[i + 1])
  std::vector<double> log_grey;
  std::vector<Eigen::Vector3d> normal;
  std::vector<bool> kept;

  size_t vertices() const { return start.empty() ? 0 : start.size() - 1; }
};

// Residuals (each vertex's mean removed) of the log grey levels under `light`, and, when `jac`
// is given, their derivatives by the light (rows, one per sighting).
void Residuals(const FitData& data, const Eigen::Vector3d& light, std::vector<double>* residual,
               std::vector<Eigen::Vector3d>* jac) {
  residual->assign(data.log_grey.size(), 0);
  if (jac != nullptr) jac->assign(data.log_grey.size(), Eigen::Vector3d::Zero());
  for (size_t i = 0; i < data.vertices(); ++i) {
    double mean = 0;
    Eigen::Vector3d mean_grad = Eigen::Vector3d::Zero();
    int count = 0;
    for (size_t j = data.start[i]; j < data.start[i + 1]; ++j) {
      if (!data.kept[j]) continue;
      const double dot = data.normal[j].dot(light);
      const double shading = 1 + std::max(0.0, dot);
      (*residual)[j] = data.log_grey[j] - std::log(shading);
      mean += (*residual)[j];
      if (jac != nullptr) {
        (*jac)[j] = dot > 0 ? Eigen::Vector3d(-data.normal[j] / shading) : Eigen::Vector3d::Zero();
        mean_grad += (*jac)[j];
      }
      ++count;
    }
    if (count == 0) continue;
    mean /= count;
    mean_grad /= count;
    for (size_t j = data.start[i]; j < data.start[i + 1]; ++j) {
      if (!data.kept[j]) continue;
      (*residual)[j] -= mean;
      if (jac != nullptr) (*jac)[j] -= mean_grad;
    }
  }
}

double Rms(const FitData& data, const std::vector<double>& residual) {
  double sum = 0;
  int64_t count = 0;
  for (size_t j = 0; j < residual.size(); ++j) {
    if (!data.kept[j]) continue;
    sum += residual[j] * residual[j];
    ++count;
  }
  return count == 0 ? 0 : std::sqrt(sum / count);
}

// Levenberg-Marquardt from `light`.
Eigen::Vector3d Refine(const FitData& data, Eigen::Vector3d light) {
  std::vector<double> r, trial;
  std::vector<Eigen::Vector3d> jac;
  Residuals(data, light, &r, &jac);
  double cost = Rms(data, r);
  double lambda = 1e-3;
  for (int iteration = 0; iteration < 50; ++iteration) {
    Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
    Eigen::Vector3d g = Eigen::Vector3d::Zero();
    for (size_t j = 0; j < r.size(); ++j) {
      if (!data.kept[j]) continue;
      h += jac[j] * jac[j].transpose();
      g += jac[j] * r[j];
    }
    bool improved = false;
    for (int attempt = 0; attempt < 8 && !improved; ++attempt) {
      Eigen::Matrix3d damped = h;
      damped.diagonal() *= 1 + lambda;
      damped.diagonal().array() += 1e-9;
      const Eigen::Vector3d step = -damped.ldlt().solve(g);
      const Eigen::Vector3d next = light + step;
      Residuals(data, next, &trial, nullptr);
      const double next_cost = Rms(data, trial);
      if (next_cost < cost) {
        improved = true;
        const bool small = step.norm() < 1e-6 * (1 + light.norm());
        light = next;
        cost = next_cost;
        lambda = std::max(1e-7, lambda / 4);
        if (small) return light;
      } else {
        lambda *= 8;
      }
    }
    if (!improved) break;
    Residuals(data, light, &r, &jac);
  }
  return light;
}

// The best of a grid of lights (directions spread over the sphere, a few strengths) on every
// `stride`-th vertex, refined on all of them.
Eigen::Vector3d Fit(const FitData& data) {
  FitData coarse;
  const size_t stride = std::max<size_t>(1, data.vertices() / 4000);
  coarse.start.push_back(0);
  for (size_t i = 0; i < data.vertices(); i += stride) {
    for (size_t j = data.start[i]; j < data.start[i + 1]; ++j) {
      coarse.log_grey.push_back(data.log_grey[j]);
      coarse.normal.push_back(data.normal[j]);
      coarse.kept.push_back(data.kept[j]);
    }
    coarse.start.push_back(coarse.log_grey.size());
  }
  std::vector<double> r;
  Eigen::Vector3d best = Eigen::Vector3d::Zero();
  Residuals(coarse, best, &r, nullptr);
  double best_cost = Rms(coarse, r);
  constexpr int kDirections = 160;
  const double golden = M_PI * (3 - std::sqrt(5.0));
  for (int d = 0; d < kDirections; ++d) {
    const double z = 1 - (d + 0.5) * 2.0 / kDirections;
    const double radius = std::sqrt(1 - z * z);
    const Eigen::Vector3d direction(radius * std::cos(golden * d), radius * std::sin(golden * d),
                                    z);
    for (double strength : {0.3, 0.8, 2.0, 5.0}) {
      Residuals(coarse, strength * direction, &r, nullptr);
      const double cost = Rms(coarse, r);
      if (cost < best_cost) {
        best_cost = cost;
        best = strength * direction;
      }
    }
  }
  return Refine(data, Refine(coarse, best));
}

}  // namespace

ScanLight EstimateScanLight(const Mesh& mesh, const std::vector<LitView>& views,
                            const std::vector<bool>& fit, const ScanLightOptions& options,
                            Mesh* albedo) {
  if (mesh.normals.size() != mesh.vertices.size()) Fail("scan light: the mesh has no normals");
  if (fit.size() != mesh.vertices.size()) Fail("scan light: one fit flag per vertex needed");
  ScanLight light;
  light.views = static_cast<int64_t>(views.size());
  const Sightings sightings(mesh, views, options);
  // The fit's vertices: every k-th of those it may use.
  std::vector<int> usable;
  for (size_t v = 0; v < fit.size(); ++v)
    if (fit[v]) usable.push_back(static_cast<int>(v));
  std::vector<int> sample;
  const size_t stride =
      std::max<size_t>(1, usable.size() / static_cast<size_t>(options.max_fit_vertices));
  for (size_t k = 0; k < usable.size(); k += stride) sample.push_back(usable[k]);
  std::vector<std::vector<Sighting>> seen(mesh.vertices.size());
  sightings.ForEach(sample, [&](int v, const Sighting& s) { seen[v].push_back(s); });
  FitData data;
  data.start.push_back(0);
  for (int v : sample) {
    if (seen[v].size() < 2) continue;
    for (const Sighting& s : seen[v]) {
      data.log_grey.push_back(std::log(static_cast<double>(s.rgb.mean())));
      data.normal.push_back(s.normal.cast<double>().normalized());
    }
    data.start.push_back(data.log_grey.size());
    std::vector<Sighting>().swap(seen[v]);
  }
  data.kept.assign(data.log_grey.size(), true);
  light.vertices = static_cast<int64_t>(data.vertices());
  if (light.vertices < options.min_vertices) {
    light.why = Cat("only ", light.vertices, " vertices were seen twice off the floor (needs ",
                    options.min_vertices, ")");
  } else {
    Eigen::Vector3d fitted = Fit(data);
    // Sightings the fit cannot explain (a shadow, a highlight, a misregistered edge) are left
    // out, and the light fitted again.
    std::vector<double> r;
    Residuals(data, fitted, &r, nullptr);
    std::vector<double> magnitude;
    for (double x : r) magnitude.push_back(std::abs(x));
    std::nth_element(magnitude.begin(), magnitude.begin() + magnitude.size() / 2, magnitude.end());
    const double limit = std::max(0.02, 3 * 1.4826 * magnitude[magnitude.size() / 2]);
    for (size_t j = 0; j < r.size(); ++j) data.kept[j] = std::abs(r[j]) <= limit;
    fitted = Refine(data, fitted);
    Residuals(data, Eigen::Vector3d::Zero(), &r, nullptr);
    light.rms_flat = Rms(data, r);
    Residuals(data, fitted, &r, nullptr);
    light.rms_lit = Rms(data, r);
    light.observations = std::count(data.kept.begin(), data.kept.end(), true);
    if (light.rms_lit > (1 - options.min_improvement) * light.rms_flat) {
      light.why = Cat("no directional light explains the scan's intensities (log residual RMS ",
                      light.rms_lit, " against ", light.rms_flat, " under ambient light alone)");
    } else if (fitted.norm() < options.min_strength) {
      light.why = Cat("the fitted light is weak (", fitted.norm(), " of the ambient)");
    } else {
      light.observed = true;
      light.light = fitted;
    }
  }
  if (albedo == nullptr) return light;
  // Every vertex's albedo: its colours over the shading they were seen in.
  std::vector<int> all(mesh.vertices.size());
  for (size_t v = 0; v < all.size(); ++v) all[v] = static_cast<int>(v);
  std::vector<Eigen::Vector3d> colour(all.size(), Eigen::Vector3d::Zero());
  std::vector<double> shading(all.size(), 0);
  std::vector<float> every_shading;
  sightings.ForEach(all, [&](int v, const Sighting& s) {
    const double sh = light.Shading(s.normal.cast<double>().normalized());
    colour[v] += s.weight * s.rgb.cast<double>();
    shading[v] += s.weight * sh;
    if (v % 16 == 0) every_shading.push_back(static_cast<float>(sh));
  });
  double typical = 1;
  if (!every_shading.empty()) {
    std::nth_element(every_shading.begin(), every_shading.begin() + every_shading.size() / 2,
                     every_shading.end());
    typical = every_shading[every_shading.size() / 2];
  }
  *albedo = mesh;
  albedo->colors.resize(mesh.vertices.size(), Eigen::Matrix<uint8_t, 3, 1>(128, 128, 128));
  for (size_t v = 0; v < all.size(); ++v) {
    const Eigen::Vector3d a =
        shading[v] > 0 ? Eigen::Vector3d(colour[v] / shading[v])
                       : Eigen::Vector3d(albedo->colors[v].cast<double>() / (255.0 * typical));
    for (int c = 0; c < 3; ++c) {
      albedo->colors[v][c] =
          static_cast<uint8_t>(std::clamp(std::lround(255 * a[c]), long{0}, long{255}));
    }
  }
  return light;
}

}  // namespace holocap
