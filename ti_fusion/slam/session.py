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
changing it (no fusion, no keyframes; the whole map is rendered, not an active window). A localisation's frames
where the map is out of view are posed by frame-to-frame odometry ("odometry: off the map", ``localize_frame``)
until the map rendered at their pose covers them again, rather than searching the map every frame.

A session that never finds itself ends with every frame unlocalised (the CLI exits with status 3), unless
``map.unfound = "map-anyway"``: after ``map.find_frames`` unlocalised frames the session sets the loaded map
aside and maps on in its own frame from the next frame, as a run without a map does.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from ti_fusion.slam.result import FrameResult
from ti_fusion.status import Tracking, alignment_status

log = logging.getLogger(__name__)

# A localisation whose tracking is lost this many frames in a row has left the map (it fuses nothing, so nothing
# new can be tracked against): it looks for itself again instead of reporting the motion model's guesses.
LOST_FRAMES = 3
# A localisation's frame whose tracked correspondences cover less than this fraction of its depth is off the map: the
# little of the map it sees does not hold its pose (nothing is fused to extend it), so it counts as lost.
ON_MAP = 0.3
# Off the map, every this many frames posed by odometry the frame also looks for itself in the map (place recognition
# and verification, as a search does): odometry drifts, and from a pose too far off the map's render does not
# bring it back (a jump beyond slam.max_update_m); a bounded cost, not a search every frame.
SEARCH_EVERY = 10
# (degrees, metres): odometry this near a localisation's alignment against the map settles a weak direction of the
# map's depth in place of the slide starts (their steps are 4 cm and more; odometry's step error is millimetres).
SETTLED = (0.5, 0.005)


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
    off_map: bool = False  # localize: the map is out of view, frames are posed by odometry from the last one
    odometry: list[int] = field(default_factory=list)  # localize: the frames posed by odometry off the map
    back_on_map: list[int] = field(default_factory=list)  # localize: the frames that tracked against it again
    searched_off_map: list[int] = field(default_factory=list)  # localize: the frames off it that searched the map
    streak: int = 0  # localize: frames off the map so far, by odometry
    kept: "KeptMaps | None" = None  # localize: the last posed frame's maps, odometry's source
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
        self.off_map = False
        self.streak = 0
        self.searches.append(frame + 1)
        log.info(f"frame {frame}: lost the map for {LOST_FRAMES} frames: looking for itself in it again from the "
                 "next frame")

    def summary(self) -> dict:
        """summary.json's session fields."""
        return {"session": "localize" if self.localize else "extend",
                "localised_at": None if self.found is None else self.found["frame"],
                "unlocalised_frames": len(self.unlocalised),
                "unlocalised": [{"frame": f, "reason": why} for f, why in self.unlocalised][:50],
                "found": self.found, "own_map_at": self.own_map_at, "searches_again": self.searches[:50],
                **({"odometry_frames": len(self.odometry), "odometry": _spans(self.odometry)[:50],
                    "back_on_map": self.back_on_map[:50], "searched_off_map": len(self.searched_off_map)}
                   if self.localize else {})}

    def keep_maps(self, slam, frame) -> None:
        """localize: ``frame`` got a pose; its vertex and normal maps are the next frame's odometry source."""
        if self.kept is None:
            self.kept = KeptMaps(slam.frame_pyramid, slam.model_pyramid)
        self.kept.keep(frame.index)


def find_in_map(slam, frame, terms: tuple[str, ...]):
    """One frame of a session that has not found itself: a ``FrameResult`` that is relocalised
    (with ``found``), or unlocalised with why."""
    session = slam.session
    placement, checked, tried = _find_place(slam, frame)
    if placement is None:
        why = "no keyframe of the map looks like this frame" if not checked else \
            f"{len(checked)} keyframe(s) of the map look like it, none verified ({checked[0].reason})"
        return _unlocalised(slam, frame, why, tried)
    slam.seed(frame, placement.pose)
    result = slam._track(frame, terms)
    check_on_map(slam, frame, result)
    result.tried = tried + result.tried
    if not result.tracked:
        slam.seed(None, None)
        return _unlocalised(slam, frame, f"keyframe {placement.keyframe.id} verified, but the frame does not track "
                                         f"against the map there ({result.reason})", result.tried)
    c = placement.candidate
    result.tracking = Tracking.RELOCALISED
    session.located = True
    result.found = _found_event(frame, placement, session)
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


class KeptMaps:
    """Copies of the frame pyramid's vertex and normal maps (the rows of the levels the model has) of the last frame
    with a pose: off the map, a localisation tracks the next frame against them (``odometry``), put into the model
    pyramid, whose maps ICP's kernels already take as the source. Not ``usable`` where the two pyramids differ in
    shape (then a frame off the map has no odometry: lost, as before)."""

    def __init__(self, frame_pyramid, model_pyramid):
        import taichi as ti

        self.frame, self.model = frame_pyramid, model_pyramid
        fields = [(frame_pyramid.vertex[0].field, model_pyramid.vertex[0].field),
                  (frame_pyramid.normal[0].field, model_pyramid.normal[0].field)]
        # a pair (FramePyramid.pair): one set of fields, the model's levels below the frame's, of the same sizes
        self.shared = all(a is b for a, b in fields)
        if self.shared:
            self.usable = frame_pyramid.shapes[:model_pyramid.levels] == model_pyramid.shapes
        else:
            self.usable = all(a.shape == b.shape for a, b in fields) and frame_pyramid.row0 == model_pyramid.row0 and \
                frame_pyramid.levels >= model_pyramid.levels
        # the model's levels' rows, from its first level's: the frame's levels of the same sizes span as many
        self.rows = model_pyramid.row0[-1] + model_pyramid.shapes[-1][0] - model_pyramid.row0[0]
        self.copies = [ti.Vector.field(3, ti.f32, shape=(self.rows, a.shape[1])) for a, _ in fields] \
            if self.usable else []
        self.index: int | None = None  # the frame whose maps are kept

    def keep(self, index: int) -> None:
        from ti_fusion.kernels.pyramid import copy_rows

        if self.usable:
            start = self.frame.row0[0]
            copy_rows(self.frame.vertex[0].field, start, self.copies[0], 0, self.rows)
            copy_rows(self.frame.normal[0].field, start, self.copies[1], 0, self.rows)
            self.index = index

    def into_model(self):
        """The model pyramid holding the kept frame's maps (its depth and intensity are not used by depth ICP)."""
        from ti_fusion.kernels.pyramid import copy_rows

        first = self.model.row0[0]
        copy_rows(self.copies[0], 0, self.model.vertex[0].field, first, self.rows)
        copy_rows(self.copies[1], 0, self.model.normal[0].field, first, self.rows)
        return self.model


def localize_frame(slam, frame, terms: tuple[str, ...]):
    """One frame of a localisation that has found itself: tracked against the map while it is in view; where the
    frame leaves it (tracking lost, or its correspondences cover less than ``ON_MAP`` of its depth), posed by
    frame-to-frame odometry from the last posed frame ("odometry: off the map"), and from there each frame
    tracks against the map again only where the map rendered at its odometry pose covers ``ON_MAP`` of its
    depth, and every ``SEARCH_EVERY``-th also searches the map. A frame that neither tracks nor has odometry is
    lost (``LOST_FRAMES`` of them: search again)."""
    session = slam.session
    if not session.off_map:
        result = slam._track(frame, terms)
        check_on_map(slam, frame, result)
        if result.tracked:
            return result
        moved = odometry(slam, frame, f"off the map ({result.reason})")
        if moved is None or not moved.tracked:
            if moved is not None:
                result.tried += moved.tried
            return result
        session.off_map, session.streak = True, 1
        session.odometry.append(frame.index)
        log.info(f"frame {frame.index}: off the map ({result.reason}): posed by odometry until it sees the map again")
        moved.tried = result.tried + moved.tried
        return moved
    moved = odometry(slam, frame, "off the map")
    if moved is None or not moved.tracked:
        return moved if moved is not None else FrameResult(
            frame.index, frame.timestamp, slam._predicted_pose(frame.timestamp), Tracking.LOST, "off the map, and "
            "no odometry", tried=[])
    back = back_on_map(slam, frame, moved, terms)
    session.streak += 1
    if back is None and session.streak % SEARCH_EVERY == 0:
        back = search_off_map(slam, frame, moved, terms)
    if back is None:
        session.odometry.append(frame.index)
        return moved
    session.off_map = False
    session.back_on_map.append(frame.index)
    log.info(f"frame {frame.index}: back on the map after {session.streak - 1} frame(s) by odometry")
    session.streak = 0
    return back


def search_off_map(slam, frame, moved, terms: tuple[str, ...]):
    """Off the map, a frame posed by odometry (``moved``) looks for itself in the map as a search does; where a
    keyframe verifies and the frame tracks against the map from there, that result ("relocalised"), else None
    (``moved.tried`` says what was tried)."""
    session = slam.session
    session.searched_off_map.append(frame.index)
    placement, _, tried = _find_place(slam, frame)
    moved.tried += tried
    if placement is None:
        return None
    back = back_on_map(slam, frame, replace(moved, pose=placement.pose), terms)
    if back is None:
        return None
    back.tracking = Tracking.RELOCALISED
    back.found = _found_event(frame, placement, session)
    log.info(f"frame {frame.index}: found itself in the map again at keyframe {placement.keyframe.id} while off it")
    return back


def odometry(slam, frame, why: str):
    """The frame tracked against the last posed frame's maps (depth ICP from the motion model's guess, then from
    that frame's pose): status "odometry: <why>" with its pose, or lost; None where no maps are kept."""
    from ti_fusion.geometry import invert, renormalize

    kept = slam.session.kept
    if kept is None or not kept.usable or slam.last_good is None or kept.index != slam.last_good[0].index:
        return None
    source, last = kept.into_model(), slam.last_good[1]
    predicted = slam._predicted_pose(frame.timestamp)
    tried, first = [], None
    for guess in (predicted, last):
        icp = slam.icp.align(source, slam.frame_pyramid, init=invert(guess) @ last)
        pose = renormalize(last @ invert(icp.pose))
        failure = slam._health(icp, pose, guess, predicted)
        tried.append(f"odometry: {alignment_status(failure)}")
        first = first or (icp, failure)
        if not failure:
            return FrameResult(frame.index, frame.timestamp, pose, Tracking.ODOMETRY, why, icp=icp,
                               hypothesis="odometry", tried=tried)
    return FrameResult(frame.index, frame.timestamp, predicted, Tracking.LOST, f"{why}; odometry: {first[1]}",
                       icp=first[0], hypothesis="odometry", tried=tried)


def odometry_settles(slam, frame, pose: np.ndarray) -> bool:
    """A localisation's frame tracked against the map to ``pose`` along a direction the map's depth leaves weak:
    whether odometry from the last posed frame (its whole view, not only the part the map covers) lands within
    ``SETTLED`` of it, so the other minima along that direction need not be tried (slam.slide_ratio)."""
    from ti_fusion.geometry import pose_error

    moved = odometry(slam, frame, "check")
    if moved is None or not moved.tracked:
        return False
    rot_deg, trans_m = pose_error(moved.pose, pose)
    return rot_deg < SETTLED[0] and trans_m < SETTLED[1]


def back_on_map(slam, frame, moved, terms: tuple[str, ...]):
    """Off the map, the frame posed by odometry (``moved``) tracked against the map rendered at that pose, where
    the render covers ``ON_MAP`` of its depth (at the coarsest level: a cheap test, no ICP where it fails);
    the result where it tracks and its correspondences cover ``ON_MAP`` of the frame's depth, else None."""
    from ti_fusion.geometry import invert, renormalize

    source, start = slam._reference("intensity" in slam.icp.needs(terms), at=moved.pose)
    level = source.levels - 1
    live = slam.frame_pyramid.depth[level].to_numpy() > 0
    seen = np.count_nonzero(live & (source.depth[level].to_numpy() > 0)) / max(np.count_nonzero(live), 1)
    if seen < ON_MAP:
        moved.tried.append(f"map: covers {seen:.0%} of the frame < {ON_MAP:.0%}")
        return None
    terms = slam.icp.ready(terms, source, slam.frame_pyramid)
    icp = slam.icp.align(source, slam.frame_pyramid, init=np.eye(4), terms=terms)
    pose = renormalize(start @ invert(icp.pose))
    failure = slam._health(icp, pose, start)
    result = FrameResult(frame.index, frame.timestamp, pose, Tracking.LOST if failure else Tracking.OK, failure,
                         icp=icp, hypothesis="odometry", tried=moved.tried + [
                             f"map: {alignment_status(failure)}"])
    check_on_map(slam, frame, result)
    if not result.tracked:
        moved.tried.append(f"map: {result.status}")
        return None
    return result


def _find_place(slam, frame) -> tuple:
    """(where ``frame`` is in the map or None, the keyframes checked, each as a line of ``FrameResult.tried``):
    loop closure's ``find_place``."""
    placement, checked = slam.loop.find_place(frame, slam.loop_maps())
    return placement, checked, [f"place: keyframe {c.match} (score {c.score:.3f}): {c.reason}" for c in checked]


def _found_event(frame, placement, session) -> dict:
    """``FrameResult.found`` of a frame that found itself at ``placement`` (/slam/stats ``found``)."""
    c = placement.candidate
    return {"frame": frame.index, "keyframe": placement.keyframe.id, "map_frame": placement.keyframe.frame,
            "score": round(c.score, 4), "pnp_inliers": c.pnp_inliers,
            "icp_inlier_ratio": None if c.icp_inlier_ratio is None else round(c.icp_inlier_ratio, 4),
            "unlocalised_before": len(session.unlocalised)}


def _spans(frames: list[int]) -> list[list[int]]:
    """[[first, last], ...] of the runs of consecutive frames."""
    spans: list[list[int]] = []
    for f in frames:
        if spans and f == spans[-1][1] + 1:
            spans[-1][1] = f
        else:
            spans.append([f, f])
    return spans


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


def _unlocalised(slam, frame, why: str, tried: list[str]):
    session = slam.session
    session.unlocalised.append((frame.index, why))
    if session.unfound == "map-anyway" and len(session.unlocalised) >= session.give_up:
        log.warning(f"frame {frame.index}: the session has not found itself in the map in {len(session.unlocalised)} "
                    "frames (map.find_frames): it maps on in its own frame from the next frame "
                    "(map.unfound = map-anyway); the loaded map is set aside")
        slam.own_map()
        session.own_map_at = frame.index + 1
    return FrameResult(frame.index, frame.timestamp, None, Tracking.UNLOCALISED, why, tried=tried)
