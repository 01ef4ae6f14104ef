// The parsers' libFuzzer targets. Each fuzz_<target> executable (CMakeLists.txt) feeds
// libFuzzer's inputs to one of them; corpus/<target>/ holds its seeds.
#pragma once

#include <cstddef>
#include <cstdint>

namespace holocap::fuzz {

// Parses `data` with the parser `target` names ("krt", "take_json", ...; an unknown name
// aborts). A parser may reject its input only with holocap::Error: any other exception aborts,
// and so does a file holocap wrote from a parsed result that does not read back. Returns 0.
int RunTarget(const char* target, const uint8_t* data, size_t size);

}  // namespace holocap::fuzz
