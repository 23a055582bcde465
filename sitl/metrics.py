"""Scenario metrics from what the simulator saw: pure functions over recorded samples, no I/O.

Inputs are the camera's ground truth per rendered frame, the setpoints the autopilot received, the
companion's state changes and the safety events, all on one clock (seconds since the scenario started).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from behaviors.geometry import Box


@dataclass(frozen=True)
class FrameSample:
    """One rendered frame: where the vehicle and the target were, and the target's box if it was seen."""

    t: float
    drone_north: float
    drone_east: float
    target_north: float
    target_east: float
    target_box: Box | None  # None when out of the image or hidden
    target_visible: float = 0.0


@dataclass(frozen=True)
class SetpointSample:
    t: float
    forward: float
    right: float
    down: float
    yaw_rate: float

    @property
    def horizontal_speed(self) -> float:
        return math.hypot(self.forward, self.right)


@dataclass(frozen=True)
class TimedEvent:
    """A companion state change, a safety event or a scripted action, with its time and details."""

    t: float
    kind: str
    detail: dict[str, Any] = field(default_factory=dict)


SAFETY_KINDS = (
    "hold",
    "stop",
    "watchdog",
    "mode_change",
    "link_lost",
    "backend_lost",
    "frame_stale",
    "abort",
)


FOLLOW_STATES = frozenset({"following", "awaiting_supervisor", "confirmed"})


def following_intervals(
    states: Sequence[TimedEvent], end_t: float, following: frozenset[str] = FOLLOW_STATES
) -> list[tuple[float, float]]:
    """Intervals during which the companion followed a target (state events carry detail["state"])."""
    out: list[tuple[float, float]] = []
    start: float | None = None
    for ev in sorted(states, key=lambda e: e.t):
        is_following = str(ev.detail.get("state", "")).lower() in following
        if is_following and start is None:
            start = ev.t
        elif not is_following and start is not None:
            out.append((start, ev.t))
            start = None
    if start is not None:
        out.append((start, end_t))
    return out


def _inside(t: float, intervals: Sequence[tuple[float, float]]) -> bool:
    return any(a <= t <= b for a, b in intervals)


def percentile(values: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile (q in 0..100); nan for no values."""
    if not values:
        return math.nan
    s = sorted(values)
    pos = (len(s) - 1) * q / 100.0
    lo, hi = math.floor(pos), math.ceil(pos)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


def setpoint_rate(setpoints: Sequence[SetpointSample], intervals: Sequence[tuple[float, float]]) -> float:
    """Setpoints per second received within the intervals (0 for none)."""
    duration = sum(b - a for a, b in intervals)
    if duration <= 0:
        return 0.0
    return sum(1 for s in setpoints if _inside(s.t, intervals)) / duration


def last_setpoint_after(setpoints: Sequence[SetpointSample], t: float) -> float | None:
    """Seconds from t to the last setpoint received after t; None when none came after t."""
    later = [s.t for s in setpoints if s.t > t]
    return max(later) - t if later else None


def first_time(events: Sequence[TimedEvent], kind: str) -> float | None:
    times = [e.t for e in events if e.kind == kind]
    return min(times) if times else None


def summarise(
    frames: Sequence[FrameSample],
    setpoints: Sequence[SetpointSample],
    events: Sequence[TimedEvent],
    standoff_m: float,
    image_size: tuple[int, int],
    end_t: float,
    outcome: str,
    min_visible: float = 0.3,
    frozen: Sequence[tuple[float, float]] = (),
    unflown: Sequence[tuple[float, float]] = (),
) -> dict[str, Any]:
    """The metrics JSON of one vehicle's run (numbers rounded for reading; nan becomes None). `frozen`:
    intervals in which the companion process was stopped; its state still reads "following" there, but
    nothing of its control ran, so they count in neither the view nor the standoff (the coast measures them).
    `unflown`: intervals in which the autopilot was not in the mode that flies the companion's setpoints (PX4
    grants OFFBOARD only after a second of them), which count in neither for the same reason."""
    states = [e for e in events if e.kind == "state"]
    follow = following_intervals(states, end_t)
    excluded = [*frozen, *unflown]
    in_follow = [f for f in frames if _inside(f.t, follow) and not _inside(f.t, excluded)]
    w, h = image_size
    seen = [
        f
        for f in in_follow
        if f.target_box is not None
        and f.target_visible >= min_visible
        and 0 <= f.target_box.cx < w
        and 0 <= f.target_box.cy < h
    ]
    pixel_errors = [
        math.hypot(f.target_box.cx - w / 2, f.target_box.cy - h / 2) for f in seen if f.target_box
    ]
    standoff_errors = [
        math.hypot(f.drone_north - f.target_north, f.drone_east - f.target_east) - standoff_m
        for f in in_follow
    ]
    speeds = [s.horizontal_speed for s in setpoints]
    safety = [{"t": round(e.t, 3), "kind": e.kind, **e.detail} for e in events if e.kind in SAFETY_KINDS]

    def num(x: float | None, nd: int = 3) -> float | None:
        return None if x is None or not math.isfinite(x) else round(x, nd)

    return {
        "outcome": outcome,
        "time_to_first_candidate_s": num(first_time(events, "candidate")),
        "time_to_verified_candidate_s": num(first_time(events, "verified")),
        "time_to_confirmation_s": num(first_time(events, "confirmed")),
        "follow_time_s": num(sum(b - a for a, b in follow)),
        "target_in_view_ratio": num(len(seen) / len(in_follow)) if in_follow else None,
        "pixel_error_mean_px": num(sum(pixel_errors) / len(pixel_errors), 1) if pixel_errors else None,
        "pixel_error_p95_px": num(percentile(pixel_errors, 95), 1) if pixel_errors else None,
        "standoff_rmse_m": num(math.sqrt(sum(e * e for e in standoff_errors) / len(standoff_errors)))
        if standoff_errors
        else None,
        "max_commanded_speed_m_s": num(max(speeds)) if speeds else 0.0,
        "reinits": sum(1 for e in events if e.kind == "reinit"),
        "setpoint_rate_hz": num(setpoint_rate(setpoints, follow), 1),
        "setpoints_received": len(setpoints),
        "safety_events": safety,
    }


def distance_coasted(
    track: Sequence[tuple[float, float, float]],
    t_fault: float,
    still_m_s: float = 0.3,
    window_s: float = 10.0,
) -> float:
    """Ground distance (m) the vehicle travelled from `t_fault` until it came to rest.

    `track` is (t, north, east) per rendered frame. At rest: under `still_m_s` averaged over 0.5 s. The
    path is summed over 0.1 s steps, so position noise at a standstill adds little; `window_s` bounds it.
    """
    pts = [p for p in track if t_fault <= p[0] <= t_fault + window_s]
    if len(pts) < 2:
        return 0.0
    thinned = [pts[0]]
    for p in pts[1:]:
        if p[0] - thinned[-1][0] >= 0.1:
            thinned.append(p)
    travelled = 0.0
    for i in range(1, len(thinned)):
        a, b = thinned[i - 1], thinned[i]
        later = [q for q in thinned[i:] if q[0] - b[0] <= 0.5]
        if b[0] - t_fault > 0.2 and len(later) >= 2:
            span = later[-1][0] - later[0][0]
            if span > 0 and math.dist(later[0][1:], later[-1][1:]) / span < still_m_s:
                travelled += math.dist(a[1:], b[1:])
                break
        travelled += math.dist(a[1:], b[1:])
    return travelled


@dataclass(frozen=True)
class PoseSample:
    """Where the vehicle was (world metres, down from home, heading in degrees) at time t."""

    t: float
    north: float
    east: float
    down: float
    heading_deg: float


def heading_error_at(
    estimates: Sequence[PoseSample], truth: Sequence[PoseSample], t: float, max_gap_s: float = 0.1
) -> float | None:
    """The autopilot's heading error (deg, signed: estimate minus truth) at time `t`: the estimate nearest in
    time against the truth sample nearest to it, within `max_gap_s` of each other; None without one."""
    if not estimates or not truth:
        return None
    e = min(estimates, key=lambda s: abs(s.t - t))
    p = min(truth, key=lambda s: abs(s.t - e.t))
    if abs(p.t - e.t) > max_gap_s:
        return None
    return math.remainder(e.heading_deg - p.heading_deg, 360.0)


def estimate_error(
    estimates: Sequence[PoseSample], truth: Sequence[PoseSample], max_gap_s: float = 0.1
) -> dict[str, float] | None:
    """How far the autopilot's estimate was from the truth (each estimate against the nearest truth sample in
    time, within `max_gap_s`; both sorted by time): horizontal mean, p95 and max (m), vertical max (m), heading
    mean and max (deg). None without a single pair."""
    if not truth:
        return None
    horizontal: list[float] = []
    vertical: list[float] = []
    heading: list[float] = []
    j = 0
    for e in estimates:
        while j + 1 < len(truth) and abs(truth[j + 1].t - e.t) <= abs(truth[j].t - e.t):
            j += 1
        p = truth[j]
        if abs(p.t - e.t) > max_gap_s:
            continue
        horizontal.append(math.hypot(e.north - p.north, e.east - p.east))
        vertical.append(abs(e.down - p.down))
        heading.append(abs(math.remainder(e.heading_deg - p.heading_deg, 360.0)))
    if not horizontal:
        return None
    return {
        "horizontal_mean_m": round(sum(horizontal) / len(horizontal), 2),
        "horizontal_p95_m": round(percentile(horizontal, 95), 2),
        "horizontal_max_m": round(max(horizontal), 2),
        "vertical_max_m": round(max(vertical), 2),
        "heading_mean_deg": round(sum(heading) / len(heading), 1),
        "heading_max_deg": round(max(heading), 1),
        "samples": len(horizontal),
    }
