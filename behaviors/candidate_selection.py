"""Choosing a back-end candidate: the first acquisition, and which one re-initialises the tracker
(CloudTrack paper, eq. C_box)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou


def select_first_acquisition(
    candidates: Sequence[Detection],
    accept_uncertain: bool,
    eligible: Callable[[Detection], bool] = lambda d: d.box.is_valid(),
) -> Detection | None:
    """The candidate a search starts tracking, never a "no".

    First the verifier's verdict ("yes", then "uncertain" where it may start), and within each the
    back-end's judgement of where the candidate stands and how large it is among the others in view
    (`Detection.placement_ok`, `backend.scene`: "the second from the left", "next to the pier", outside
    the boat a wakeboarder is towed behind): fitting first, then not judged, then not fitting; then the
    best detector score. The placement ranks, never rejects: with no other candidate, one that does not
    fit is still taken.

    An "uncertain" that nothing judged past the detector's class (`Detection.judged` false: the
    description names nothing the verifier can check) starts a search even when uncertain ones may not:
    no answer will ever say more, and in search and rescue an unconfirmed find, held for the supervisor,
    beats none. An "uncertain" the verifier did judge (too small to see, a colour half there) waits for
    a "yes", unless the description's rank picks it alone (`Detection.singled_out`: "the cyclist in the
    blue shirt closest to the camera" whose dark blue shirt reads mostly black); it then comes right after
    a "yes" that fits too. A relation that several may satisfy ("between", "next to") only ranks."""
    ranked = _start_ranks(candidates, accept_uncertain, eligible)
    return min(ranked, key=lambda pair: pair[0])[1] if ranked else None


def may_start(
    candidates: Sequence[Detection],
    accept_uncertain: bool,
    eligible: Callable[[Detection], bool] = lambda d: d.box.is_valid(),
) -> list[Detection]:
    """The candidates `select_first_acquisition` chooses among: what a search acts on in this answer (the
    detection curve counts the target found where it is one of them)."""
    return [d for _, d in _start_ranks(candidates, accept_uncertain, eligible)]


def alike(
    candidates: Sequence[Detection],
    chosen: Detection,
    accept_uncertain: bool,
    eligible: Callable[[Detection], bool] = lambda d: d.box.is_valid(),
) -> int:
    """How many others `select_first_acquisition` could have started on as well: the same verdict and
    placement as `chosen`, told apart by the detector's score alone. The supervisor should know that the
    choice among them was no judgement (three white cars at the front, "minivan" judged by nothing)."""
    ranked = _start_ranks(candidates, accept_uncertain, eligible)
    mine = next((rank[:2] for rank, d in ranked if d is chosen), None)
    return sum(1 for rank, d in ranked if d is not chosen and rank[:2] == mine)


def _start_ranks(
    candidates: Sequence[Detection], accept_uncertain: bool, eligible: Callable[[Detection], bool]
) -> list[tuple[tuple[int, int, float], Detection]]:
    """The candidates a search may start on, each with its rank (smallest first; see
    `select_first_acquisition`)."""
    pool = [d for d in candidates if d.verdict is not Verdict.NO and eligible(d)]
    picked = [d for d in pool if d.singled_out and d.placement_ok is True]
    singled = picked[0] if len(picked) == 1 else None
    may_start = [
        d for d in pool if d.verdict is Verdict.YES or accept_uncertain or not d.judged or d is singled
    ]

    def rank(d: Detection) -> tuple[int, int, float]:
        placement = {True: 0, None: 1, False: 2}[d.placement_ok]
        if d.verdict is Verdict.YES:
            return (0 if placement == 0 else 2, placement, -d.score)
        return (1 if d is singled else 3, placement, -d.score)

    return [(rank(d), d) for d in may_start]


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
