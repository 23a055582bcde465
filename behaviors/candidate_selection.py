"""Choosing a back-end candidate: the first acquisition, and which one re-initialises the tracker
(CloudTrack paper, eq. C_box)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box
from behaviors.spatial_relations import Relation, narrow_by_relation


def select_first_acquisition(
    candidates: Sequence[Detection],
    accept_uncertain: bool,
    relation: Relation | None,
    eligible: Callable[[Detection], bool] = lambda d: d.box.is_valid(),
) -> Detection | None:
    """The candidate a search starts tracking: "yes" first, then "uncertain" if allowed, never a "no";
    among them the ones not placed against the description (`Detection.placement_ok` false: in the
    boat a wakeboarder is towed behind), then the ones that stand as the prompt relates the target to
    others ("between the man in red and ..."; every candidate in view counts as one of the others), then
    the best detector score. Each narrowing applies only when some candidate passes it.

    An "uncertain" that nothing judged past the detector's class (`Detection.judged` false: the
    description names nothing the verifier can check) starts a search even when uncertain ones may not:
    no answer will ever say more, and in search and rescue an unconfirmed find, held for the supervisor,
    beats none. An "uncertain" the verifier did judge (too small to see, a colour half there) waits for
    a "yes"."""
    boxes = [d.box for d in candidates]
    tiers: tuple[Callable[[Detection], bool], ...] = (
        lambda d: d.verdict is Verdict.YES,
        lambda d: d.verdict is Verdict.UNCERTAIN and (accept_uncertain or not d.judged),
    )
    for admitted in tiers:
        indices = [i for i, d in enumerate(candidates) if admitted(d) and eligible(d)]
        placed = [i for i in indices if candidates[i].placement_ok is not False]
        indices = placed or indices
        pool = [candidates[i] for i in narrow_by_relation(relation, indices, boxes)]
        if pool:
            return max(pool, key=lambda d: d.score)
    return None


def c_box(prev: Box, cand: Box) -> float:
    """C_box = sum over d in {x, y} of |c_prev - c_cand| + |s_prev - s_cand| (centres and sizes, pixels, L1)."""
    return abs(prev.cx - cand.cx) + abs(prev.cy - cand.cy) + abs(prev.w - cand.w) + abs(prev.h - cand.h)


def select_by_c_box(prev: Box, candidates: Sequence[Detection]) -> Detection | None:
    """The candidate closest to the last trusted box by C_box; None when there are none.

    Ties go to the earlier candidate so the choice is deterministic.
    """
    best: Detection | None = None
    best_cost = float("inf")
    for cand in candidates:
        if not cand.box.is_valid():
            continue
        cost = c_box(prev, cand.box)
        if cost < best_cost:
            best, best_cost = cand, cost
    return best


def select_by_score(candidates: Sequence[Detection]) -> Detection | None:
    """The reference code's policy: the candidate with the highest detector score."""
    valid = [c for c in candidates if c.box.is_valid()]
    return max(valid, key=lambda c: c.score) if valid else None
