// Comparing two runs of a per-frame command: every mesh (splat model file, site file) the same
// bytes, and the same report and per-frame results once what only measures time (and where the run
// wrote) is left out.
#pragma once

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "core/frame_tasks.h"
#include "core/fs.h"
#include "tests/support/test_support.h"

namespace holocap::testing {

// `json` without what differs between two runs of the same work: times (every key ending in
// "seconds", t_s, elapsed_s, timing, peak_rss_mb), the seconds_per_frame series and the
// options naming the output directory.
inline nlohmann::json WithoutTimes(nlohmann::json json) {
  if (json.is_object()) {
    nlohmann::json out = nlohmann::json::object();
    for (auto& [key, value] : json.items()) {
      const bool time = key == "t_s" || key == "elapsed_s" || key == "timing" ||
                        key == "peak_rss_mb" || key == "out" ||
                        (key.size() >= 7 && key.compare(key.size() - 7, 7, "seconds") == 0);
      if (!time) out[key] = WithoutTimes(value);
    }
    return out;
  }
  if (json.is_array()) {
    nlohmann::json out = nlohmann::json::array();
    for (auto& value : json) {
      if (value.is_object() && value.value("metric", "") == "seconds_per_frame") continue;
      out.push_back(WithoutTimes(value));
    }
    return out;
  }
  return json;
}

inline nlohmann::json ReadJson(const std::filesystem::path& file) {
  return nlohmann::json::parse(ReadFileToString(file));
}

// When each complete set's record of the run in `dir` was written.
inline std::map<int64_t, double> RecordTimes(const std::filesystem::path& dir) {
  std::map<int64_t, double> finished;
  for (const auto& [set, record] : ReadRunState(dir).complete)
    finished[set] = record["finished_unix_s"].get<double>();
  return finished;
}

// The meshes (*.ply, *.glb) of an output directory: name -> bytes.
inline std::map<std::string, std::string> Meshes(const std::filesystem::path& out) {
  std::map<std::string, std::string> meshes;
  for (const auto& entry : std::filesystem::directory_iterator(out)) {
    const std::string ext = entry.path().extension().string();
    if (ext == ".ply" || ext == ".glb")
      meshes[entry.path().filename().string()] = ReadFileToString(entry.path());
  }
  return meshes;
}

// Every mesh of `expected` and `actual` the same bytes, the same report.json and per-frame
// results, times aside. Returns the number of meshes compared.
inline size_t ExpectSameRun(const std::filesystem::path& expected,
                            const std::filesystem::path& actual) {
  const auto a = Meshes(expected), b = Meshes(actual);
  EXPECT_EQ(a.size(), b.size());
  size_t same = 0;
  for (const auto& [name, bytes] : a) {
    const auto other = b.find(name);
    if (other == b.end()) {
      ADD_FAILURE() << name << " is missing from " << actual;
      continue;
    }
    EXPECT_EQ(bytes.size(), other->second.size()) << name;
    EXPECT_TRUE(bytes == other->second) << name << " differs";
    same += bytes == other->second;
  }
  const nlohmann::json report_a = ReadJson(expected / "report.json");
  const nlohmann::json report_b = ReadJson(actual / "report.json");
  EXPECT_EQ(WithoutTimes(report_a).dump(1), WithoutTimes(report_b).dump(1));
  const RunState run_a = ReadRunState(expected), run_b = ReadRunState(actual);
  EXPECT_EQ(run_a.fingerprint, run_b.fingerprint);
  EXPECT_EQ(run_a.complete.size(), run_b.complete.size());
  for (const auto& [set, record] : run_a.complete) {
    if (!run_b.complete.count(set)) {
      ADD_FAILURE() << "set " << set << " is not complete in " << actual;
      continue;
    }
    EXPECT_EQ(WithoutTimes(record["result"]).dump(),
              WithoutTimes(run_b.complete.at(set)["result"]).dump());
    EXPECT_EQ(record["outputs"], run_b.complete.at(set)["outputs"]) << "set " << set;
  }
  return same;
}

// The model's files: name (relative) -> bytes; what the run keeps for itself (records, plan,
// reports, logs) left out.
inline std::map<std::string, std::string> ModelFiles(const std::filesystem::path& dir) {
  std::map<std::string, std::string> files;
  for (const char* name : {"model.json", "gaussians.bin"})
    files[name] = ReadFileToString(dir / name);
  for (const char* folder : {"deltas", "cameras"}) {
    for (const auto& entry : std::filesystem::directory_iterator(dir / folder)) {
      const std::string name = (std::filesystem::path(folder) / entry.path().filename()).string();
      files[name] = ReadFileToString(entry.path());
    }
  }
  return files;
}

// The same report and frame records as the run in `expected`, times aside.
inline void ExpectSameReportAndRecords(const std::filesystem::path& expected,
                                       const std::filesystem::path& actual) {
  EXPECT_EQ(WithoutTimes(ReadJson(expected / "report.json")).dump(1),
            WithoutTimes(ReadJson(actual / "report.json")).dump(1));
  const RunState run_a = ReadRunState(expected), run_b = ReadRunState(actual);
  EXPECT_EQ(run_a.fingerprint, run_b.fingerprint);
  ASSERT_TRUE(run_b.done()) << run_b.Describe();
  for (const auto& [set, record] : run_a.complete) {
    EXPECT_EQ(WithoutTimes(record["result"]).dump(),
              WithoutTimes(run_b.complete.at(set)["result"]).dump());
  }
}

// Every file of `a` in `b` with the same bytes, and no other.
inline void ExpectSameFiles(const std::map<std::string, std::string>& a,
                            const std::map<std::string, std::string>& b,
                            const std::filesystem::path& actual) {
  ASSERT_EQ(a.size(), b.size()) << actual;
  for (const auto& [name, bytes] : a) {
    ASSERT_TRUE(b.count(name)) << name << " is missing from " << actual;
    EXPECT_TRUE(bytes == b.at(name)) << name << " differs";
  }
}

// The same model bytes, report and frame records as `expected`, times aside.
inline void ExpectSameModel(const std::filesystem::path& expected,
                            const std::filesystem::path& actual) {
  ExpectSameFiles(ModelFiles(expected), ModelFiles(actual), actual);
  ExpectSameReportAndRecords(expected, actual);
}

// What a player reads of a site (manifest.json, index.html, player/, streams/): name (relative)
// -> bytes; what the run keeps for itself (records, plan, reports, logs) left out.
inline std::map<std::string, std::string> SiteFiles(const std::filesystem::path& site) {
  std::map<std::string, std::string> files;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(site)) {
    const std::string name = std::filesystem::relative(entry.path(), site).string();
    const std::string top = name.substr(0, name.find('/'));
    if (entry.is_regular_file() &&
        (top == "manifest.json" || top == "index.html" || top == "player" || top == "streams"))
      files[name] = ReadFileToString(entry.path());
  }
  return files;
}

// The same site bytes, report and group records as `expected`, times aside.
inline void ExpectSameSite(const std::filesystem::path& expected,
                           const std::filesystem::path& actual) {
  const auto a = SiteFiles(expected);
  ASSERT_TRUE(a.count("manifest.json")) << expected;
  ExpectSameFiles(a, SiteFiles(actual), actual);
  ExpectSameReportAndRecords(expected, actual);
}

// Runs `holocap ARGS` (a shell word list) and kills it (SIGKILL) as soon as `record` exists;
// true when the command was killed, false when it ended before (or never wrote the record in
// two minutes and was killed then, which the caller's checks of the records tell apart).
inline bool KillWhenRecorded(const std::string& args, const std::filesystem::path& record) {
  const pid_t child = fork();
  if (child < 0) return false;
  if (child == 0) {
    execl("/bin/sh", "sh", "-c", ("exec " + CliPath() + " " + args).c_str(),
          static_cast<char*>(nullptr));
    _exit(127);
  }
  int polls = 0;
  while (polls++ < 60000 && !std::filesystem::exists(record))
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  kill(child, SIGKILL);
  int status = 0;
  waitpid(child, &status, 0);
  return WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL;
}

}  // namespace holocap::testing
