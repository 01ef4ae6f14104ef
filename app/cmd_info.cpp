// holocap info TAKE: what a take holds.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iomanip>
#include <iostream>
#include <set>

#include "app/commands.h"
#include "core/take.h"

namespace holocap {

void PrintTakeInfo(const Take& take, std::ostream& out) {
  out << "take        " << take.dir().string() << "  (format " << take.format_version() << ", "
      << take.state() << ")\n";
  out << "rig         " << take.rig().name << ", sync " << ToString(take.rig().sync) << ", "
      << take.rig().fps << " fps asked\n";
  out << "frame sets  " << take.size();
  if (take.skipped_index_lines() > 0)
    out << "  (" << take.skipped_index_lines() << " incomplete set(s) skipped)";
  out << "\n";
  int64_t first = 0, last = 0;
  double spread_sum = 0;
  int64_t spread_max = 0;
  for (size_t i = 0; i < take.size(); ++i) {
    const auto& entry = take.entry(i);
    for (const auto& item : entry.items) {
      if ((first == 0 && last == 0) || item.timestamp_ns < first) first = item.timestamp_ns;
      last = std::max(last, item.timestamp_ns);
    }
    spread_sum += entry.spread_ns;
    spread_max = std::max(spread_max, entry.spread_ns);
  }
  if (take.size() > 0) {
    double duration = (last - first) * 1e-9;
    out << "timestamps  " << first << " .. " << last << " ns (" << std::fixed
        << std::setprecision(3) << duration << " s)\n";
    out << "sync spread mean " << std::setprecision(1) << spread_sum / take.size() / 1e3
        << " us, max " << spread_max / 1e3 << " us\n";
  }
  const bool calibrated = take.has_calibration();
  const bool ground_truth = take.has_ground_truth();
  out << "calibration " << (calibrated ? "yes (calib/)" : "no: uncalibrated (holocap calibrate)")
      << "\n";
  out << "ground truth " << (ground_truth ? "yes (gt/)" : "no") << "\n";
  out << "sensors     " << take.streams().size() << "\n";
  for (const auto& stream : take.streams()) {
    int64_t frames = 0;
    for (const auto& entry : take.entries()) frames += entry.Find(stream.name) != nullptr;
    auto dropped = take.dropped().count(stream.name) ? take.dropped().at(stream.name) : 0;
    out << "  " << std::left << std::setw(10) << stream.name << std::right << " " << std::setw(7)
        << ToString(stream.role) << " " << stream.width << "x" << stream.height << " "
        << stream.pixel_format << " clock=" << stream.clock << " frames=" << frames
        << " dropped=" << dropped;
    for (bool gt : {false, true}) {
      auto file =
          (gt ? take.gt_dir() / "cameras" : take.calib_dir()) / (stream.name + ".cameramodel");
      if (std::filesystem::exists(file)) {
        try {
          out << (gt ? " true-lens=" : " lens=") << CameraModel::Read(file).lensmodel();
        } catch (const std::exception& e) {
          out << (gt ? " true-lens=" : " lens=") << "unreadable";
        }
      }
    }
    if (!stream.paired_with.empty()) out << " paired_with=" << stream.paired_with;
    out << "  " << stream.uri << "\n";
  }
}

static void AddInfoCommand(CLI::App& app) {
  auto* command =
      app.add_subcommand("info", "Describe a take: sensors, lenses, frames, sync, drops");
  auto take_dir = std::make_shared<std::string>();
  auto verify = std::make_shared<bool>(false);
  command->add_option("TAKE", *take_dir, "The take directory")->required();
  command->add_flag("--verify", *verify, "Decode every frame and stop at the first bad one");
  command->callback([take_dir, verify] {
    Take take = Take::Open(*take_dir);
    // Verify before printing anything, so a bad take gives the one error line alone.
    if (*verify) take.Verify();  // throws naming the first damage
    PrintTakeInfo(take, std::cout);
    if (*verify) {
      std::cout << "verified    every frame of " << take.size() << " frame sets decodes\n";
    }
  });
}

HOLOCAP_COMMAND(30, AddInfoCommand);

}  // namespace holocap
