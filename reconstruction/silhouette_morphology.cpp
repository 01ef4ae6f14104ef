// The closing thresholded silhouettes need, measured on the silhouettes' own boundaries.
//
// Closing a mask by a disk of radius r fills every background region narrower than 2r that the
// mask surrounds or nearly surrounds. On a clean boundary those regions are the subject's own
// concave corners and narrow concavities: a corner gains about 0.2 r^2, so the gain per pixel
// of boundary grows steadily with r, at a rate set by the shape. A threshold that cuts holes,
// cracks or bites into a silhouette adds regions of one small width: the closing that spans
// that width fills them all at once, a jump in the gain at that radius, after which the gain
// returns to the shape's steady rate. So the gain is measured per radius, counting only fills
// that are holes (background the mask encloses) or long and narrow (a crack, a bite or a
// narrow concavity: at least four radii long); compact corner fills are left out as what any
// boundary gains. The steady rate is the median step over the radii (most steps are the
// shape's); a step at a small radius that exceeds both twice that rate and an absolute floor
// is a jump; the closing is the last radius of the first run of jumps, none when there is no
// jump. Only the smaller half of the radii may jump: a wider gap is more likely the subject's
// own (the gaps between limbs or columns), which other views carve open anyway.
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

cv::Mat Disk(int radius) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * radius + 1, 2 * radius + 1));
}

// The background pixels `mask` encloses (not 4-connected to the image's edge), as 255.
cv::Mat Holes(const cv::Mat& mask) {
  cv::Mat padded;
  cv::copyMakeBorder(mask, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::floodFill(padded, cv::Point(0, 0), cv::Scalar(255), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  cv::Mat holes;
  cv::bitwise_not(padded(cv::Rect(1, 1, mask.cols, mask.rows)), holes);
  return holes;
}

// Boundary pixels of `mask`: foreground with a 4-neighbour in the background.
int64_t Perimeter(const cv::Mat& mask) {
  cv::Mat eroded;
  cv::erode(mask, eroded, cv::getStructuringElement(cv::MORPH_CROSS, cv::Size(3, 3)),
            cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
  return cv::countNonZero(mask) - cv::countNonZero(eroded);
}

// The area the closing by `radius` adds to `mask` in fills that are holes or at least four
// radii long, and how many such fills.
void DefectFills(const cv::Mat& mask, const cv::Mat& holes, int radius, int64_t* area, int* count) {
  cv::Mat closed;
  cv::morphologyEx(mask, closed, cv::MORPH_CLOSE, Disk(radius), cv::Point(-1, -1), 1,
                   cv::BORDER_REPLICATE);
  const cv::Mat added = closed & ~mask;
  cv::Mat labels, stats, centroids;
  const int labelled = cv::connectedComponentsWithStats(added, labels, stats, centroids, 8, CV_32S);
  std::vector<std::vector<cv::Point>> points(labelled);
  std::vector<uint8_t> enclosed(labelled, 1);
  for (int y = 0; y < labels.rows; ++y) {
    const int* label = labels.ptr<int>(y);
    const uint8_t* hole = holes.ptr<uint8_t>(y);
    for (int x = 0; x < labels.cols; ++x) {
      if (label[x] == 0) continue;
      points[label[x]].emplace_back(x, y);
      if (hole[x] == 0) enclosed[label[x]] = 0;
    }
  }
  for (int i = 1; i < labelled; ++i) {
    const cv::Size2f extent = cv::minAreaRect(points[i]).size;
    const double length = std::max(extent.width, extent.height) + 1;
    if (enclosed[i] || length >= 4.0 * radius) {
      *area += stats.at<int>(i, cv::CC_STAT_AREA);
      ++*count;
    }
  }
}

}  // namespace

nlohmann::json ClosingChoice::ToJson() const {
  return {{"close_px", close_px},
          {"radii_px", radii_px},
          {"fill_px", fill_px},
          {"fills", fills},
          {"steady_step_px", steady_step_px},
          {"min_jump_px", min_jump_px},
          {"holes", holes},
          {"why", why}};
}

ClosingChoice ClosingChoice::FromJson(const nlohmann::json& json) {
  ClosingChoice choice;
  choice.close_px = json.at("close_px").get<int>();
  choice.radii_px = json.at("radii_px").get<std::vector<int>>();
  choice.fill_px = json.at("fill_px").get<std::vector<double>>();
  choice.fills = json.at("fills").get<std::vector<int>>();
  choice.steady_step_px = json.at("steady_step_px").get<double>();
  choice.min_jump_px = json.at("min_jump_px").get<double>();
  choice.holes = json.at("holes").get<int>();
  choice.why = json.at("why").get<std::string>();
  return choice;
}

ClosingChoice ChooseClosing(const std::vector<cv::Mat>& masks, int max_radius_px,
                            double min_jump_px) {
  if (masks.empty()) Fail("choosing a closing needs one mask or more");
  if (max_radius_px < 2)
    Fail("choosing a closing: the largest radius (", max_radius_px, " px) must be 2 px or more");
  if (!(min_jump_px >= 0)) Fail("choosing a closing: min_jump_px (", min_jump_px, ") is negative");
  ClosingChoice choice;
  choice.min_jump_px = min_jump_px;
  std::vector<int64_t> area(static_cast<size_t>(max_radius_px) + 1, 0);
  std::vector<int> fills(area.size(), 0);
  int64_t perimeter = 0;
  for (const cv::Mat& mask : masks) {
    if (mask.empty() || mask.type() != CV_8UC1) Fail("choosing a closing: masks must be CV_8UC1");
    perimeter += Perimeter(mask);
    const cv::Mat holes = Holes(mask);
    cv::Mat labels;
    choice.holes += cv::connectedComponents(holes, labels, 4, CV_32S) - 1;
    for (int r = 1; r <= max_radius_px; ++r) DefectFills(mask, holes, r, &area[r], &fills[r]);
  }
  std::vector<double> steps;
  for (int r = 0; r <= max_radius_px; ++r) {
    choice.radii_px.push_back(r);
    choice.fill_px.push_back(perimeter > 0 ? static_cast<double>(area[r]) / perimeter : 0);
    choice.fills.push_back(fills[r]);
    if (r > 0) steps.push_back(choice.fill_px[r] - choice.fill_px[r - 1]);
  }
  std::vector<double> sorted = steps;
  std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
  choice.steady_step_px = sorted[sorted.size() / 2];
  const double jump = std::max(2 * choice.steady_step_px, min_jump_px);
  const int last_candidate = (max_radius_px + 1) / 2;
  int first_jump = 0;
  for (int r = 1; r <= last_candidate && first_jump == 0; ++r) {
    if (steps[r - 1] > jump) first_jump = r;
  }
  if (first_jump > 0) {
    choice.close_px = first_jump;
    while (choice.close_px < last_candidate && steps[choice.close_px] > jump) ++choice.close_px;
  }
  std::string curve = Cat("fills of holes and cracks per boundary pixel ");
  for (int r = 1; r <= max_radius_px; ++r)
    curve += Cat(r > 1 ? ", " : "", Fixed3(choice.fill_px[r]), " at ", r, " px");
  curve += Cat(" (", choice.holes, " holes in ", masks.size(), " views); the steady step ",
               Fixed3(choice.steady_step_px), " px a radius, a jump over ", Fixed3(jump), " px");
  choice.why =
      choice.close_px == 0
          ? Cat("the boundary is clean: ", curve, ", none up to ", last_candidate, " px")
          : Cat("the closing that fills the jump in ", curve, ": ", choice.close_px, " px");
  return choice;
}

}  // namespace holocap
