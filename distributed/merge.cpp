#include "distributed/merge.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include "core/check_option.h"
#include "core/error.h"

namespace holocap {

void MergeOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(tolerance_ns, 0);
  HOLOCAP_CHECK_OPTION(IsOneOf(match, {"auto", "timestamp", "sequence"}), match);
  HOLOCAP_CHECK_OPTION_IN(writer_threads, 1, 64);
}

nlohmann::json MergePartRecord::ToJson() const {
  return {{"node", node},           {"part", part.string()},  {"state", state},
          {"sets", sets},           {"merged", merged},       {"missed", missed},
          {"discarded", discarded}, {"offset_ns", offset_ns}, {"offset_source", offset_source}};
}

nlohmann::json MergeSummary::Metrics() const {
  nlohmann::json json = {{"match", match},
                         {"slots", slots},
                         {"sets_complete", sets_complete},
                         {"sets_incomplete", sets_incomplete},
                         {"spread_us_max", spread_us_max},
                         {"spread_us_mean", spread_us_mean},
                         {"seconds", seconds},
                         {"parts", nlohmann::json::array()}};
  for (const auto& part : parts) json["parts"].push_back(part.ToJson());
  return json;
}

namespace {

// One frame set of a part: where it is, and when (corrected to the common clock).
struct PartSet {
  size_t entry = 0;
  int64_t time_ns = 0;
  uint64_t sequence = 0;
  int64_t slot = 0;
};

struct Part {
  Take take;
  MergePartRecord record;
  std::vector<PartSet> sets;
};

int64_t Median(std::vector<int64_t> values) {
  std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
  return values[values.size() / 2];
}

// The merge as named steps over the parts; state in members.
class Merger {
 public:
  Merger(const std::vector<std::filesystem::path>& parts, std::filesystem::path out,
         MergeOptions options, Report* report)
      : paths_(parts), out_(std::move(out)), options_(std::move(options)), report_(report) {}

  MergeSummary Run() {
    const auto start = std::chrono::steady_clock::now();
    OpenParts();
    CheckCompatible();
    AssignSlots();
    FormSets();
    Write();
    summary_.seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    Conclude();
    return summary_;
  }

 private:
  void OpenParts() {
    if (paths_.empty()) Fail("merge: give at least one part");
    for (const auto& path : paths_) {
      Part part{Take::Open(path), {}, {}};
      const nlohmann::json node = part.take.metadata().value("node", nlohmann::json::object());
      part.record.part = path;
      part.record.node = node.value("name", path.filename().string());
      part.record.state = part.take.state();
      part.record.sets = static_cast<int64_t>(part.take.size());
      const nlohmann::json clock = node.value("clock", nlohmann::json::object());
      part.record.offset_ns = clock.value("offset_ns", int64_t{0});
      part.record.offset_source = clock.value("offset_source", std::string("none recorded"));
      parts_.push_back(std::move(part));
    }
  }

  void CheckCompatible() {
    const RigDescription& first = parts_[0].take.rig();
    std::set<std::string> sensors, nodes;
    std::string clock;
    for (const Part& part : parts_) {
      const RigDescription& rig = part.take.rig();
      if (std::abs(rig.fps - first.fps) > 1e-9 || rig.sync != first.sync) {
        Fail("merge: part '", part.record.part.string(), "' was recorded at ", rig.fps, " fps (",
             ToString(rig.sync), "), '", paths_[0].string(), "' at ", first.fps, " fps (",
             ToString(first.sync), ")");
      }
      if (!nodes.insert(part.record.node).second)
        Fail("merge: two parts were recorded by node '", part.record.node, "'");
      for (const StreamInfo& stream : part.take.streams()) {
        if (!sensors.insert(stream.name).second)
          Fail("merge: sensor '", stream.name, "' is in two parts (the second: '",
               part.record.part.string(), "')");
        if (clock.empty()) clock = stream.clock;
        if (stream.clock != clock || clock.rfind("device:", 0) == 0)
          clock_mismatch_ = Cat("sensor '", stream.name, "' stamps in clock '", stream.clock,
                                "', another in '", clock, "'");
      }
    }
    period_ns_ = static_cast<int64_t>(std::llround(1e9 / first.fps));
    tolerance_ns_ =
        options_.tolerance_ns > 0 ? options_.tolerance_ns : static_cast<int64_t>(0.4 * period_ns_);
    summary_.match = options_.match != "auto"                   ? options_.match
                     : first.sync == SyncMode::kHardwareTrigger ? "sequence"
                                                                : "timestamp";
    if (!clock_mismatch_.empty())
      Fail("merge: the parts' timestamps cannot be compared (", clock_mismatch_, ")");
  }

  // Each set's time (mean of its frames', corrected by its node's offset) and its slot.
  void AssignSlots() {
    int64_t reference = 0;
    bool have_reference = false;
    for (Part& part : parts_) {
      for (size_t i = 0; i < part.take.size(); ++i) {
        const FrameSetEntry& entry = part.take.entry(i);
        if (entry.items.empty()) continue;
        long double sum = 0;
        for (const auto& item : entry.items) sum += item.timestamp_ns;
        const int64_t time =
            static_cast<int64_t>(std::llround(sum / entry.items.size())) - part.record.offset_ns;
        part.sets.push_back({i, time, entry.items.front().sequence, 0});
        if (!have_reference || time < reference) reference = time;
        have_reference = true;
      }
    }
    for (Part& part : parts_) {
      for (PartSet& set : part.sets) {
        set.slot = static_cast<int64_t>(
            std::llround(static_cast<double>(set.time_ns - reference) / period_ns_));
      }
      if (summary_.match == "sequence" && !part.sets.empty()) {
        // The counters of each part aligned once by timestamp: the median of counter minus
        // time slot over its first sets.
        std::vector<int64_t> shifts;
        for (size_t k = 0; k < std::min<size_t>(part.sets.size(), 15); ++k)
          shifts.push_back(static_cast<int64_t>(part.sets[k].sequence) - part.sets[k].slot);
        const int64_t base = Median(shifts);
        for (PartSet& set : part.sets) set.slot = static_cast<int64_t>(set.sequence) - base;
      }
    }
  }

  void FormSets() {
    const size_t n = parts_.size();
    std::map<int64_t, std::vector<const PartSet*>> slots;
    for (size_t p = 0; p < n; ++p) {
      for (const PartSet& set : parts_[p].sets) {
        auto& members = slots.try_emplace(set.slot, n, nullptr).first->second;
        if (members[p] != nullptr) {
          ++parts_[p].record.discarded;  // a second set of one node in one slot
          continue;
        }
        members[p] = &set;
      }
    }
    if (slots.empty()) return;
    const int64_t first = slots.begin()->first, last = slots.rbegin()->first;
    summary_.slots = last - first + 1;
    double spread_sum = 0;
    for (int64_t slot = first; slot <= last; ++slot) {
      auto found = slots.find(slot);
      std::vector<const PartSet*> members =
          found == slots.end() ? std::vector<const PartSet*>(n, nullptr) : found->second;
      int64_t low = INT64_MAX, high = INT64_MIN;
      bool complete = true;
      for (size_t p = 0; p < n; ++p) {
        if (members[p] == nullptr) {
          complete = false;
          continue;
        }
        low = std::min(low, members[p]->time_ns);
        high = std::max(high, members[p]->time_ns);
      }
      const bool within = complete && high - low <= tolerance_ns_;
      if (!within) {
        ++summary_.sets_incomplete;
        for (size_t p = 0; p < n; ++p) {
          if (members[p] == nullptr) {
            ++parts_[p].record.missed;
          } else {
            ++parts_[p].record.discarded;
          }
        }
        continue;
      }
      std::vector<size_t> entries;
      for (size_t p = 0; p < n; ++p) {
        entries.push_back(members[p]->entry);
        ++parts_[p].record.merged;
      }
      merged_.push_back(std::move(entries));
      const double spread_us = (high - low) / 1e3;
      summary_.spread_us_max = std::max(summary_.spread_us_max, spread_us);
      spread_sum += spread_us;
    }
    summary_.sets_complete = static_cast<int64_t>(merged_.size());
    if (!merged_.empty()) summary_.spread_us_mean = spread_sum / merged_.size();
  }

  nlohmann::json Metadata() const {
    nlohmann::json parts = nlohmann::json::array();
    for (const Part& part : parts_) {
      nlohmann::json item = part.record.ToJson();
      item["node_metadata"] = part.take.metadata().value("node", nlohmann::json::object());
      parts.push_back(item);
    }
    return {{"capture", parts_[0].take.metadata().value("capture", nlohmann::json::object())},
            {"merge",
             {{"match", summary_.match},
              {"tolerance_ns", tolerance_ns_},
              {"timestamps", "each node's corrected by its clock offset"},
              {"parts", parts}}}};
  }

  void Write() {
    RigDescription rig = parts_[0].take.rig();
    rig.sensors.clear();
    std::vector<StreamInfo> streams;
    for (const Part& part : parts_) {
      for (const auto& spec : part.take.rig().sensors) rig.sensors.push_back(spec);
      for (const auto& [host, address] : part.take.rig().hosts) rig.hosts[host] = address;
      for (const StreamInfo& stream : part.take.streams()) streams.push_back(stream);
    }
    TakeWriterOptions take_options;
    take_options.overwrite = options_.overwrite;
    take_options.command = "merge";
    take_options.inputs = paths_;
    TakeWriter writer(out_, rig, streams, Metadata(), take_options);
    for (const Part& part : parts_) {
      for (const StreamInfo& stream : part.take.streams())
        if (part.record.missed > 0) writer.CountDropped(stream.name, part.record.missed);
    }
    std::atomic<size_t> next{0};
    std::mutex error_mutex;
    std::string error;
    auto work = [&] {
      for (size_t k = next++; k < merged_.size(); k = next++) {
        try {
          FrameSet set;
          set.index = static_cast<int64_t>(k);
          for (size_t p = 0; p < parts_.size(); ++p) {
            FrameSet own = parts_[p].take.Read(merged_[k][p]);
            for (Frame& frame : own.frames) {
              frame.timestamp_ns -= parts_[p].record.offset_ns;
              set.frames.push_back(std::move(frame));
            }
          }
          writer.Append(set);
          if (report_ != nullptr && k % 30 == 0)
            report_->AddPoint("sets_written", static_cast<double>(k + 1), static_cast<int64_t>(k));
        } catch (const Error& e) {
          std::lock_guard lock(error_mutex);
          if (error.empty()) error = e.what();
          next = merged_.size();
        }
      }
    };
    std::vector<std::thread> threads;
    for (int t = 0; t < options_.writer_threads; ++t) threads.emplace_back(work);
    for (auto& thread : threads) thread.join();
    if (!error.empty()) Fail("merge: ", error);
    writer.Close();
  }

  void Conclude() {
    std::string missed, cut_short;
    for (const Part& part : parts_) {
      summary_.parts.push_back(part.record);
      missed += Cat(missed.empty() ? "" : ", ", part.record.node, " ", part.record.missed);
      if (part.record.state != "complete") {
        cut_short +=
            Cat(cut_short.empty() ? "" : "; ", "node '", part.record.node,
                "' stopped mid-take (its part is cut short after ", part.record.sets, " sets)");
      }
    }
    const std::string counts =
        Cat(summary_.sets_complete, " frame sets merged from ", parts_.size(), " parts, ",
            summary_.sets_incomplete, " of ", summary_.slots,
            " slots incomplete (missed by node: ", missed, ")");
    if (!cut_short.empty()) {
      summary_.End(Termination::kFailure, Cat(cut_short, "; ", counts));
    } else if (summary_.sets_complete == 0) {
      summary_.End(Termination::kDegenerate, Cat("no slot held a set of every part; ", counts));
    } else {
      summary_.End(Termination::kSuccess, counts);
    }
  }

  std::vector<std::filesystem::path> paths_;
  std::filesystem::path out_;
  MergeOptions options_;
  Report* report_;
  std::vector<Part> parts_;
  std::string clock_mismatch_;
  int64_t period_ns_ = 0;
  int64_t tolerance_ns_ = 0;
  std::vector<std::vector<size_t>> merged_;  // per merged set, each part's entry
  MergeSummary summary_;
};

}  // namespace

MergeSummary MergeParts(const std::vector<std::filesystem::path>& parts,
                        const std::filesystem::path& out, const MergeOptions& options,
                        Report* report) {
  options.Check();
  return Merger(parts, out, options, report).Run();
}

}  // namespace holocap
