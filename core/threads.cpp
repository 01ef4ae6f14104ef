#include "core/threads.h"

#include <omp.h>

#include <algorithm>

namespace holocap {

int MachineThreadLimit() { return kThreadsPerCore * std::max(1, omp_get_num_procs()); }

int ResolveThreads(int requested) {
  return std::min(requested > 0 ? requested : omp_get_max_threads(), MachineThreadLimit());
}

int ResolveThreads(int requested, int jobs) {
  return std::max(1, std::min(ResolveThreads(requested), std::max(1, jobs)));
}

}  // namespace holocap
