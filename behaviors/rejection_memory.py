"""Targets the supervisor rejected, so the same person is not proposed again.

A candidate matches a remembered rejection by the back-end's candidate id, by estimated ground position
(within a radius widened by both estimates' uncertainty), or by appearance signature (cosine similarity
of plain number vectors, e.g. colour histograms). Positions are compared in metres on a local tangent plane.

The radius stands in for appearance, which the companion does not judge, and so would hide anyone standing
near a rejected person; of one keyframe's candidates only the nearest takes a rejection by place
(`RejectionMemory.matches_each`): two people in one keyframe are two people. Once the back-end holds the
rejection (`RejectedTarget.shared_from_query`) it judges appearance in every later answer, and position
matches only within two sigma of both estimates. Another vehicle's rejection in a fleet mission
(`RejectedTarget.via`) is never taken as judged so: the back-end's appearance match fails for a look-alike
seen from another lane, so the radius holds for it throughout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from behaviors.geolocation import GeoEstimate, latlon_to_offset


@dataclass(frozen=True)
class RejectedTarget:
    candidate_id: str = ""
    position: GeoEstimate | None = None
    signature: tuple[float, ...] = ()
    time_s: float = 0.0
    # The first query whose answer the back-end judged with this rejection known (0: not known to hold it).
    shared_from_query: int = 0
    # Whose rejection it is in a fleet mission ("": this vehicle's own): another vehicle's holds by place.
    via: str = ""
    # A second place it stands at: where the keyframe the supervisor judged placed the candidate, when the
    # track's estimate (`position`) is another (a track started late on a keyframe seconds old may hold the
    # background; behaviors.mission `Target.proposed_at`). Matched as `position` is.
    also_at: GeoEstimate | None = None


@dataclass(frozen=True)
class RejectionMemory:
    entries: tuple[RejectedTarget, ...] = ()
    radius_m: float = 5.0
    signature_threshold: float = 0.95
    capacity: int = 64  # oldest forgotten first; a search area holds few people

    def remember(self, target: RejectedTarget) -> RejectionMemory:
        entries = (*self.entries, target)[-self.capacity :]
        return RejectionMemory(entries, self.radius_m, self.signature_threshold, self.capacity)

    def shared(self, candidate_id: str, from_query: int) -> RejectionMemory:
        """The back-end holds the rejection of `candidate_id`: answers to `from_query` on were judged with it."""
        entries = tuple(
            replace(e, shared_from_query=from_query)
            if candidate_id and e.candidate_id == candidate_id and not e.shared_from_query
            else e
            for e in self.entries
        )
        return replace(self, entries=entries)

    def matches(
        self,
        candidate_id: str = "",
        position: GeoEstimate | None = None,
        signature: Sequence[float] = (),
        query_id: int = 0,
    ) -> RejectedTarget | None:
        """The remembered rejection this candidate looks like, or None. `query_id`: the query whose answer
        the candidate is in (0: none, or not known)."""
        return self.matches_each(((candidate_id, position, signature),), query_id)[0]

    def matches_each(
        self, candidates: Sequence[tuple[str, GeoEstimate | None, Sequence[float]]], query_id: int = 0
    ) -> tuple[RejectedTarget | None, ...]:
        """`matches` for each of one keyframe's candidates, given as (id, position, signature). Two candidates
        in one keyframe are two people, so a rejection matched by place alone is matched by the nearest of
        them only: at 30 m the radius and two sigma of both estimates reach 12 m, and a rejected person
        would otherwise hide the one standing beside them for the rest of the search."""
        found: list[RejectedTarget | None] = [None] * len(candidates)
        nearest: dict[int, tuple[float, int]] = {}  # entry -> (metres, candidate) of its nearest place match
        for i, (candidate_id, position, signature) in enumerate(candidates):
            for k, entry in enumerate(self.entries):
                if found[i] is None and (
                    (candidate_id and entry.candidate_id == candidate_id)
                    or (
                        signature
                        and entry.signature
                        and cosine_similarity(entry.signature, signature) >= self.signature_threshold
                    )
                ):
                    found[i] = entry
                metres = self._place_match(entry, position, query_id)
                if metres is not None and (k not in nearest or metres < nearest[k][0]):
                    nearest[k] = (metres, i)
        for k, (_, i) in sorted(nearest.items()):
            found[i] = found[i] or self.entries[k]
        return tuple(found)

    def _place_match(
        self, entry: RejectedTarget, position: GeoEstimate | None, query_id: int
    ) -> float | None:
        """How far `position` is from the nearer of `entry`'s places, when near enough to match; else None."""
        if position is None:
            return None
        judged = bool(entry.shared_from_query) and query_id >= entry.shared_from_query
        radius_m = 0.0 if judged else self.radius_m
        near = [
            d
            for at in (entry.position, entry.also_at)
            if at is not None and (d := self._near(at, position, radius_m)) is not None
        ]
        return min(near, default=None)

    def _near(self, a: GeoEstimate, b: GeoEstimate, radius_m: float) -> float | None:
        """The distance between `a` and `b` when within `radius_m` widened by their uncertainty; else None."""
        north, east = latlon_to_offset(a.lat_deg, a.lon_deg, b.lat_deg, b.lon_deg)
        sigma = math.hypot(a.sigma_m, b.sigma_m)
        # Two sigma of the combined error, but a very uncertain estimate cannot blank a whole area.
        allowed = radius_m + min(2.0 * sigma, 2.0 * self.radius_m)
        distance = math.hypot(north, east)
        return distance if distance <= allowed else None


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
