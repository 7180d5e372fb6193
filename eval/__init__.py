"""Ground-truth matching, scoring, the end-to-end harness, sweeps and benchmarks."""
