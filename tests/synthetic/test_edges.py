"""The synthetic Kinect v1 edges (ti_fusion/synthetic/edges.py, synth.edge_shadow / edge_holes / flying_pixels):
the projector's shadow beside a near edge, the holes along depth edges, flying pixels between an edge's two
sides; and the colour's exposure changes (synth.exposure), JPEG (synth.jpeg_quality) and time offset
(synth.color_offset_ms). All off by default, so the frames without them stay as they were."""

from __future__ import annotations

import numpy as np

from ti_fusion.config import SynthConfig
from ti_fusion.synthetic.edges import depth_edges, kinect_edges, projector_shadow
from ti_fusion.synthetic.scene import SyntheticSequence


def _step(near=1.0, far=2.0, width=80, edge=30):
    """A near surface on columns < edge, a far one beyond it, 10 rows."""
    z = np.full((10, width), far, np.float32)
    z[:, :edge] = near
    return z


def test_the_projector_shadow_is_as_wide_as_the_disparity_step():
    fxb = 525.0 * 0.075
    z = _step()
    shadow = projector_shadow(z, fxb)
    # background column c is lit once c + fxb/2 passes the edge's last near column 29 + fxb (0.1 px margin)
    expected = np.arange(z.shape[1])
    expected = (expected >= 30) & (expected - 29 < fxb * (1 - 0.5) - 0.1)
    assert (shadow == expected[None, :]).all()
    assert not projector_shadow(np.full((4, 50), 1.5, np.float32), fxb).any()  # a plane shadows nothing
    # every second column of the full image: the same shadow, less the one column the sampling misses
    sampled = projector_shadow(z[:, ::2], fxb, step=2)
    assert (sampled <= shadow[:, ::2]).all() and shadow[:, ::2].sum(1).max() - sampled.sum(1).max() == 1


def test_holes_and_flying_pixels_along_depth_edges():
    z = _step()
    edges = depth_edges(z)
    assert edges.sum() == 20 and edges[:, 29:31].all()  # both sides of the jump, every row
    holed = kinect_edges(z, 39.375, 1, shadow=False, holes=2, flying=0.0, seed=1)
    assert (holed[:, 27:33] == 0).all() and (holed[:, :27] == 1).all() and (holed[:, 33:] == 2).all()
    flying = kinect_edges(z, 39.375, 1, shadow=False, holes=2, flying=1.0, seed=1)
    mid = flying[:, 29:31]
    assert ((mid > 1) & (mid < 2)).mean() > 0.9  # between the two sides
    assert (flying[:, [27, 28, 31, 32]] == 0).all()  # their neighbourhoods span no edge: dropped
    assert (kinect_edges(z, 39.375, 1, False, 2, 1.0, seed=1) == flying).all()  # the seed fixes the draw


def test_edge_effects_are_opt_in(cpu):
    """Off by default (the existing synthetic runs keep their frames); on, they drop depth beside the cabinet."""
    small = SynthConfig(scene="cabinet", width=160, height=120, fx=131.25)
    plain = SyntheticSequence(small).frame(3)[0]
    assert (SyntheticSequence(SynthConfig(scene="cabinet", width=160, height=120, fx=131.25)).frame(3)[0]
            == plain).all()
    edged = SyntheticSequence(SynthConfig(scene="cabinet", width=160, height=120, fx=131.25, edge_shadow=True,
                                          edge_holes=4, flying_pixels=0.2)).frame(3)[0]
    lost = (plain > 0) & (edged == 0)
    assert 0.01 < lost.mean() < 0.3
    assert not ((plain == 0) & (edged > 0)).any()
    assert SynthConfig().edge_shadow is False and SynthConfig().edge_holes == 0 and SynthConfig().flying_pixels == 0


def test_exposure_scales_each_frame_by_its_own_gain(cpu):
    """synth.exposure: one brightness gain per frame, fixed by the frame's seed; depth untouched."""
    base = dict(scene="cabinet", width=160, height=120, fx=131.25)
    plain = SyntheticSequence(SynthConfig(**base))
    lit = SyntheticSequence(SynthConfig(**base, exposure=0.2))
    gains = []
    for i in (2, 3):
        (d0, c0), (d1, c1) = plain.frame(i), lit.frame(i)
        assert (d0 == d1).all()
        ok = (c0 > 20) & (c0 < 200) & (c1 < 255)
        ratio = c1[ok].astype(np.float64) / c0[ok]
        assert np.percentile(ratio, 95) - np.percentile(ratio, 5) < 0.05  # one gain over the image (rounding)
        gains.append(np.median(ratio))
    assert abs(np.log(gains[0] / gains[1])) > 0.01  # each frame its own
    assert (lit.frame(2)[1] == SyntheticSequence(SynthConfig(**base, exposure=0.2)).frame(2)[1]).all()
    assert SynthConfig().exposure == 0


def test_jpeg_colour_is_opt_in(cpu):
    """synth.jpeg_quality: the colour through JPEG (as TUM's re-encoded keyframes), depth untouched."""
    base = dict(scene="cabinet", width=160, height=120, fx=131.25)
    (d0, c0), (d1, c1) = SyntheticSequence(SynthConfig(**base)).frame(2), \
        SyntheticSequence(SynthConfig(**base, jpeg_quality=75)).frame(2)
    assert (d0 == d1).all() and c1.dtype == np.uint8 and c1.shape == c0.shape
    assert 0.5 < np.abs(c0.astype(np.int16) - c1).mean() < 8
    assert SynthConfig().jpeg_quality == 0


def test_colour_offset_moves_the_colour_camera_along_the_step(cpu):
    """synth.color_offset_ms: the colour is rendered from the pose that far along the step to the next frame
    (back towards the previous one when negative); depth stays at the frame's own pose."""
    from ti_fusion.geometry import pose_error

    base = dict(scene="cabinet", width=160, height=120, fx=131.25)
    plain = SyntheticSequence(SynthConfig(**base))
    seq = SyntheticSequence(SynthConfig(**base, color_offset_ms=67.0))  # a tenth of the cabinet's 0.67 s step
    step = pose_error(seq.poses[3], seq.poses[4])
    moved = pose_error(seq.poses[3], seq.color_pose(3))
    assert abs(moved[1] - step[1] / 10) < 0.1 * step[1] / 10 + 1e-4, (moved, step)
    back = SyntheticSequence(SynthConfig(**base, color_offset_ms=-67.0))
    assert pose_error(back.color_pose(3), seq.poses[2])[1] < pose_error(seq.poses[3], seq.poses[2])[1]
    (d0, c0), (d1, c1) = plain.frame(3), seq.frame(3)
    assert (d0 == d1).all() and not (c0 == c1).all()
    assert np.allclose(plain.color_pose(3), plain.poses[3]) and SynthConfig().color_offset_ms == 0
