"""ti-fusion: dense RGB-D SLAM (projective point-to-plane ICP + point-based fusion) on Taichi kernels.

The command line (``ti-fusion``, ``python -m ti_fusion``) covers the usual runs; from Python:

    from ti_fusion.backend import init_backend          # start Taichi: "cpu", "vulkan", "cuda", "auto"
    from ti_fusion.config import load_config            # typed settings: defaults, a file, overrides
    from ti_fusion.io.datasets import open_dataset      # TUM, ICL-NUIM, 7-Scenes or the synthetic sequence
    from ti_fusion.slam.dense import DenseSLAM          # register_frame(frame): track, then fuse

Smaller pieces: ``ti_fusion.tracking.icp.ICP`` (``align``), ``ti_fusion.tracking.features.FeatureOdometry``
(``register_frame``), ``ti_fusion.mapping.mapper.SurfelMapper`` (``integrate``),
``ti_fusion.evaluation.metrics.evaluate`` (ATE/RPE). Poses are 4×4 camera-to-world matrices; depth is in
metres with 0 for invalid.
"""

__version__ = "0.1.0"
