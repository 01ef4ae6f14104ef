// core/output.h: which take holds a path, the take lock within one process, and the claims'
// refusals that need no CLI.
#include "core/output.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/file.h>
#include <unistd.h>

#include <fstream>

#include "core/error.h"
#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;
namespace fs = std::filesystem;

// Whether another open file description can take the take's lock now.
bool LockIsFree(const fs::path& take) {
  const int fd = ::open((take / kTakeLockFile).c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) return false;
  const bool free = ::flock(fd, LOCK_EX | LOCK_NB) == 0;
  ::close(fd);
  return free;
}

TEST(Output, EnclosingTakeIsTheNearestFolderWithATakeJson) {
  TempDir dir;
  fs::create_directories(dir / "t/frames/cam0");
  std::ofstream(dir / "t/take.json") << "{}";
  EXPECT_EQ(EnclosingTake(dir / "t/frames/cam0/000000.png"), fs::canonical(dir / "t"));
  EXPECT_EQ(EnclosingTake(dir / "t/recon/not-yet"), fs::canonical(dir / "t"));
  EXPECT_EQ(EnclosingTake(dir / "t/../elsewhere"), std::nullopt);
}

// One process may claim two outputs in one take (the demo does); the lock ends with the last.
TEST(Output, TheTakeLockIsCountedWithinAProcessAndFreedByTheLast) {
  TempDir dir;
  fs::create_directories(dir / "t");
  std::ofstream(dir / "t/take.json") << "{}";
  {
    const OutputDirectory recon = OutputDirectory::Claim(dir / "t/recon", {"reconstruct"});
    {
      const TakeLock again = TakeLock::Acquire(dir / "t", "train nvol");
      EXPECT_TRUE(again.held());
      EXPECT_FALSE(LockIsFree(dir / "t"));
    }
    EXPECT_FALSE(LockIsFree(dir / "t")) << "the first claim still holds it";
    EXPECT_NE(ReadFileToString(dir / "t" / kTakeLockFile).find(std::to_string(::getpid())),
              std::string::npos);
  }
  EXPECT_TRUE(LockIsFree(dir / "t"));
  EXPECT_THROW(TakeLock::Acquire(dir / "missing", "calibrate"), Error);
}

TEST(Output, AnOutputFileIsReplacedOnlyWithOverwrite) {
  TempDir dir;
  std::ofstream(dir / "board.png") << "printed";
  EXPECT_THROW(ClaimOutputFile(dir / "board.png", {"board"}), Error);
  EXPECT_NO_THROW(ClaimOutputFile(dir / "board.png", {"board", true}));
  EXPECT_THROW(ClaimOutputFile(dir / "layout.yaml", {"board", true, {dir / "layout.yaml"}}), Error);
  EXPECT_EQ(ReadFileToString(dir / "board.png"), "printed");  // a claim writes nothing
}

// The tasks of a sharded run claim one new folder at the same moment: a folder holding only
// another task's marker, still a temporary file, is claimed as new; anything else in a folder
// without a marker is refused.
TEST(Output, AMarkerBeingWrittenByAnotherTaskIsNoStrangerOutput) {
  TempDir dir;
  fs::create_directories(dir / "site");
  std::ofstream(dir / "site" / (std::string(kOutputMarkerFile) + ".tmp4242_17")) << "export web\n";
  EXPECT_NO_THROW(OutputDirectory::Claim(dir / "site", {"export web"}));
  EXPECT_EQ(ReadFileToString(dir / "site" / kOutputMarkerFile), "export web\n");
  fs::create_directories(dir / "other");
  std::ofstream(dir / "other" / "notes.txt") << "mine";
  EXPECT_THROW(OutputDirectory::Claim(dir / "other", {"export web"}), Error);
}

}  // namespace
}  // namespace holocap
