// Joining the parts that capture nodes recorded (each one a take of its own host's sensors) into
// one take. Parts are recordings: the merge reads them and never writes into them.
//
// Every part's set is placed in a slot of the rig's frame period: by its timestamps after the
// node's recorded clock offset (take.json metadata "node.clock.offset_ns"), or, where triggers
// are shared (hardware sync), by its frame counter, the counters of each part aligned to the
// others once by timestamp. A slot holding one set of every part, their times within the
// tolerance, is a merged frame set; any other slot in the take's span is counted as missed
// against each node that has no set there (never torn: no merged set lacks a sensor), and the
// frames the other nodes had for it are counted as discarded.
#pragma once

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/report.h"
#include "core/take.h"

namespace holocap {

struct MergeOptions {
  // Largest spread of a merged set's node times (ns, after clock offsets). 0: 0.4 periods.
  int64_t tolerance_ns = 0;
  // "auto" (frame counters for hardware-triggered rigs, else timestamps), "timestamp",
  // "sequence".
  std::string match = "auto";
  int writer_threads = 2;  // threads decoding parts' frames and writing the merged take
  bool overwrite = false;  // replace an existing merged take (never a capture's recording)

  void Check() const;  // throws Error explaining a bad value
};

// What happened to one part.
struct MergePartRecord {
  std::string node;  // the node that recorded it (its metadata, else the folder's name)
  std::filesystem::path part;
  std::string state;          // the part's take state: "complete", or "recording" (cut short)
  int64_t sets = 0;           // frame sets in the part
  int64_t merged = 0;         // of them, in the merged take
  int64_t missed = 0;         // slots of the take's span in which it had no set
  int64_t discarded = 0;      // its sets in slots another node missed
  int64_t offset_ns = 0;      // the clock offset its times were corrected by
  std::string offset_source;  // where that offset came from

  nlohmann::json ToJson() const;
};

struct MergeSummary : Summary {
  std::string match;            // "timestamp" or "sequence": how slots were formed
  int64_t slots = 0;            // slots in the take's span (first to last set of any part)
  int64_t sets_complete = 0;    // merged frame sets written
  int64_t sets_incomplete = 0;  // slots some node missed
  double spread_us_max = 0;     // across nodes, after offsets, over merged sets
  double spread_us_mean = 0;
  double seconds = 0;
  std::vector<MergePartRecord> parts;

  nlohmann::json Metrics() const;
};

// Merges `parts` into a new take at `out`. Throws Error for unusable input (a part that is not a
// take, sensor names shared by two parts, differing frame rates, timestamps in clocks that
// cannot be compared). A part that was cut short (state "recording") makes the summary FAILURE
// naming its node; the merged take still holds every complete set.
MergeSummary MergeParts(const std::vector<std::filesystem::path>& parts,
                        const std::filesystem::path& out, const MergeOptions& options,
                        Report* report = nullptr);

}  // namespace holocap
