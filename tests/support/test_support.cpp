#include "tests/support/test_support.h"

#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <opencv2/imgproc.hpp>
#include <random>

#include "core/error.h"
#include "core/image.h"

namespace holocap::testing {

TempDir::TempDir(const std::string& prefix) {
  std::random_device device;
  for (int attempt = 0; attempt < 100; ++attempt) {
    auto candidate = std::filesystem::temp_directory_path() /
                     (prefix + "-" + std::to_string(getpid()) + "-" + std::to_string(device()));
    if (std::filesystem::create_directory(candidate)) {
      path_ = candidate;
      return;
    }
  }
  Fail("cannot create a temporary directory");
}

TempDir::~TempDir() {
  std::error_code ignored;
  std::filesystem::remove_all(path_, ignored);
}

std::filesystem::path TestDataDir() { return HOLOCAP_TEST_DATA_DIR; }
std::filesystem::path SourceDir() { return HOLOCAP_SOURCE_DIR; }
std::string CliPath() { return HOLOCAP_CLI; }

CommandResult RunShell(const std::string& command) {
  CommandResult result;
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) Fail("cannot run: ", command);
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0)
    result.output.append(buffer.data(), n);
  int status = pclose(pipe);
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  return result;
}

CommandResult RunCli(const std::string& args) {
  return RunShell("HOLOCAP_NO_PROGRESS=1 '" + CliPath() + "' " + args);
}

TakeSelection TrueCameras() {
  TakeSelection selection;
  selection.ground_truth_cameras = true;
  return selection;
}

void ExpectOneLineError(const CommandResult& result, const std::string& needle) {
  EXPECT_NE(result.exit_code, 0) << result.output;
  std::string output = result.output;
  while (!output.empty() && output.back() == '\n') output.pop_back();
  EXPECT_EQ(output.find('\n'), std::string::npos) << "more than one line:\n" << result.output;
  EXPECT_EQ(output.rfind("holocap: error: ", 0), 0u) << result.output;
  EXPECT_NE(output.find(needle), std::string::npos) << "expected '" << needle << "' in: " << output;
}

void CutHolesAndCrack(const std::filesystem::path& take) {
  for (const auto& entry : std::filesystem::directory_iterator(take / "gt" / "masks")) {
    const std::filesystem::path frame = take / "frames" / entry.path().filename() / "000000.png";
    const cv::Mat truth = ReadImage(entry.path() / "000000.png");
    cv::Mat image = ReadImage(frame);
    const cv::Rect box = cv::boundingRect(truth);
    for (int i = 0; i < 8; ++i) {
      const cv::Point at(box.x + box.width * (1 + i % 4) / 5, box.y + box.height * (1 + i / 4) / 3);
      if (truth.at<uint8_t>(at) != 0) cv::circle(image, at, 1 + i % 2, cv::Scalar::all(0), -1);
    }
    cv::line(image, cv::Point(box.x, box.y + box.height / 2),
             cv::Point(box.x + box.width, box.y + box.height * 5 / 8), cv::Scalar::all(0), 2);
    WriteImage(frame, image);
  }
}

}  // namespace holocap::testing
