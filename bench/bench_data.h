// Data sets the benches share, read from the repository's tests/data.
#pragma once

#include <filesystem>

#include "interop/interop.h"

namespace holocap::bench {

// Imports Middlebury dinoSparseRing (16 real views of one frame) into `root`/dino once and
// returns the take's directory; a take already there is reused.
inline std::filesystem::path ImportDinoOnce(const std::filesystem::path& root) {
  const std::filesystem::path source = std::filesystem::path(HOLOCAP_TEST_DATA_DIR) / "middlebury" /
                                       "dinoSparseRing" / "dinoSR_par.txt";
  std::filesystem::path take = root / "dino";
  if (!std::filesystem::exists(take / "take.json")) {
    ImportOptions import;
    import.format = InteropFormat::kMiddlebury;
    import.overwrite = true;
    ImportTake(source, take, import);
  }
  return take;
}

}  // namespace holocap::bench
