"""Taichi kernels of ti-fusion (imported as ``ti_fusion.kernels``).

Every kernel here has a NumPy float64 reference in ``tests/`` and runs on cpu and vulkan alike:
32-bit floats in fields, and accumulators chosen per backend (see ``ti_fusion.backend``).
"""
