// The two programs from one set of commands: holocap, without LibTorch, and holocap-neural,
// with it (HOLOCAP_WITH_NEURAL). A command registered as needing LibTorch is listed by holocap
// and handed to holocap-neural, its neighbour in the same folder, with the same arguments.
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <sstream>
#include <vector>

#include "app/commands.h"
#include "core/error.h"

namespace holocap {
namespace {

std::vector<char*>& ProgramArguments() {
  static std::vector<char*> arguments;
  return arguments;
}

}  // namespace

void SetProgramArguments(int argc, char** argv) {
  ProgramArguments().assign(argv, argv + argc);
  ProgramArguments().push_back(nullptr);
}

bool ProgramHasLibTorch() {
#if HOLOCAP_WITH_NEURAL
  return true;
#else
  return false;
#endif
}

CLI::App* AddCommandAt(CLI::App& app, const std::string& path, const std::string& help) {
  std::vector<std::string> words;
  std::stringstream in(path);
  for (std::string word; in >> word;) words.push_back(word);
  if (words.empty()) Fail("a command needs a name");
  CLI::App* parent = &app;
  for (size_t i = 0; i + 1 < words.size(); ++i) {
    CLI::App* found = nullptr;
    for (CLI::App* sub :
         parent->get_subcommands([&](CLI::App* s) { return s->get_name() == words[i]; }))
      found = sub;
    parent = found != nullptr ? found : parent->add_subcommand(words[i]);
  }
  return parent->add_subcommand(words.back(), help);
}

void AddHandedOverCommand(CLI::App* command) {
  // Everything after the command's name is holocap-neural's to parse, --help included.
  command->set_help_flag();
  command->allow_extras();
  command->prefix_command();
  command->callback([command] { HandOverToLibTorchProgram("holocap " + command->get_name()); });
}

void HandOverToLibTorchProgram(const std::string& what) {
  if (ProgramHasLibTorch() || ProgramArguments().size() < 2)
    Fail(what, " has nothing to hand over to: this program links LibTorch itself");
  std::fflush(stdout);
  std::error_code ec;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
  const std::filesystem::path program =
      (ec ? std::filesystem::path(ProgramArguments()[0]).parent_path() : self.parent_path()) /
      "holocap-neural";
  ::execv(program.c_str(), ProgramArguments().data());
  std::fprintf(stderr, "holocap: error: %s runs in '%s', which cannot be started: %s\n",
               what.c_str(), program.c_str(), std::strerror(errno));
  std::exit(1);
}

}  // namespace holocap
