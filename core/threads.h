// How many threads a stage runs: one rule for every stage, so that `--threads 0` means the
// same everywhere.
#pragma once

namespace holocap {

// The most threads a stage starts: kThreadsPerCore a core OpenMP sees. More only queue on the
// same cores, and far more than the system can start make OpenMP fail (--threads 100000 once
// ended in a segmentation fault).
inline constexpr int kThreadsPerCore = 4;
int MachineThreadLimit();

// `requested` > 0 as is, otherwise every core OpenMP offers (OMP_NUM_THREADS, else the cores);
// either way no more than MachineThreadLimit(). The threads change no result, only its speed.
int ResolveThreads(int requested);

// The same, never more threads than `jobs` and never fewer than one.
int ResolveThreads(int requested, int jobs);

}  // namespace holocap
