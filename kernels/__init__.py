"""Taichi kernels of ti-fusion (imported as ``ti_fusion.kernels``).

Every kernel here has a NumPy float64 reference in ``tests/`` and runs on cpu and vulkan alike:
32-bit floats in fields, and accumulators chosen per backend (see ``ti_fusion.backend``).
"""

from ti_fusion.frontend import fast_class_check

fast_class_check()  # before the kernels below are defined: Taichi's decorators are slow without it
