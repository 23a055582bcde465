"""When the loss signals untrust a track, and when it is trusted again (the "verified" policy).

Measured on real footage (docs/benchmarks.md), most false alarms that stopped a drone following the
right person were one signal alone flickering for a few frames: the colour histogram (`appearance`)
of a surfer in spray, VitTrack's score on a small target. A flag that comes and goes per frame also
makes a flight stop and start following (every LOST entry sends a zero setpoint and a re-detection).
So the signals are weighed as evidence over time, in seconds of the sequence or flight clock:

- *Strong* evidence untrusts the track at once: a geometric or tracker signal (`tracker_failed`,
  `left_frame`, `jump`: the box itself is wrong) or two independent weak signals on the same frame
  (the tracker's own score and the colour model agree that it is not the target).
- A *weak* signal alone (`score`, `collapsed`, `appearance`: the tracker's own confidence, or a model
  of the target's shape since the start or of its colours; 25 of nano's 42 `collapsed` frames were on
  a crouching target) must persist: each frame it fires adds its time to an evidence account, each quiet frame
  takes its time away, and the track is untrusted once the account holds `persistence_s` seconds.
- Recovery has the same hysteresis: strong evidence fills the account; a lost track is trusted again
  only once quiet frames have emptied it (`persistence_s` seconds without an alarm), unless a back-end
  answer confirms the track first (the caller then starts a fresh `LossEvidence`).

`persistence_s` 0 gives the per-frame behaviour (every alarm untrusts, every quiet frame re-trusts).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

WEAK_SIGNALS = frozenset({"score", "collapsed", "appearance"})  # [tracker] weak_loss_signals
_EPS = 1e-9


@dataclass(frozen=True)
class LossEvidenceSettings:
    persistence_s: float = 1.0  # seconds of evidence to untrust on a weak signal alone, and to re-trust
    weak_signals: frozenset[str] = WEAK_SIGNALS
    # False: the weak signals are no evidence at all, alone or together (only a geometric one untrusts the
    # track): for targets they were not measured on (`[tracker] loss_model_classes`), where their alarms
    # on the dev set were as often on the target as off it.
    weigh_weak: bool = True

    def __post_init__(self) -> None:
        if self.persistence_s < 0:
            raise ValueError("persistence_s must be >= 0")


@dataclass(frozen=True)
class LossEvidence:
    """The account for one track. `reason` is "" while trusted, else the signal that untrusted it."""

    evidence_s: float = 0.0  # net seconds of alarm, within [0, persistence_s]
    reason: str = ""
    time_s: float | None = None  # the last frame's time

    @property
    def trusted(self) -> bool:
        return not self.reason


def judge_frame(
    state: LossEvidence,
    time_s: float,
    fired: Sequence[str],
    settings: LossEvidenceSettings = LossEvidenceSettings(),
) -> LossEvidence:
    """The account after one frame at `time_s` on which the signals `fired` (names, in the loss
    detector's order; only the enabled ones)."""
    limit = settings.persistence_s
    dt = 0.0 if state.time_s is None else max(0.0, time_s - state.time_s)
    weak = [name for name in fired if name in settings.weak_signals]
    if not settings.weigh_weak:
        fired = [name for name in fired if name not in settings.weak_signals]
        weak = []
    strong = len(weak) < len(fired) or len(weak) >= 2
    if strong:
        # Name what is wrong with the box itself when a geometric signal fired.
        reason = next((name for name in fired if name not in settings.weak_signals), fired[0])
        return LossEvidence(limit, reason, time_s)
    if weak:
        evidence = min(limit, state.evidence_s + dt)
        lost = evidence >= limit - _EPS or bool(state.reason)
        return LossEvidence(evidence, weak[0] if lost else "", time_s)
    evidence = max(0.0, state.evidence_s - dt)
    reason = state.reason if evidence > _EPS else ""
    return LossEvidence(evidence, reason, time_s)
