// Printable boards: a raster PNG, or a PDF of vector squares that prints exactly to scale.
#include <cmath>
#include <cstdio>

#include "calibration/calibration.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"

namespace holocap {
namespace {

constexpr double kMetresPerInch = 0.0254;

std::string Number(double value) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%.4f", value);
  return buffer;
}

}  // namespace

cv::Mat RenderBoardImage(const BoardLayout& layout, double dpi) {
  if (!(dpi > 0) || dpi > 2400) Fail("board print resolution must be in (0, 2400] dpi, got ", dpi);
  const Board board(layout);
  const double px_per_m = dpi / kMetresPerInch;
  const int width = static_cast<int>(std::lround((board.u_max() - board.u_min()) * px_per_m));
  const int height = static_cast<int>(std::lround((board.v_max() - board.v_min()) * px_per_m));
  if (static_cast<double>(width) * height > 4e8)
    Fail("board print of ", width, "x", height, " px is too large: lower the dpi");
  cv::Mat image(height, width, CV_8UC1);
  for (int y = 0; y < height; ++y) {
    uint8_t* row = image.ptr<uint8_t>(y);
    const double v = board.v_min() + (y + 0.5) / px_per_m;
    for (int x = 0; x < width; ++x) {
      const double u = board.u_min() + (x + 0.5) / px_per_m;
      row[x] = board.Reflectance(u, v) > 0.5 ? 255 : 0;
    }
  }
  return image;
}

void WriteBoardPrint(const BoardLayout& layout, const std::filesystem::path& file, double dpi) {
  const std::string extension = file.extension().string();
  if (extension == ".png") {
    WritePng(file, RenderBoardImage(layout, dpi), 6);
    return;
  }
  if (extension != ".pdf") Fail("board print '", file.string(), "': use a .png or .pdf name");
  const Board board(layout);
  const double pt_per_m = 72.0 / kMetresPerInch;
  const double page_w = (board.u_max() - board.u_min()) * pt_per_m;
  const double page_h = (board.v_max() - board.v_min()) * pt_per_m;
  // Black runs of the pattern's cells; PDF's y axis points up, the board's v axis down.
  std::string content = "0 g\n";
  for (const Eigen::Vector4d& r : board.BlackRectangles()) {
    const double x = (r[0] - board.u_min()) * pt_per_m;
    const double y = page_h - (r[1] + r[3] - board.v_min()) * pt_per_m;
    content += Number(x) + " " + Number(y) + " " + Number(r[2] * pt_per_m) + " " +
               Number(r[3] * pt_per_m) + " re\n";
  }
  content += "f\n";
  std::vector<std::string> objects = {
      "<< /Type /Catalog /Pages 2 0 R >>", "<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
      "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 " + Number(page_w) + " " + Number(page_h) +
          "] /Contents 4 0 R /Resources << >> >>",
      "<< /Length " + std::to_string(content.size()) + " >>\nstream\n" + content + "endstream"};
  std::string pdf = "%PDF-1.4\n";
  std::vector<size_t> offsets;
  for (size_t k = 0; k < objects.size(); ++k) {
    offsets.push_back(pdf.size());
    pdf += std::to_string(k + 1) + " 0 obj\n" + objects[k] + "\nendobj\n";
  }
  const size_t xref = pdf.size();
  pdf += "xref\n0 " + std::to_string(objects.size() + 1) + "\n0000000000 65535 f \n";
  for (size_t offset : offsets) {
    char line[32];
    std::snprintf(line, sizeof(line), "%010zu 00000 n \n", offset);
    pdf += line;
  }
  pdf += "trailer\n<< /Size " + std::to_string(objects.size() + 1) +
         " /Root 1 0 R >>\nstartxref\n" + std::to_string(xref) + "\n%%EOF\n";
  WriteFileAtomic(file, pdf);
}

}  // namespace holocap
