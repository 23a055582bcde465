"""Choosing a back-end candidate: the first acquisition, and which one re-initialises the tracker
(CloudTrack paper, eq. C_box)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou
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


SAME_CANDIDATE_IOU = 0.5  # two answers about one keyframe name the same person when their boxes overlap this


def settle_early_choice(
    candidates: Sequence[Detection],
    early_box: Box,
    choose: Callable[[Sequence[Detection]], Detection | None],
) -> tuple[Detection | None, bool]:
    """The final verdicts on the keyframe a track started on early (on `early_box`): (the candidate to
    track, whether it is the early choice kept). The early choice is kept while `choose` accepts its
    candidate in the final answer; another candidate also accepted is no reason to switch (a lenient VLM
    accepts bystanders too). Otherwise `choose` picks among all; None: it accepts no one."""
    same = [d for d in candidates if iou(d.box, early_box) >= SAME_CANDIDATE_IOU]
    if same:
        kept = choose([max(same, key=lambda d: iou(d.box, early_box))])
        if kept is not None:
            return kept, True
    return choose(candidates), False


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
