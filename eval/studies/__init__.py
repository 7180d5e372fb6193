"""Studies over plant sets: the eval recipe, sweeps, the robustness report, tuning, the guard,
the benchmarks, fidelity and the results pages."""
