"""NumPy references of the Taichi kernels, the tests' oracles and the benchmarks' baselines: ``icp`` (one
ICP pass in float64) and ``fusion`` (the fusion step on the map's float32 arrays)."""
