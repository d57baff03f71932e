"""Loop closure's look ahead, on a thread beside the loop's (``LoopClosure.look_ahead`` hands it to its ``InOrder``).

    job = beside.submit(lambda: look_ahead(frame, ...), quiet=True)   # beside: an InOrder (loop/in_order.py)
    ahead = beside.take(job)                                          # its Ahead, or None where it failed

For a frame that the motion model's guess makes a keyframe, ``look_ahead`` computes what verifying it needs of its
images alone: its ORB features, place recognition's candidates, and each candidate's pre-check and PnP
(``LoopVerifier.check_features``). None of it reads the frame's pose: the keyframe test on the tracked pose
decides where it did, the same functions of the same inputs give the same answers, and a frame the guess got
wrong is done on the loop's thread as before.

Why a thread: OpenCV's ORB, matching and PnP RANSAC and NumPy's larger loops release the GIL, and on the CPU backend
the loop's thread holds it through each kernel launch while Taichi's workers wait on the loop's Python, so this
work fills the core the loop's Python leaves idle instead of following tracking and fusion on the loop's thread
(docs/PERFORMANCE.md, "Loop closure beside the frame").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ti_fusion.loop.keyframes import Keyframe
from ti_fusion.loop.place_recognition import Place, PlaceDatabase
from ti_fusion.loop.verification import FeatureCheck, LoopVerifier
from ti_fusion.tracking.features import FrameFeatures, extract_features


@dataclass
class Ahead:
    """A frame's look ahead (``look_ahead``): for its keyframe, if the tracked pose makes it one."""

    frame: int  # the frame's index
    features: FrameFeatures  # its ORB features, lifted with its depth
    places: list[Place]  # place recognition's candidates, best first
    checks: list[FeatureCheck]  # each candidate's pre-check and PnP, in the same order


def look_ahead(frame, keyframe_id: int, vo, orb, database: PlaceDatabase, keyframes: list[Keyframe],
               verifier: LoopVerifier) -> Ahead:
    """What ``LoopClosure.after_frame`` would compute of ``frame`` as keyframe ``keyframe_id`` before its dense ICP:
    its features (``extract_features`` with ``vo`` and ``orb``), the database's candidates for it, and each
    candidate's ``check_features``, all of the same inputs as there (the database as the keyframes before it
    left it)."""
    features = extract_features(frame, vo, orb)
    query = Keyframe(keyframe_id, frame.index, frame.timestamp, np.eye(4), features, frame.intrinsics, None, None,
                     np.zeros((0, 3)))
    places = database.query(query)
    return Ahead(frame.index, features, places,
                 [verifier.check_features(query, keyframes[place.keyframe]) for place in places])
