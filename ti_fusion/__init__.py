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


def _ensure_home() -> None:
    """Set $HOME from the password database when it is unset (a service, ``env -i``): Taichi aborts the
    process at import without it, before any message could say why."""
    import os

    if os.environ.get("HOME"):
        return
    home = ""
    try:
        import pwd

        home = pwd.getpwuid(os.getuid()).pw_dir
    except (ImportError, KeyError, OSError):
        pass
    if not home or not os.path.isdir(home):
        import tempfile

        home = tempfile.gettempdir()  # Taichi then keeps its kernel cache under the temporary folder
    os.environ["HOME"] = home


_ensure_home()


def _before_taichi() -> None:
    """Taichi's decorators' class check made cheap before Taichi itself is imported (ti_fusion/frontend.py)."""
    from ti_fusion.frontend import class_check_on_import

    class_check_on_import()


_before_taichi()
