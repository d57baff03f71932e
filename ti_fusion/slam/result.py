"""``FrameResult``: what ``DenseSLAM.register_frame`` did with one frame (``ti_fusion.slam.dense`` exports it too).

Its own module so that the modules ``dense`` calls for a frame (``ti_fusion.slam.session``) make results
without importing ``dense``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ti_fusion.status import Tracking, status_text

if TYPE_CHECKING:
    import numpy as np

    from ti_fusion.mapping.mapper import FusionStats
    from ti_fusion.tracking.icp import ICPResult


@dataclass
class FrameResult:
    """What ``register_frame`` did with one frame."""

    index: int
    timestamp: float
    pose: np.ndarray | None  # camera-to-world estimate when registered (the current one after a loop
    # closure: DenseSLAM.poses); None for a frame skipped before the map starts
    tracking: Tracking
    reason: str = ""  # why the frame was lost or skipped
    icp: ICPResult | None = None
    fusion: FusionStats | None = None
    ms: dict[str, float] = field(default_factory=dict)
    loop: object | None = None  # the loop closure's report on a keyframe (``ti_fusion.loop.closure.LoopReport``)
    hypothesis: str | None = None  # the start whose alignment won: "motion", "last", "features", "wide" or "turn"
    tried: list[str] = field(default_factory=list)  # every start tried, in order, with its outcome
    found: dict | None = None  # a session against a saved map: where the frame that found itself in it matched

    def __post_init__(self):
        self.tracking = Tracking(self.tracking)  # also from its value ("ok")

    @property
    def status(self) -> str:
        """As logs and summaries write it: "init", "ok", "relocalised", "lost: <reason>", "skipped: <reason>",
        "unlocalised: <reason>"."""
        return status_text(self.tracking, self.reason)

    @property
    def tracked(self) -> bool:
        """The frame got a pose (tracked, or the first of the map) and was fused."""
        return self.tracking.tracked

    @property
    def lost(self) -> bool:
        return self.tracking is Tracking.LOST

    @property
    def skipped(self) -> bool:
        return self.tracking is Tracking.SKIPPED
