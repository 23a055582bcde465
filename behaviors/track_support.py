"""Whether the back-end's answers still support a trusted track: the detector's misses on the tracked box.

A Siamese tracker (NanoTrack) can hold a confident box on the background: the person walked under a roof
or out of the view and the box stayed on the roof, or on bare ground against the image's edge, where the
box cannot leave the frame and no per-frame loss signal fires (measured in flight: 3.9 s on ground at the
view's edge, then the 8 m find of issue 43). The keyframe answers see what the tracker cannot: the
detector proposes an object of the searched class on a real target as often as its detection curve says
for that size (`behaviors.detection_curve`, measured on real footage), and never on bare ground.

So each answer about a keyframe on which the track was trusted is a look at the tracked box: a candidate
touching it (any verdict: support means something of the class is there, not that it is the described one;
among people standing together the detector frames them apart from the tracker's box) supports the track;
none is a miss. The chance that a target really under the
box gave every miss since the last answer that found it is the product, over those misses, of the chance
that a look misses this target; below `max_miss_chance`, and after at least `min_unsupported_s` of misses
(one burst of blurred keyframes is not a loss), the track is unsupported: the tracker follows something the
detector does not see.

One target is not the average target. The curve is the population's rate by size; one person in spray or
in shade is found far less often (on the dev footage at 11-16 px: one surfer 14 % of frames, another
rider 100 %, the curve 41 %), and its misses come in runs. So the chance a look misses *this* target is
the beta-binomial's: the curve's POD counted as `prior_looks` looks of it, plus what the answers on this
track found (hits) and missed: P(found) = (prior_looks * POD + hits) / (prior_looks + hits + misses). A
target the answers kept finding is expected to be found again, and its misses add up fast; one they rarely
found says little by being missed. `prior_looks` 2 is the spread measured between the dev sequences'
rates at the same size (the variance of a rate p over a beta of strength n is p(1 - p) / (n + 1): about
1 at 16 px, 9 at 23 px).

The POD is the curve of what the mission acts on (found and not judged "no"), a lower bound on "proposed
at all". A size the curve claims nothing for (POD 0) with no hits on the track adds no evidence. Answers
are counted once per keyframe (an early and a final answer on the same keyframe are one look).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SupportSettings:
    # Below this chance that a target under the box gave every miss since the last find: unsupported. A
    # target the track found on its last ten answers, at a size found 90 % of the time: three misses.
    max_miss_chance: float = 0.001
    min_unsupported_s: float = 2.0  # the misses span at least this long (keyframe capture times)
    prior_looks: float = 2.0  # the curve's POD counts as this many looks of the target (module doc)

    def __post_init__(self) -> None:
        if not 0 < self.max_miss_chance < 1:
            raise ValueError("max_miss_chance must be in (0, 1)")
        if self.min_unsupported_s < 0:
            raise ValueError("min_unsupported_s must be >= 0")
        if self.prior_looks <= 0:
            raise ValueError("prior_looks must be above 0")


@dataclass(frozen=True)
class Support:
    """The account of one track: its record, and the run of misses since the last find (or its start)."""

    since_s: float | None = None  # capture time of the last keyframe that found the track (or its start)
    keyframe_id: int = -1  # the last keyframe counted: an answer about it or an older one counts no more
    hits: int = 0  # answers that found it, since the track started
    misses: int = 0  # answers that missed it, since the track started
    run: int = 0  # misses since the last find
    miss_chance: float = 1.0  # chance a target under the box would have given every miss of the run

    def unsupported(self, time_s: float, settings: SupportSettings = SupportSettings()) -> bool:
        """The misses say the box holds no target (module doc)."""
        return (
            self.run > 0
            and self.miss_chance < settings.max_miss_chance
            and self.since_s is not None
            and time_s - self.since_s >= settings.min_unsupported_s
        )


def started(keyframe_id: int, time_s: float, found: bool = False) -> Support:
    """A fresh account for a track started (or re-initialised) on `keyframe_id`, captured at `time_s`;
    `found`: on a detector's box (that keyframe is the track's first find), not an operator's."""
    return Support(since_s=time_s, keyframe_id=keyframe_id, hits=1 if found else 0)


def found_chance(state: Support, pod: float, settings: SupportSettings = SupportSettings()) -> float:
    """The chance the next look finds this target if it is under the box (module doc)."""
    pod = min(1.0, max(0.0, pod))
    n = settings.prior_looks
    return (n * pod + state.hits) / (n + state.hits + state.misses)


def judge_answer(
    state: Support,
    keyframe_id: int,
    time_s: float,
    found: bool,
    pod: float,
    settings: SupportSettings = SupportSettings(),
) -> Support:
    """The account after one answer about keyframe `keyframe_id` (captured at `time_s`) on which the track was
    trusted: `found` a candidate on the tracked box, else a miss; `pod` is the curve's at the box's size."""
    if keyframe_id <= state.keyframe_id:
        return state
    if found:
        return Support(time_s, keyframe_id, state.hits + 1, state.misses)
    chance = state.miss_chance * (1.0 - found_chance(state, pod, settings))
    since = state.since_s if state.since_s is not None else time_s
    return Support(since, keyframe_id, state.hits, state.misses + 1, state.run + 1, chance)
