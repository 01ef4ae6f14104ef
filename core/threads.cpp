#include "core/threads.h"

#include <omp.h>

#include <algorithm>

namespace holocap {

int ResolveThreads(int requested) { return requested > 0 ? requested : omp_get_max_threads(); }

int ResolveThreads(int requested, int jobs) {
  return std::max(1, std::min(ResolveThreads(requested), std::max(1, jobs)));
}

}  // namespace holocap
