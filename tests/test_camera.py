"""Intrinsics.downsampled's answers, remembered for the intrinsics a run asks about every frame."""

import dataclasses

import numpy as np

from ti_fusion.camera import Intrinsics


def _by_hand(K: Intrinsics, f: int) -> Intrinsics:
    return dataclasses.replace(K, fx=K.fx / f, fy=K.fy / f, cx=K.cx / f, cy=K.cy / f, skew=K.skew / f,
                               width=(K.width + f - 1) // f, height=(K.height + f - 1) // f)


def test_downsampled_is_the_same_answer_each_time_and_keeps_the_numbers_types():
    K = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    for f in (2, 4, 8):
        assert K.downsampled(f) == _by_hand(K, f)
        assert Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480).downsampled(f) == _by_hand(K, f)  # a new equal one
    assert K.downsampled(1) is K
    as_numpy = Intrinsics(np.float64(585), np.float64(585), np.float64(320), np.float64(240), 640, 480)
    assert as_numpy == K
    assert type(K.downsampled(2).fx) is float and type(as_numpy.downsampled(2).fx) is np.float64
    odd = Intrinsics(500.0, 500.0, 200.5, 150.5, 401, 301, skew=1.0, distortion=[0.1, 0.0, 0.0, 0.0],
                     distortion_model="plumb_bob")  # a list: no key, worked out each time
    assert odd.downsampled(2) == _by_hand(odd, 2) and odd.downsampled(2).width == 201
