"""A supervisor's decision that names no candidate (the GCS's candidate 0, what QGroundControl's buttons send)
is for the candidate the operator was shown. When the candidate it would apply to changed a moment before it
arrived, it was pressed for the one before: the new one's line cannot have reached the operator yet (one
round trip over the telemetry link, and a press under way). Such a decision is refused, with the candidate
now awaiting named, and a press after the guard time applies to it. Decisions naming a candidate (the
supervisor page) never need this.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DecisionGuard:
    """Which candidate an undirected decision would apply to now, and since when (event time)."""

    candidate_id: str = ""  # empty: none
    since_s: float = 0.0


def observe(guard: DecisionGuard, candidate_id: str, now_s: float) -> DecisionGuard:
    """The guard after an event: a different candidate (or none) restarts its time."""
    if candidate_id == guard.candidate_id:
        return guard
    return DecisionGuard(candidate_id, now_s)


def too_new(guard: DecisionGuard, now_s: float, guard_s: float) -> bool:
    """Whether an undirected decision at `now_s` may have been meant for the candidate before this one."""
    return bool(guard.candidate_id) and now_s - guard.since_s < guard_s
