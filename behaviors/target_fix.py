"""Which of a track's ground estimates a find and the memories report: the freshest of the good ones.

Every tracked frame gives a ground estimate with a one-sigma error (`behaviors.geolocation`). The latest
can be the worst (a surveying drone flying away sees the person at the view's far edge, where the errors
also exceed their first-order sigma), so an estimate much worse than the track's best is never taken. But
the best alone is stale: a person walks on while the drone follows and the supervisor decides, and the
estimate from the drone's closest look is of a place they left (the follow scenario with a supervisor
deciding after 10 s reported its find 15 m from the walking person, with a sigma of 0.8 m). So the kept
estimate is the latest whose sigma is within `FRESHER_WITHIN` of the smallest the track has had: while the
drone keeps its standoff the estimates stay that good and the find follows the person. Whichever is kept,
its time goes with it: a rescuer must know how old a position is (a person seen well a minute ago may have
walked on).

An estimate from a box against the image's side or bottom edge (`GeoEstimate.clipped`) is no measure of the
person's feet, and its sigma cannot say how far off it is: the tracker may hold the background the person
crossed the edge from. A surveying drone passing a person at the view's side sees them leave over that edge,
and the track's last boxes (the freshest) are such boxes: in a real-ArduCopter fleet run the tracker held the
left edge for 4 s after the person had left, its estimates sliding 4-15 m on with the drone at sigmas of
3.7-4.6 m, within `FRESHER_WITHIN` of the best (3.1 m), and the find was placed 8 m off. So a clipped
estimate is kept only while the track has no other (then the first: nearest the view the back-end judged),
never instead of one from a whole box, and it does not set the best sigma the others are held to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from behaviors.geolocation import GeoEstimate

FRESHER_WITHIN = 1.5  # a later estimate with at most this many times the best sigma is as good, and fresher


@dataclass(frozen=True)
class KeptFix:
    """The estimate to report, when it was observed (event time, s), and the smallest sigma the track has had."""

    estimate: GeoEstimate | None = None
    best_sigma_m: float = math.inf
    time_s: float = math.nan


def kept_fix(kept: KeptFix, latest: GeoEstimate, time_s: float) -> KeptFix:
    """After `latest`, observed at `time_s`: it is kept when its sigma is within `FRESHER_WITHIN` of the
    track's best, else the estimate kept before stays, with its own time. A clipped `latest` is kept only
    when nothing is; an unclipped one always replaces a clipped one."""
    if latest.clipped:
        return kept if kept.estimate is not None else KeptFix(latest, kept.best_sigma_m, time_s)
    best = min(kept.best_sigma_m, latest.sigma_m)
    if kept.estimate is None or kept.estimate.clipped or latest.sigma_m <= FRESHER_WITHIN * best:
        return KeptFix(latest, best, time_s)
    return KeptFix(kept.estimate, best, kept.time_s)
