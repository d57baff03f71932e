"""A folder or 7-Scenes-like run whose colour comes from a second camera: --color-intrinsics and
--color-extrinsics FILE give the colour camera, and the run loop's registrar (ti_fusion/io/registration.py)
turns its colour into the depth camera's; what is refused, in one line."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, so3_exp
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.registration import ColorRegistrar, resized

T = make_pose(so3_exp(np.array([0.01, -0.02, 0.01])), [0.025, 0.003, -0.002])
# the renderer filters its textures over a pixel's footprint, so the colour seen at the depth camera is the
# target only for a colour camera of about the depth's pixels per degree (at 400x300, fx 375: median 4 levels)
K_COLOR = Intrinsics(fx=300.0, fy=301.0, cx=165.0, cy=118.0, width=320, height=240)
K_LARGE = Intrinsics(fx=600.0, fy=602.0, cx=330.0, cy=236.0, width=640, height=480)


@pytest.fixture(scope="module")
def offset_folder(tmp_path_factory):
    """Three frames of the synthetic room: 320x240 depth in mm, 640x480 colour from a camera 2.5 cm aside;
    and the colour rendered at the depth camera, the target."""
    from ti_fusion.backend import init_backend
    from ti_fusion.synthetic.scene import SyntheticSequence

    init_backend("cpu")
    root = tmp_path_factory.mktemp("offset")
    for name in ("depth", "rgb", "large/depth", "large/rgb"):
        (root / name).mkdir(parents=True)
    seq = SyntheticSequence(SynthConfig(width=320, height=240, fx=262.5))
    targets = []
    for i in range(3):
        pose = seq.poses[i * 20]
        depth, at_depth = seq.render(pose, noise=False)
        for folder, K in (("", K_COLOR), ("large/", K_LARGE)):
            cv2.imwrite(str(root / f"{folder}depth" / f"{i:06d}.png"), np.round(depth * 1000).astype(np.uint16))
            color = seq.render_offset_color(pose, T, K, noise=False)
            cv2.imwrite(str(root / f"{folder}rgb" / f"{i:06d}.png"), color[..., ::-1])
        targets.append(at_depth)
    (root / "T_color_depth.txt").write_text("\n".join(" ".join(f"{x:.12g}" for x in r) for r in T) + "\n")
    return root, targets


def cfg(root, **kw) -> DatasetConfig:
    return DatasetConfig(path=str(root), format="folder", depth_scale=1000, intrinsics="262.5,262.5,159.5,119.5", **kw)


@pytest.mark.slow
def test_a_folder_with_a_second_color_camera_is_registered(offset_folder):
    """The colour camera 2.5 cm aside, its own intrinsics: the registrar reprojects its colour into the depth
    camera, within 2 grey levels (median) of the colour seen at the depth camera."""
    root, targets = offset_folder
    ds = open_dataset(cfg(root, color_extrinsics=str(root / "T_color_depth.txt"),
                          color_intrinsics=",".join(map(str, K_COLOR.as_tuple()))))
    assert ds.color_camera[0] == K_COLOR and ds.notes == []
    register = ColorRegistrar(ds.color_camera)
    for i in range(3):
        frame = register(ds[i])
        assert frame.color_registered and frame.color.shape == (240, 320, 3)
        valid = frame.meta["color_valid"]
        grey = [cv2.cvtColor(c, cv2.COLOR_RGB2GRAY).astype(int) for c in (frame.color, targets[i])]
        assert valid.mean() > 0.7 and np.median(np.abs(grey[0] - grey[1])[valid]) <= 2
    # colour of another size than depth: kept whole by the loader (not resized), registered from its pixels
    ds = open_dataset(cfg(root / "large", color_extrinsics=str(root / "T_color_depth.txt"),
                          color_intrinsics=",".join(map(str, K_LARGE.as_tuple()))))
    frame = ds[0]
    assert frame.color.shape == (480, 640, 3) and not frame.color_registered
    frame = ColorRegistrar(ds.color_camera)(frame)
    assert frame.color.shape == (240, 320, 3) and frame.meta["color_valid"].mean() > 0.7
    ds = open_dataset(cfg(root / "large", color_extrinsics=str(root / "T_color_depth.txt"),
                          color_intrinsics=",".join(map(str, K_LARGE.as_tuple())), downsample=2))
    frame = ColorRegistrar(ds.color_camera)(ds[0])  # both halved: the colour camera follows
    assert frame.color.shape == (120, 160, 3) and frame.meta["color_valid"].mean() > 0.7


def test_the_color_camera_follows_the_image_it_is_given():
    assert resized(K_LARGE, 320, 240, 0) == K_LARGE.downsampled(2)  # img[::2, ::2]
    K = resized(K_LARGE, 400, 300, 0)  # cv2.resize: pixel edges scale
    assert K.fx == pytest.approx(375.0) and K.cx == pytest.approx((330.0 + 0.5) * 0.625 - 0.5)


def test_what_is_refused(offset_folder, tmp_path):
    root, _ = offset_folder
    with pytest.raises(InputError, match="--color-extrinsics registers colour to depth together with "
                                         "--color-intrinsics"):
        open_dataset(cfg(root, color_extrinsics=str(root / "T_color_depth.txt")))
    with pytest.raises(InputError, match="no such file .a transform topic is for bags"):
        open_dataset(cfg(root, color_extrinsics="/tf_static", color_intrinsics="600,600,320,240"))
    with pytest.raises(InputError, match="--color-intrinsics"):
        open_dataset(cfg(root, color_extrinsics=str(root / "T_color_depth.txt"), color_intrinsics="600,600,2000,240"))
