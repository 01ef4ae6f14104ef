// Printable boards: a raster PNG, or a PDF of vector squares that prints exactly to scale.
#include <cmath>
#include <cstdio>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/image.h"

namespace holocap {
namespace {

constexpr double kMetresPerInch = 0.0254;

// The pattern's square cells: side, origin (board coordinates) and count per axis.
struct CellLattice {
  double cell = 0;
  double origin = 0;
  int across = 0;
  int down = 0;
};

CellLattice LatticeOf(const Board& board) {
  const BoardLayout& layout = board.layout();
  CellLattice lattice;
  if (layout.type == BoardType::kChessboard) {
    lattice.cell = layout.spacing;
    lattice.origin = -layout.spacing;
    lattice.across = layout.chessboard_width_n + 1;
    lattice.down = layout.chessboard_height_n + 1;
    return lattice;
  }
  int border = 0, total = 0;
  calibration_internal::FamilyGeometry(layout.family, &border, &total);
  lattice.cell = layout.spacing / border;
  lattice.origin = -lattice.cell * (total - border) / 2;
  lattice.across = (2 * layout.tags_across - 1) * border + total - border;
  lattice.down = (2 * layout.tags_down - 1) * border + total - border;
  return lattice;
}

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
  const CellLattice lattice = LatticeOf(board);
  const double pt_per_m = 72.0 / kMetresPerInch;
  const double page_w = (board.u_max() - board.u_min()) * pt_per_m;
  const double page_h = (board.v_max() - board.v_min()) * pt_per_m;
  // Black cells as horizontal runs; PDF's y axis points up, the board's v axis down.
  std::string content = "0 g\n";
  for (int cv = 0; cv < lattice.down; ++cv) {
    const double v = lattice.origin + (cv + 0.5) * lattice.cell;
    int run_start = -1;
    for (int cu = 0; cu <= lattice.across; ++cu) {
      const double u = lattice.origin + (cu + 0.5) * lattice.cell;
      const bool black = cu < lattice.across && board.Reflectance(u, v) < 0.5;
      if (black && run_start < 0) run_start = cu;
      if (!black && run_start >= 0) {
        const double x = (lattice.origin + run_start * lattice.cell - board.u_min()) * pt_per_m;
        const double y =
            page_h - (lattice.origin + (cv + 1) * lattice.cell - board.v_min()) * pt_per_m;
        content += Number(x) + " " + Number(y) + " " +
                   Number((cu - run_start) * lattice.cell * pt_per_m) + " " +
                   Number(lattice.cell * pt_per_m) + " re\n";
        run_start = -1;
      }
    }
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
