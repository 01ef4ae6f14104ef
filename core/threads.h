// How many threads a stage runs: one rule for every stage, so that `--threads 0` means the
// same everywhere.
#pragma once

namespace holocap {

// `requested` > 0 as is, otherwise every core OpenMP offers (OMP_NUM_THREADS, else the cores).
int ResolveThreads(int requested);

// The same, never more threads than `jobs` and never fewer than one.
int ResolveThreads(int requested, int jobs);

}  // namespace holocap
