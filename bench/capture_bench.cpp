// Capture throughput against real GigE Vision peers: 8 fake camera processes in a private
// network namespace, software-triggered, recorded by the Recorder into a take. Prints the rig
// rate asked (cameras x resolution x fps), the rate written, frame sets complete against
// triggers, frames lost, packet resend requests, sync spread, and the disk's own sequential
// write speed measured in the same run. The peers are arv-fake-gv-camera-0.8 ("arv", software
// triggers served on a 25 Hz tick only) and holocap-fake-gige-camera with a 100 Hz trigger tick,
// libaravis' camera model behind holocap's GVCP/GVSP peer ("hc", answers packet resend requests)
// or behind libaravis' own peer ("hc-la", answers none); "loss" is their GVSP packet loss per
// thousand on first sending, "resends" the packets the driver asked for again and "resent"
// those it received. Frames carry libaravis' ramp (compresses to almost nothing) or noise
// (incompressible: what the disk must take is the rig rate itself).
//
//   capture_bench [--seconds 60] [--out /tmp/holocap-capture-bench]   (seconds per row)

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include "capture/recorder.h"
#include "core/error.h"
#include "tests/capture/fake_gige.h"

namespace holocap {
namespace {

// Sequential write of `bytes` in 8 MiB blocks, fsync'ed: the disk's own speed in MB/s.
double DiskWriteMBs(const std::filesystem::path& dir, size_t bytes) {
  const auto file = dir / "disk-probe.bin";
  std::vector<char> block(8 << 20);
  for (size_t i = 0; i < block.size(); ++i) block[i] = static_cast<char>(i * 2654435761u >> 13);
  const auto start = std::chrono::steady_clock::now();
  int fd = open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (fd < 0) Fail("cannot write ", file.string(), ": ", std::strerror(errno));
  for (size_t done = 0; done < bytes; done += block.size()) {
    if (write(fd, block.data(), block.size()) != static_cast<ssize_t>(block.size()))
      Fail("disk probe write failed");
  }
  fsync(fd);
  close(fd);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::filesystem::remove(file);
  return static_cast<double>(bytes) / 1e6 / seconds;
}

struct Config {
  std::string peer;  // "arv": arv-fake-gv-camera-0.8; "hc" | "hc-la": holocap-fake-gige-camera
  double tick_hz;    // 0 with "arv"
  int lost_per_thousand;
  std::string pattern;  // "ramp" | "noise"
  int cameras;
  int width;
  int height;
  double fps;
  std::string codec;
};

}  // namespace
}  // namespace holocap

int main(int argc, char** argv) {
  using namespace holocap;
  double seconds = 60;
  std::filesystem::path out = "/tmp/holocap-capture-bench";
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::string(argv[i]) == "--seconds") seconds = std::stod(argv[i + 1]);
    if (std::string(argv[i]) == "--out") out = argv[i + 1];
  }
  try {
    std::filesystem::remove_all(out);
    std::filesystem::create_directories(out);
    const double disk = DiskWriteMBs(out, size_t{1} << 30);
    std::printf("disk sequential write (1 GiB, 8 MiB blocks, fsync): %.0f MB/s  [%s]\n\n", disk,
                out.c_str());

    DriverRegistry registry;
    RegisterAravisDriver(registry);
    const std::vector<Config> configs = {{"arv", 0, 0, "ramp", 8, 256, 256, 25, "zstd"},
                                         {"arv", 0, 0, "ramp", 8, 256, 256, 30, "zstd"},
                                         {"hc", 100, 0, "ramp", 8, 256, 256, 30, "zstd"},
                                         {"hc", 100, 20, "ramp", 8, 256, 256, 30, "zstd"},
                                         {"hc-la", 100, 20, "ramp", 8, 128, 64, 30, "zstd"},
                                         {"hc", 100, 0, "noise", 8, 512, 512, 30, "zstd"},
                                         {"hc", 100, 0, "noise", 8, 1024, 768, 30, "zstd"},
                                         {"hc", 100, 0, "noise", 8, 1024, 768, 30, "png"}};
    std::printf("%-5s %-4s %-5s %-4s %-9s %-4s %-5s %8s %10s %8s %11s %7s %8s %8s %9s %8s\n",
                "peer", "loss", "frame", "cams", "size", "fps", "codec", "rig MB/s", "write MB/s",
                "vs disk", "sets/trig", "lost", "resends", "resent", "spread ms", "mean ms");
    double best_zero_drop = 0, best_nearly = 0;
    std::string best_text = "none", best_nearly_text = "none";
    for (const Config& config : configs) {
      testing::FakeGigeCameras cameras(config.cameras, config.lost_per_thousand, config.tick_hz,
                                       config.pattern,
                                       config.peer == "hc-la" ? "libaravis" : "holocap");
      RigDescription rig;
      rig.name = "fake-booth";
      rig.sync = SyncMode::kSoftwareTrigger;
      rig.fps = config.fps;
      for (int i = 0; i < config.cameras; ++i) {
        SensorSpec spec;
        spec.name = "cam" + std::to_string(i);
        spec.uri = "aravis:" + cameras.id(i);
        spec.options = {{"roi", {0, 0, config.width, config.height}}, {"pixel_format", "Mono8"}};
        if (config.lost_per_thousand > 0 && config.peer != "hc") {
          // As the packet-loss test of a peer that resends nothing: a lost packet is asked for
          // again within a few ms, and a frame still missing packets 20 ms on is counted lost.
          spec.options["frame_retention_ms"] = 20;
          spec.options["packet_timeout_ms"] = 5;
        }
        rig.sensors.push_back(spec);
      }
      RecorderOptions options;
      options.seconds = seconds;
      options.codec = config.codec;
      if (config.peer == "arv") {
        options.trigger_phase_s = 0.020;  // mid-way between the fakes' 40 ms trigger ticks
      } else {
        options.sync_tolerance_ns = static_cast<int64_t>(0.5e9 / config.fps);  // as the tests
      }
      const auto take = out / ("take-" + std::to_string(config.width) + "-" + config.codec + "-" +
                               std::to_string(static_cast<int>(config.fps)) + "-" +
                               std::to_string(static_cast<int>(config.tick_hz)) + "-" +
                               std::to_string(config.lost_per_thousand) + "-" + config.pattern);
      Recorder recorder(rig, take, options, registry);
      RecorderSummary summary = recorder.Run();
      int64_t triggers = 0, resends = 0, resent = 0;
      for (const auto& sensor : summary.sensors) {
        triggers = std::max(triggers, sensor.triggers);
        resends += sensor.driver.value("n_resend_requests", int64_t{0});
        resent += sensor.driver.value("n_resent_packets", int64_t{0});
      }
      const double rig_mb_s = config.cameras * config.width * config.height * config.fps / 1e6;
      std::printf(
          "%-5s %-4d %-5s %-4d %4dx%-4d %-4.0f %-5s %8.1f %10.2f %7.2f%% %5lld/%-5lld %7lld %8lld "
          "%8lld %9.2f %8.2f%s\n",
          config.peer.c_str(), config.lost_per_thousand, config.pattern.c_str(), config.cameras,
          config.width, config.height, config.fps, config.codec.c_str(), rig_mb_s,
          summary.write_mb_s, 100.0 * summary.write_mb_s / disk,
          static_cast<long long>(summary.frame_sets_complete), static_cast<long long>(triggers),
          static_cast<long long>(summary.frames_dropped), static_cast<long long>(resends),
          static_cast<long long>(resent), summary.sync_spread_us_max / 1e3,
          summary.sync_spread_us_mean / 1e3,
          summary.termination == Termination::kSuccess ? "" : ("  " + summary.message).c_str());
      std::fflush(stdout);
      char text[160];
      std::snprintf(text, sizeof(text), "%d x %dx%d x %.0f fps = %.1f MB/s (%s, %s, %s frames)",
                    config.cameras, config.width, config.height, config.fps, rig_mb_s,
                    config.codec.c_str(), config.peer.c_str(), config.pattern.c_str());
      const bool ok = summary.termination == Termination::kSuccess;
      if (ok && summary.frames_dropped == 0 && rig_mb_s > best_zero_drop) {
        best_zero_drop = rig_mb_s;
        best_text = text;
      }
      // The fake cameras now and then acknowledge a trigger and send nothing for it (a set or a
      // few in 1800 on a loaded two-core host), so the zero-drop line has a companion.
      if (ok && triggers > 0 && summary.frame_sets_complete * 1000 >= triggers * 995 &&
          rig_mb_s > best_nearly) {
        best_nearly = rig_mb_s;
        best_nearly_text = text;
      }
      std::filesystem::remove_all(take);
    }
    std::printf("\nlargest rig rate recorded with zero drops: %s\n", best_text.c_str());
    std::printf("largest rig rate with at least 99.5%% of triggered sets complete: %s\n",
                best_nearly_text.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "capture_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
