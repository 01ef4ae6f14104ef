#include "core/threads.h"

#include <gtest/gtest.h>
#include <omp.h>

namespace holocap {
namespace {

// A thread count past what the machine can run is its limit (--threads 100000 once crashed
// OpenMP); 0 is every core; a count within the limit is kept as asked.
TEST(Threads, CountsPastTheMachineAreItsLimit) {
  const int limit = MachineThreadLimit();
  EXPECT_EQ(limit, kThreadsPerCore * omp_get_num_procs());
  EXPECT_EQ(ResolveThreads(100000), limit);
  EXPECT_EQ(ResolveThreads(limit + 1), limit);
  EXPECT_EQ(ResolveThreads(1), 1);
  EXPECT_EQ(ResolveThreads(limit), limit);
  EXPECT_GE(ResolveThreads(0), 1);
  EXPECT_LE(ResolveThreads(0), limit);
  EXPECT_EQ(ResolveThreads(100000, 3), 3);
  EXPECT_EQ(ResolveThreads(2, 0), 1);
}

}  // namespace
}  // namespace holocap
