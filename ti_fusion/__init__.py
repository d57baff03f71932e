"""ti-fusion: dense RGB-D SLAM (projective point-to-plane ICP + point-based fusion) on Taichi kernels."""

__version__ = "0.1.0"
