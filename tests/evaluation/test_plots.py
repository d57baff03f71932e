"""The trajectory plot's loop edges: drawn as lines between two camera positions (applied green and solid
with a ring at each end, the other candidates faint red and dashed), given as rows of the poses or as world
positions."""

import cv2
import numpy as np
import pytest

from ti_fusion.evaluation.plots import plot_trajectory
from ti_fusion.geometry import se3_exp


def circle(n=60, radius=1.0, drift=0.0):
    """Camera-to-world poses around a circle in the x–z plane, ending near the start (plus ``drift`` in x)."""
    angle = np.linspace(0.0, 1.9 * np.pi, n)
    poses = np.stack([np.eye(4)] * n)
    poses[:, 0, 3] = radius * np.cos(angle) + drift * np.linspace(0.0, 1.0, n)
    poses[:, 2, 3] = radius * np.sin(angle)
    poses[:, 1, 3] = 0.01 * np.sin(5 * angle)
    return poses


def color_pixels(image_bgr, rgb, tol=50):
    """Pixels within ``tol`` of an RGB colour."""
    return int((np.abs(image_bgr[..., ::-1].astype(int) - rgb).max(axis=-1) <= tol).sum())


GREEN = (44, 160, 44)  # matplotlib's tab:green


def reddish_pixels(image_bgr, margin=40):
    """Pixels whose red exceeds green and blue by ``margin``: tab:red, also faint (blended with white)."""
    rgb = image_bgr[..., ::-1].astype(int)
    return int(((rgb[..., 0] > rgb[..., 1] + margin) & (rgb[..., 0] > rgb[..., 2] + margin)).sum())


@pytest.mark.slow
def test_loop_edges_are_drawn(tmp_path):
    est = circle(drift=0.1)
    edges = [(59, 0, True), (55, 3, True), (40, 10, False),  # rows of the poses
             (est[30, :3, 3], est[0, :3, 3], False)]  # world positions
    plain = cv2.imread(str(plot_trajectory(tmp_path / "plain.png", est)))
    drawn = cv2.imread(str(plot_trajectory(tmp_path / "loops.png", est, loop_edges=edges)))
    assert drawn.shape == plain.shape
    green, red = color_pixels(plain, GREEN), reddish_pixels(plain)  # anti-aliased blue may come close
    assert color_pixels(drawn, GREEN) > green + 200 and reddish_pixels(drawn) > red + 200
    # with ground truth, the edges follow the rigidly aligned estimate; an empty list draws nothing
    world = se3_exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, -0.5]))
    gt = circle()
    aligned = cv2.imread(str(plot_trajectory(tmp_path / "gt.png", world @ est, gt, loop_edges=[
        ((world @ est[59])[:3, 3], (world @ est[0])[:3, 3], True), (40, 10, False)])))
    gt_only = cv2.imread(str(plot_trajectory(tmp_path / "gt_only.png", world @ est, gt)))
    assert color_pixels(aligned, GREEN) > color_pixels(gt_only, GREEN) + 50
    assert reddish_pixels(aligned) > reddish_pixels(gt_only) + 50  # one thin, faint, dashed line
    none = cv2.imread(str(plot_trajectory(tmp_path / "none.png", est, loop_edges=[])))
    assert np.array_equal(none, plain)


@pytest.mark.parametrize("edge", [(0, 60, True), (0.5, 1, True), (0, 1), ((0, 0), (1, 1, 1), True)])
def test_bad_loop_edges_are_refused(tmp_path, edge):
    with pytest.raises(ValueError, match="loop edge"):
        plot_trajectory(tmp_path / "x.png", circle(), loop_edges=[edge])
