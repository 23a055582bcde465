"""Targets the supervisor rejected, so the same person is not proposed again.

A candidate matches a remembered rejection by the back-end's candidate id, by estimated ground position
(within a radius widened by both estimates' uncertainty), or by appearance signature (cosine similarity
of plain number vectors, e.g. colour histograms). Positions are compared in metres on a local tangent plane.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from behaviors.geolocation import GeoEstimate, latlon_to_offset


@dataclass(frozen=True)
class RejectedTarget:
    candidate_id: str = ""
    position: GeoEstimate | None = None
    signature: tuple[float, ...] = ()
    time_s: float = 0.0


@dataclass(frozen=True)
class RejectionMemory:
    entries: tuple[RejectedTarget, ...] = ()
    radius_m: float = 5.0
    signature_threshold: float = 0.95
    capacity: int = 64  # oldest forgotten first; a search area holds few people

    def remember(self, target: RejectedTarget) -> RejectionMemory:
        entries = (*self.entries, target)[-self.capacity :]
        return RejectionMemory(entries, self.radius_m, self.signature_threshold, self.capacity)

    def matches(
        self,
        candidate_id: str = "",
        position: GeoEstimate | None = None,
        signature: Sequence[float] = (),
    ) -> RejectedTarget | None:
        """The remembered rejection this candidate looks like, or None."""
        for entry in self.entries:
            if candidate_id and entry.candidate_id == candidate_id:
                return entry
            if position is not None and entry.position is not None and self._near(entry.position, position):
                return entry
            if (
                signature
                and entry.signature
                and cosine_similarity(entry.signature, signature) >= self.signature_threshold
            ):
                return entry
        return None

    def _near(self, a: GeoEstimate, b: GeoEstimate) -> bool:
        north, east = latlon_to_offset(a.lat_deg, a.lon_deg, b.lat_deg, b.lon_deg)
        sigma = math.hypot(a.sigma_m, b.sigma_m)
        # Two sigma of the combined error, but a very uncertain estimate cannot blank a whole area.
        allowed = self.radius_m + min(2.0 * sigma, 2.0 * self.radius_m)
        return math.hypot(north, east) <= allowed


def cosine_similarity(a: Sequence[float], b: Sequence[float]) -> float:
    """Cosine of the angle between two equally long vectors; 0 for mismatched, empty or zero vectors."""
    if len(a) != len(b) or not a:
        return 0.0
    dot = sum(x * y for x, y in zip(a, b, strict=True))
    na = math.sqrt(sum(x * x for x in a))
    nb = math.sqrt(sum(y * y for y in b))
    if not (na > 0 and nb > 0 and math.isfinite(dot)):
        return 0.0
    return dot / (na * nb)
