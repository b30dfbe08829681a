"""Independent reference computations for the tests (and the benchmarks that sample them)."""
