"""What became of a frame: ``Tracking``, the first word of a frame's status as logs and summaries write it."""

from __future__ import annotations

from enum import Enum


class Tracking(str, Enum):
    """A frame's outcome; a lost or skipped frame also has a reason (``status`` joins them)."""

    INIT = "init"  # the map's first frame: its pose is the start (identity or ground truth)
    OK = "ok"  # tracked from the motion model or the last pose, and fused
    RELOCALISED = "relocalised"  # tracked from another start (features or the wide basin), and fused
    LOST = "lost"  # no start passed the checks: the frame reports its guess and is not fused
    SKIPPED = "skipped"  # before the map starts (e.g. a blank sensor): no pose
    UNLOCALISED = "unlocalised"  # a session against a saved map that has not found itself in it yet: no pose
    ODOMETRY = "odometry"  # a localisation off the map: posed by frame-to-frame odometry, not against the map

    @property
    def tracked(self) -> bool:
        """The frame got a pose of its own (and was fused, where the run maps)."""
        return self not in (Tracking.LOST, Tracking.SKIPPED, Tracking.UNLOCALISED)


def status_text(tracking: Tracking, reason: str = "") -> str:
    """The status string of logs and summaries: "ok", or "lost: <reason>"."""
    return f"{tracking.value}: {reason}" if reason else tracking.value


def alignment_status(failure: str) -> str:
    """One alignment's outcome as a start's line says it: "ok", or "lost: <failure>" (``failure`` "": it passed)."""
    return status_text(Tracking.LOST, failure) if failure else Tracking.OK.value
