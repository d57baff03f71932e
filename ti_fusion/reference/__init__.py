"""NumPy float64 references of the Taichi kernels: the tests' oracles and the benchmarks' baselines."""
