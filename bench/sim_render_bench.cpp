// Simulated-rig throughput: frame sets per minute of SimulateTake (render + encode + write)
// for the built-in rigs and scenes, the share spent rendering, and the process CPU time, which
// shows whether other load shared the cores (cpu_s / total_s well below the core count). Usage:
//   sim_render_bench [frames=6] [threads=0 (all cores)] [out_dir=/tmp] [only_case=-1 (all)]
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <string>

#include "sim/sim.h"

int main(int argc, char** argv) {
  const int frames = argc > 1 ? std::atoi(argv[1]) : 6;
  const int threads = argc > 2 ? std::atoi(argv[2]) : 0;
  const std::filesystem::path out_dir = argc > 3 ? argv[3] : "/tmp";
  const int only_case = argc > 4 ? std::atoi(argv[4]) : -1;
  struct Case {
    const char* rig;
    const char* scene;
    int width;
    int antialias;
    bool motion_blur;
  };
  const Case cases[] = {
      {"studio8", "subject", 0, 4, false},   {"studio8", "subject", 0, 1, false},
      {"studio8", "subject", 320, 4, false}, {"studio8", "board", 0, 4, false},
      {"studio8", "subject", 0, 4, true},    {"single-rgbd", "subject", 0, 4, false},
  };
  std::printf("%-12s %-8s %-8s %-3s %-5s %5s %8s %9s %8s %12s\n", "rig", "scene", "size", "aa",
              "blur", "sets", "total_s", "render_s", "cpu_s", "sets/minute");
  int index = -1;
  for (const Case& c : cases) {
    if (++index != only_case && only_case >= 0) continue;
    holocap::SimOptions options;
    options.rig = c.rig;
    options.scene = c.scene;
    options.frames = frames;
    options.image_width = c.width;
    options.antialias = c.antialias;
    options.motion_blur = c.motion_blur;
    options.threads = threads;
    options.overwrite = true;
    const std::filesystem::path out = out_dir / "holocap-sim-bench";
    std::filesystem::remove_all(out);
    const std::clock_t cpu_start = std::clock();
    const holocap::SimSummary summary = holocap::SimulateTake(options, out);
    const double cpu_seconds = static_cast<double>(std::clock() - cpu_start) / CLOCKS_PER_SEC;
    std::filesystem::remove_all(out);
    std::printf("%-12s %-8s %-8s %-3d %-5s %5lld %8.2f %9.2f %8.2f %12.1f%s\n", c.rig, c.scene,
                c.width == 0 ? "native" : std::to_string(c.width).c_str(), c.antialias,
                c.motion_blur ? "yes" : "no", static_cast<long long>(summary.frame_sets),
                summary.seconds, summary.render_seconds, cpu_seconds, summary.frame_sets_per_minute,
                holocap::IsUsable(summary.termination) ? "" : "  (failed)");
  }
  return 0;
}
