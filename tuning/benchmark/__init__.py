"""The benchmarks: workload W1 against its peers, the C ceiling kernel, fixed costs."""
