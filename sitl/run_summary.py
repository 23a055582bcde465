"""The lines `cloudtrack-sim run` prints after one scenario: what the scenario is about, from its results JSON.

A search scenario prints the search's figures (time to find, coverage and POD at the find, the find's
position error, the break-offs and resumes). The follow figures (pixel error, standoff RMSE) are printed only
where the scenario checks a follow: in a search the companion tracks while the survey flies its own line,
so a standoff error of tens of metres there is no failure (they stay in the JSON).
"""

from __future__ import annotations

from typing import Any

from sitl.scenarios import Scenario


def _pct(share: Any) -> str:
    return "?" if share is None else f"{float(share) * 100:.0f} %"


def _unflown(dropout: dict[str, Any]) -> str:
    """What the back-end listed unflown: its m2, or that the vehicle's part was unknown (listed without it)."""
    if "listed_s" in dropout and dropout.get("unflown_m2") is None:
        return "its part unknown"
    return f"{dropout.get('unflown_m2')} m2 unflown"


def _s(seconds: Any) -> str:
    return "none" if seconds is None else f"{seconds} s"


def _m(metres: Any) -> str:
    return "?" if metres is None else f"{metres} m"


def _breaks(m: dict[str, Any]) -> str:
    episodes = m.get("mission_breaks") or []
    if not episodes:
        return "never left the mission"
    said = []
    for e in episodes:
        back = f"resumed at item {e['resumed_at']}" if e.get("resumed_at") is not None else "not resumed"
        said.append(f"left at item {e.get('left_at')} ({e.get('left_t')} s), {back}")
    return "; ".join(said)


def search_line(vid: str, m: dict[str, Any]) -> str:
    """A search's figures for one vehicle; the find's only when there is one."""
    pod = m.get("pod_at_target")
    sighted = f"first sighting {_s(m.get('time_to_first_sighting_s'))}"
    if m.get("found"):
        error = f"find's position error {_m(m.get('geolocation_error_m'))}"
        if m.get("geolocation_error_at_seen_m") is not None:
            error += f" ({_m(m['geolocation_error_at_seen_m'])} against where the person was when seen)"
        found = (
            f"found in {_s(m.get('time_to_find_s'))} ({sighted}), coverage at the find "
            f"{_pct(m.get('coverage_at_find'))} (at the end {_pct(m.get('coverage_at_end'))}), {error}"
        )
    else:
        found = f"NOT found ({sighted}), coverage at the end {_pct(m.get('coverage_at_end'))}"
    return (
        f"  {vid} search: {found}, POD at the person {'none reported' if pod is None else f'{pod:.2f}'}, "
        f"rejected {len(m.get('rejected') or [])} of {len(m.get('proposed') or [])} proposed; "
        f"mission: {_breaks(m)}"
    )


def follow_line(vid: str, m: dict[str, Any], with_control: bool) -> str:
    """The follow's figures; the control's (pixel error, standoff) only where the scenario checks them."""
    line = (
        f"  {vid}{'' if with_control else ' tracking'}: confirmed {m['confirmed']}, first candidate {m['time_to_first_candidate_s']} s "
        f"(verified {m['time_to_verified_candidate_s']} s), "
        f"confirmation {m['time_to_confirmation_s']} s, in view {m['target_in_view_ratio']}"
    )
    if not with_control:
        return line + f", re-inits {m['reinits']}"
    return line + (
        f", pixel error {m['pixel_error_mean_px']}/{m['pixel_error_p95_px']} px (mean/p95), "
        f"standoff RMSE {m['standoff_rmse_m']} m, max speed {m['max_commanded_speed_m_s']} m/s, "
        f"setpoints {m['setpoint_rate_hz']} Hz, re-inits {m['reinits']}"
    )


def summary_lines(results: dict[str, Any], scenario: Scenario) -> list[str]:
    """The summary of one run, as printed."""
    lines = [
        f"scenario {results['scenario']} ({results['autopilot']}, tracker {results['tracker']}): "
        f"{results['outcome'].upper()}"
    ]
    search = scenario.survey is not None
    control = "standoff" in scenario.checks or not search
    for vid, m in results["vehicles"].items():
        if search:
            lines.append(search_line(vid, m))
        lines.append(follow_line(vid, m, control))
    if search and not control:
        lines.append(
            "  (the follow's standoff and image-centre figures are left out: the survey flies its own line while "
            "a candidate is tracked, so they measure no search; they are in the JSON)"
        )
    if results.get("fleet"):
        lines.extend(fleet_lines(results["fleet"]))
    lines.extend(f"  FAILED: {failure}" for failure in results["failures"])
    return lines


def fleet_lines(fleet: dict[str, Any]) -> list[str]:
    """A fleet's search (`fleet-search`): the parts, the plan's times, the drop-out and re-plan, the merged
    coverage and the mission's finds."""
    survey = fleet.get("survey") or {}
    parts = ", ".join(
        f"{vid} {p['lanes']} ({p['time_s']} s)" for vid, p in (survey.get("parts") or {}).items()
    )
    dropout, replan = fleet.get("dropout") or {}, fleet.get("replan") or {}
    coverage = fleet.get("coverage_at_end")
    return [
        f"  fleet plan: {parts}; whole area {_s(survey.get('whole_area_s'))}, one vehicle alone "
        f"{_s(survey.get('one_vehicle_alone_s'))}",
        f"  fleet drop-out: {dropout.get('vehicle')} sent home at {_s(dropout.get('rtl_s'))}, listed by the back-end "
        f"at {_s(dropout.get('listed_s'))} ({dropout.get('reason')}, {_unflown(dropout)}); "
        f"replan exited {replan.get('exit_code')} after {_s(replan.get('took_s'))}: "
        f"{(replan.get('output') or ['-'])[-1]}",
        f"  fleet search: merged coverage {'?' if coverage is None else f'{coverage:.3f}'} at the end, the area "
        f"covered at {_s(fleet.get('time_to_cover_s'))}; {len(fleet.get('finds') or [])} find(s) on the back-end, "
        f"{len(fleet.get('sightings') or [])} sighting(s) of it by other vehicles",
    ]
