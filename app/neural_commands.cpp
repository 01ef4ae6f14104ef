// In holocap: the commands that need LibTorch are handed to holocap-neural, beside this program;
// `holocap --help` still lists them. In holocap-neural (HOLOCAP_WITH_NEURAL) nothing is handed
// over: the commands are its own.
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string_view>

#include "app/commands.h"

namespace holocap {

#ifdef HOLOCAP_WITH_NEURAL

void HandOverNeuralCommands(int, char**) {}

#else

namespace {

// `report ... --merge` of a run whose command lives in holocap-neural (train splat, export web):
// its merge writes that command's model or site. Other merges (reconstruct) stay here, without
// LibTorch's start.
bool MergesANeuralRun(int argc, char** argv) {
  bool merge = false;
  for (int i = 2; i < argc; ++i) merge = merge || std::string_view(argv[i]) == "--merge";
  for (int i = 2; i < argc && merge; ++i) {
    std::ifstream run(std::filesystem::path(argv[i]) / "run.json");
    const nlohmann::json json = nlohmann::json::parse(run, nullptr, /*allow_exceptions=*/false);
    const std::string command = json.is_object() ? json.value("command", "") : "";
    if (command == "train splat" || command == "export web") return true;
  }
  return false;
}

struct NeuralCommand {
  int order;  // the place the command's own HOLOCAP_COMMAND gives it in --help
  const char* name;
  const char* help;
};
constexpr NeuralCommand kNeuralCommands[] = {
    {60, "train", "Learn an avatar from a calibrated take: `train nvol` or `train rerender`"},
    {70, "render", "Render a trained avatar along a camera path to frames or an MP4"},
    {75, "view", "Serve a site of export web (or a take, exported first) on 127.0.0.1"},
    {100, "demo", "Run every pipeline stage on a small simulated studio8 take into out/demo/"},
};

// Listed in --help; never parsed here (HandOverNeuralCommands runs first).
const bool kListed = [] {
  for (const auto& command : kNeuralCommands) {
    CommandTable().push_back({command.order, [command](CLI::App& app) {
                                app.add_subcommand(command.name, command.help)->allow_extras();
                              }});
  }
  return true;
}();

}  // namespace

void HandOverNeuralCommands(int argc, char** argv) {
  if (argc < 2) return;
  const std::string_view word = argv[1];
  bool neural = false;
  for (const auto& command : kNeuralCommands) neural = neural || word == command.name;
  // export web bakes volumes; the other formats stay here.
  neural = neural || (word == "export" && argc > 2 && std::string_view(argv[2]) == "web");
  neural = neural || (word == "report" && MergesANeuralRun(argc, argv));
  if (!neural) return;
  std::error_code ec;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
  const std::filesystem::path program =
      (ec ? std::filesystem::path(argv[0]).parent_path() : self.parent_path()) / "holocap-neural";
  ::execv(program.c_str(), argv);
  std::fprintf(stderr, "holocap: error: holocap %s runs in '%s', which cannot be started: %s\n",
               argv[1], program.c_str(), std::strerror(errno));
  std::exit(1);
}

#endif

}  // namespace holocap
