"""PNG views of a surfel map from a fixed viewpoint: coloured by surfel colour and by normal.

The viewpoint is the first camera pulled back along its optical axis (``fusion.view_back`` metres), with
a wider field of view than the sensor's, so the view shows the map around what the sequence started on.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.io.outputs import write_image

VIEW_INTRINSICS = Intrinsics(fx=420.0, fy=420.0, cx=319.5, cy=239.5, width=640, height=480)


def view_pose(first_pose: np.ndarray, back: float = 1.0) -> np.ndarray:
    """Camera-to-world pose of the first camera moved ``back`` metres behind itself (same orientation)."""
    pose = np.array(first_pose, dtype=np.float64)
    pose[:3, 3] -= back * pose[:3, 2]
    return pose


def save_views(surfel_map, pose: np.ndarray, out_dir: str | Path, prefix: str = "map",
               intrinsics: Intrinsics = VIEW_INTRINSICS, later=None) -> dict[str, Path]:
    """Write ``<prefix>_color.png`` and ``<prefix>_normals.png`` of ``surfel_map`` seen from ``pose``.

    ``surfel_map`` is a ``SurfelMap`` (or anything with its ``render_image(pose, intrinsics, by_normal)``; its
    ``render_images``, where it has one, renders both from one render).
    Each file is written whole or not at all (``OutputError`` naming it when it cannot be). ``later``: a
    function that runs a function elsewhere (``Pipeline.in_background``), given each image's encoding and
    writing (the views are rendered here; the paths returned are those the files will have).
    """
    out_dir = Path(out_dir)
    paths = {}
    kinds = (("color", False), ("normals", True))
    if hasattr(surfel_map, "render_images"):  # both from one render
        images = surfel_map.render_images(pose, intrinsics, tuple(by_normal for _, by_normal in kinds))
    else:
        images = [surfel_map.render_image(pose, intrinsics, by_normal=by_normal) for _, by_normal in kinds]
    for (name, _), rgb in zip(kinds, images):
        paths[name] = path = out_dir / f"{prefix}_{name}.png"
        write = lambda path=path, rgb=rgb: write_image(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        write() if later is None else later(write)
    return paths
