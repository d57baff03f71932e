"""A session against a saved map: the camera's pose is unknown until the session finds itself in the map.

    slam.start_session(localize=False)     # a DenseSLAM holding a map: a loaded one, or the same object later on
    result = slam.register_frame(frame)    # "unlocalised: <why>" until a frame finds itself, then as any run

Until then every frame tries: place recognition against the map's keyframes, PnP and dense verification as a
loop candidate is verified (``LoopClosure.find_place``), then ICP of the frame against the map rendered at the
pose the match gives (the starts and health checks of any tracked frame, ``DenseSLAM._track``). A frame that
does not find itself gets no pose (left out of trajectory.tum, as a frame skipped before a map starts) and is
not fused: never a start at the identity. The frame that finds itself is "relocalised", carries the event
(``FrameResult.found``), and the session goes on in the map's frame: extending the map (fusion, new keyframes,
loop closures that may reach the map's keyframes) or, with ``localize``, tracking against the map without
changing it (no fusion, no keyframes; the whole map is rendered, not an active window).

A session that never finds itself ends with every frame unlocalised (the CLI exits with status 3), unless
``map.unfound = "map-anyway"``: after ``map.find_frames`` unlocalised frames the session sets the loaded map
aside and maps on in its own frame from the next frame, as a run without a map does.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ti_fusion.status import Tracking

log = logging.getLogger(__name__)

# A localisation whose tracking is lost this many frames in a row has left the map (it fuses nothing, so nothing
# new can be tracked against): it looks for itself again instead of reporting the motion model's guesses.
LOST_FRAMES = 3
# A localisation's frame whose tracked correspondences cover less than this fraction of its depth is off the map: the
# little of the map it sees does not hold its pose (nothing is fused to extend it), so it counts as lost.
ON_MAP = 0.3


@dataclass
class Session:
    """What a DenseSLAM knows of the session it runs against a map (``DenseSLAM.start_session``)."""

    localize: bool = False  # track against the map without changing it
    unfound: str = "fail"  # "map-anyway": after ``give_up`` unlocalised frames, map on in the session's own frame
    give_up: int = 30
    found: dict | None = None  # the event of the frame that first found itself (``FrameResult.found``)
    located: bool = False  # tracking in the map's frame now (false before it found itself, and in a localisation
    # that lost the map until it finds itself again)
    unlocalised: list[tuple[int, str]] = field(default_factory=list)  # (frame, why) of the frames without a pose
    searches: list[int] = field(default_factory=list)  # localize: the frames at which it lost the map and searched
    own_map_at: int | None = None  # map-anyway: the frame the session's own map started at

    @property
    def localised(self) -> bool:
        """The session knows its pose: in the map's frame (found) or in its own (map-anyway)."""
        return self.located or self.own_map_at is not None

    @property
    def whole_map(self) -> bool:
        """Tracking renders the whole map, not the active window: while looking for itself (the place may be
        of any age), and in localisation (nothing is fused, so nothing would stay active)."""
        return self.own_map_at is None and (self.localize or not self.located)

    def lost_track(self, frame: int) -> None:
        """A localisation lost the map for ``LOST_FRAMES`` frames (it went where the map has nothing to track
        against): from the next frame it looks for itself again, its frames without a pose until it does."""
        self.located = False
        self.searches.append(frame + 1)
        log.info(f"frame {frame}: lost the map for {LOST_FRAMES} frames: looking for itself in it again from the "
                 "next frame")

    def summary(self) -> dict:
        """summary.json's session fields."""
        return {"session": "localize" if self.localize else "extend",
                "localised_at": None if self.found is None else self.found["frame"],
                "unlocalised_frames": len(self.unlocalised),
                "unlocalised": [{"frame": f, "reason": why} for f, why in self.unlocalised][:50],
                "found": self.found, "own_map_at": self.own_map_at, "searches_again": self.searches[:50]}


def find_in_map(slam, frame, terms: tuple[str, ...], result_type):
    """One frame of a session that has not found itself: a ``result_type`` (FrameResult) that is relocalised
    (with ``found``), or unlocalised with why."""
    from ti_fusion.loop.closure import LoopMaps

    session = slam.session
    maps = LoopMaps(slam.frame_pyramid, slam.scratch_pyramid(), slam.mapper.frame_level(slam.frame_pyramid))
    placement, checked = slam.loop.find_place(frame, maps)
    tried = [f"place: keyframe {c.match} (score {c.score:.3f}): {c.reason}" for c in checked]
    if placement is None:
        why = "no keyframe of the map looks like this frame" if not checked else \
            f"{len(checked)} keyframe(s) of the map look like it, none verified ({checked[0].reason})"
        return _unlocalised(slam, frame, why, tried, result_type)
    slam.seed(frame, placement.pose)
    result = slam._track(frame, terms)
    check_on_map(slam, frame, result)
    result.tried = tried + result.tried
    if not result.tracked:
        slam.seed(None, None)
        return _unlocalised(slam, frame, f"keyframe {placement.keyframe.id} verified, but the frame does not track "
                                         f"against the map there ({result.reason})", result.tried, result_type)
    c = placement.candidate
    result.tracking = Tracking.RELOCALISED
    session.located = True
    result.found = {
        "frame": frame.index, "keyframe": placement.keyframe.id, "map_frame": placement.keyframe.frame,
        "score": round(c.score, 4), "pnp_inliers": c.pnp_inliers,
        "icp_inlier_ratio": None if c.icp_inlier_ratio is None else round(c.icp_inlier_ratio, 4),
        "unlocalised_before": len(session.unlocalised)}
    if session.found is not None:  # found itself again after losing the map (localize)
        log.info(f"frame {frame.index}: found itself in the map again at keyframe {placement.keyframe.id}")
        return result
    session.found = result.found
    if not session.localize:
        slam.mapper.anchor = placement.keyframe.id  # its surfels move with the keyframe it matched until its own
        slam.reactivate_map()
        slam.loop.found(placement)
    log.info(f"frame {frame.index}: found itself in the map at keyframe {placement.keyframe.id} (frame "
             f"{placement.keyframe.frame} of the map's run), score {c.score:.3f}, {c.pnp_inliers} PnP inliers, after "
             f"{len(session.unlocalised)} frame(s) not localised")
    return result


def check_on_map(slam, frame, result) -> None:
    """With ``localize``: a tracked ``result`` whose ICP correspondences cover less than ``ON_MAP`` of the frame's
    valid depth (at the resolution it is tracked at) becomes lost, "off the map"."""
    if not slam.session.localize or not result.tracked or result.icp is None:
        return
    valid = np.count_nonzero(frame.depth > 0) / 4 ** slam.map_level
    cover = result.icp.inliers / max(valid, 1.0)
    if cover < ON_MAP:
        result.tracking = Tracking.LOST
        result.reason = f"off the map: its correspondences cover {cover:.0%} of the frame's depth < {ON_MAP:.0%}"


def _unlocalised(slam, frame, why: str, tried: list[str], result_type):
    session = slam.session
    session.unlocalised.append((frame.index, why))
    if session.unfound == "map-anyway" and len(session.unlocalised) >= session.give_up:
        log.warning(f"frame {frame.index}: the session has not found itself in the map in {len(session.unlocalised)} "
                    "frames (map.find_frames): it maps on in its own frame from the next frame "
                    "(map.unfound = map-anyway); the loaded map is set aside")
        slam.own_map()
        session.own_map_at = frame.index + 1
    return result_type(frame.index, frame.timestamp, None, Tracking.UNLOCALISED, why, tried=tried)
