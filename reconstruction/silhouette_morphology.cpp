// The closing thresholded silhouettes need, measured by how well the hull carved from them
// explains each view's silhouette.
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cstdio>

#include "core/error.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

std::string Fixed3(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.3f", value);
  return text;
}

// The views with their masks closed by a disk of `radius` pixels; the fraction of each mask
// the closing adds, averaged over the views, in `added`.
std::vector<View> Closed(const std::vector<View>& views, int radius, double* added) {
  std::vector<View> out = views;
  double sum = 0;
  for (View& view : out) {
    if (radius == 0) continue;
    const cv::Mat disk =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
    cv::Mat closed;
    cv::morphologyEx(view.mask, closed, cv::MORPH_CLOSE, disk, cv::Point(-1, -1), 1,
                     cv::BORDER_REPLICATE);
    const double before = cv::countNonZero(view.mask);
    if (before > 0) sum += (cv::countNonZero(closed) - before) / before;
    view.mask = closed;
  }
  *added = views.empty() ? 0 : sum / static_cast<double>(views.size());
  return out;
}

// The views' mean IoU of their own mask and the silhouette of the hull carved from them; 0
// when the hull is not usable.
double Agreement(const std::vector<View>& views, const HullOptions& options) {
  HullSummary summary;
  const VisualHull hull = ComputeVisualHull(views, options, &summary);
  if (!summary.IsUsable()) return 0;
  const Mesh mesh = ExtractMesh(*hull.volume);
  if (mesh.faces.empty()) return 0;
  double sum = 0;
  for (const View& view : views) sum += MaskIoU(RenderSilhouette(mesh, view.camera), view.mask);
  return sum / static_cast<double>(views.size());
}

}  // namespace

nlohmann::json ClosingChoice::ToJson() const {
  return {{"close_px", close_px},
          {"radii_px", radii_px},
          {"agreement_by_radius", agreement},
          {"added_fraction_by_radius", added_fraction},
          {"why", why}};
}

ClosingChoice ChooseClosing(const std::vector<View>& views, const HullOptions& hull,
                            const std::vector<int>& radii_px, double min_gain) {
  if (views.size() < 2)
    Fail("choosing a closing needs two views or more; ", views.size(), " given");
  if (radii_px.empty() || radii_px.front() != 0 || !(min_gain >= 0))
    Fail("choosing a closing: the radii must start at 0 and min_gain (", min_gain,
         ") must not be negative");
  for (size_t i = 1; i < radii_px.size(); ++i) {
    if (radii_px[i] <= radii_px[i - 1]) Fail("choosing a closing: the radii must increase");
  }
  ClosingChoice choice;
  const auto measure = [&](int radius) {
    double added = 0;
    choice.radii_px.push_back(radius);
    choice.agreement.push_back(Agreement(Closed(views, radius, &added), hull));
    choice.added_fraction.push_back(added);
  };
  measure(0);
  size_t chosen = 0;
  for (; chosen + 1 < radii_px.size(); ++chosen) {
    measure(radii_px[chosen + 1]);
    if (choice.agreement[chosen + 1] - choice.agreement[chosen] < min_gain) break;
  }
  chosen = std::min(chosen, choice.agreement.size() - 1);
  choice.close_px = radii_px[chosen];
  const auto at = [&](size_t i) {
    return Cat(Fixed3(choice.agreement[i]), " at ", choice.radii_px[i], " px");
  };
  std::string curve = Cat("mean IoU of each view's silhouette and the hull's ", at(0));
  for (size_t i = 1; i < choice.agreement.size(); ++i) curve += Cat(", ", at(i));
  if (chosen + 1 < choice.agreement.size()) {
    curve += Cat("; the next closing gains less than ", min_gain);
  } else {
    curve += Cat("; the largest closing measured");
  }
  choice.why =
      choice.close_px == 0
          ? Cat("the boundary is clean: ", curve)
          : Cat("the smallest closing after which the views' agreement stabilises: ", curve,
                "; it adds ", Fixed3(100 * choice.added_fraction[chosen]),
                " % to a view's silhouette");
  return choice;
}

}  // namespace holocap
