// A calibration taken over from another take of the same rig (`holocap calibrate TAKE --from`).
#include <cmath>

#include "calibration/calibration.h"
#include "core/error.h"
#include "core/fs.h"
#include "core/report.h"
#include "core/take.h"

namespace holocap {
namespace {

namespace fs = std::filesystem;

// The folder holding the models: a take's calib/, or a folder of .cameramodel files itself.
fs::path ModelFolder(const fs::path& from) {
  if (fs::exists(from / "take.json")) return from / "calib";
  return from;
}

// The calibration's own report, when it has one: a run that did not end usable gives no models
// to trust.
void CheckSourceReport(const fs::path& folder, nlohmann::json* source) {
  const fs::path file = folder / "report.json";
  if (!fs::exists(file)) {
    (*source)["report"] = nullptr;
    return;
  }
  const nlohmann::json report = ParseReport(ReadFileToString(file), file.string());
  const std::string termination = report["summary"].value("termination", std::string("FAILURE"));
  if (termination != "SUCCESS" && termination != "CONVERGENCE" && termination != "NO_CONVERGENCE") {
    Fail("'", file.string(), "' ended ", termination,
         ": its models are not a calibration to take over (calibrate that take again)");
  }
  (*source)["report"] = file.string();
  (*source)["termination"] = termination;
  (*source)["command"] = report.value("command", std::string());
  const nlohmann::json& options = report.contains("options") ? report["options"] : nlohmann::json();
  (*source)["detector"] = options.contains("detector") ? options["detector"] : nlohmann::json();
  if (options.contains("board") && options["board"].contains("type"))
    (*source)["board_type"] = options["board"]["type"];
}

// Throws Error unless the source's corners came from `asked` (the finder the caller named).
void CheckSourceDetector(const fs::path& folder, const nlohmann::json& source,
                         ChessboardFinder asked) {
  const std::string name = ToString(asked);
  const nlohmann::json& detector = source.contains("detector") ? source["detector"] : nullptr;
  if (!detector.is_string()) {
    Fail("--detector ", name, ": '", folder.string(),
         "' does not say which detector found its corners (no report.json naming one); leave "
         "--detector out to take its models over as they are");
  }
  const std::string board_type = source.value("board_type", std::string());
  if (asked == ChessboardFinder::kMrgingham && board_type != "chessboard") {
    Fail("--detector mrgingham finds chessboards only; the calibration in '", folder.string(),
         "' was solved on a ", board_type, " board");
  }
  if (detector.get<std::string>() != name) {
    Fail("--detector ", name, ": the calibration in '", folder.string(), "' was solved on the ",
         detector.get<std::string>(), " finder's corners (calibrate that take with --detector ",
         name, ", or leave --detector out)");
  }
}

}  // namespace

TakeCalibrationSummary AdoptCalibration(const fs::path& take_dir, const fs::path& from,
                                        Report* report,
                                        const std::optional<ChessboardFinder>& chessboard_finder) {
  const Take take = Take::Open(take_dir);
  const fs::path folder = ModelFolder(from);
  if (!fs::is_directory(folder))
    Fail("'", folder.string(), "' is not a folder of camera models (a calibrated take's calib/)");
  std::error_code ec;
  const fs::path resolved = fs::weakly_canonical(folder, ec);
  if (resolved.parent_path().filename() == "gt" &&
      fs::exists(resolved.parent_path().parent_path() / "take.json")) {
    Fail("'", folder.string(),
         "' is a simulated take's truth, not a calibration: it only measures (calibrate a board "
         "take, or give --ground-truth-cameras to the stage that should use the truth)");
  }
  if (fs::equivalent(folder, take.calib_dir(), ec))
    Fail("'", from.string(), "' is the take's own calibration");
  nlohmann::json source = {{"from", fs::absolute(from).lexically_normal().string()}};
  CheckSourceReport(folder, &source);
  if (chessboard_finder) CheckSourceDetector(folder, source, *chessboard_finder);

  TakeCalibrationSummary result;
  std::map<std::string, CameraModel> models;
  nlohmann::json sensors = nlohmann::json::object();
  std::string scaled;
  for (const StreamInfo& stream : take.streams()) {
    if (stream.role == SensorRole::kWitness) continue;
    const fs::path file = folder / (stream.name + ".cameramodel");
    if (!fs::exists(file)) {
      Fail("'", folder.string(), "' has no model of sensor '", stream.name, "' (no ",
           file.filename().string(), "): it is not a calibration of this take's rig");
    }
    CameraModel model = CameraModel::Read(file);
    double scale = 1;
    if (model.width() != stream.width || model.height() != stream.height) {
      // The same imager read out at another size (binning, a smaller mode): the lens scales
      // with it when both sides do by the same factor.
      scale = static_cast<double>(stream.width) / model.width();
      if (std::abs(model.height() * scale - stream.height) > 1) {
        Fail("sensor '", stream.name, "' records ", stream.width, "x", stream.height,
             " but its model in '", file.string(), "' is of a ", model.width(), "x", model.height(),
             " imager: not the same sensor scaled");
      }
      model = model.Scaled(scale);
      scaled += Cat(scaled.empty() ? "" : ", ", stream.name, " x", scale);
    }
    sensors[stream.name] = {{"file", file.string()}, {"scale", scale}};
    models.emplace(stream.name, std::move(model));
  }

  CreateDirectories(take.calib_dir());
  for (const auto& [name, model] : models) {
    const fs::path file = take.calib_dir() / (name + ".cameramodel");
    model.Write(file);
    result.written.push_back(file);
  }
  result.End(Termination::kSuccess,
             Cat("the calibration in '", folder.string(), "' taken over for ", models.size(),
                 " sensors", scaled.empty() ? "" : Cat(" (scaled: ", scaled, ")")));
  result.calibration.termination = result.termination;
  result.calibration.message = result.message;

  Report local("calibrate");
  Report& r = report != nullptr ? *report : local;
  r.options()["from"] = source["from"];
  r.options()["detector"] = source.contains("detector") ? source["detector"] : nlohmann::json();
  r.plan()["adopted"] = source;
  r.plan()["sensors"] = sensors;
  r.SetSummary(result);
  result.report_file = r.Write(take.calib_dir() / "report.json");
  result.written.push_back(result.report_file);
  return result;
}

}  // namespace holocap
