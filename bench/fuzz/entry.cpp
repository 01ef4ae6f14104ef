// libFuzzer's entry of one fuzz_<target> executable; HOLOCAP_FUZZ_TARGET names the target.
#include "bench/fuzz/targets.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return holocap::fuzz::RunTarget(HOLOCAP_FUZZ_TARGET, data, size);
}
