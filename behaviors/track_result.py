"""What the onboard tracking front-end reports for one frame."""

from __future__ import annotations

from dataclasses import dataclass

from behaviors.geometry import Box


@dataclass(frozen=True)
class TrackResult:
    """One tracker step after loss detection.

    `ok` is the tracker's own success flag; `score` is None for trackers without a meaningful score
    (CSRT, KCF, MIL). `lost_reason` is empty while the target is trusted, else names the loss signal
    that fired ("score", "left_frame", "collapsed", "jump", "appearance", "tracker_failed").
    """

    frame_id: int
    time_s: float
    box: Box | None
    score: float | None
    ok: bool
    lost_reason: str = ""
    # A loss signal that fired on this frame while the track stays trusted (the "verified" policy weighs
    # a lone model-based signal over time): a reason to ask the back-end for evidence now.
    alarm: str = ""

    @property
    def trusted(self) -> bool:
        return self.ok and self.box is not None and not self.lost_reason
