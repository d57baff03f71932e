"""Package discovery (the rest of the metadata is in pyproject.toml).

Every package under ti_fusion/ is found automatically; the Taichi kernels live in the top-level folder
kernels/ (the project's layout) and are installed as ti_fusion.kernels.
"""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["ti_fusion", "ti_fusion.*"]) + ["ti_fusion.kernels"],
    package_dir={"ti_fusion.kernels": "kernels"},
)
