"""The status report's console fields (CONTRACT section 1) as the companion fills them, validated by the
back-end's own model (`cloudtrack.api_models.VehicleStatusIn`), and the find over MAVLink (section 3)."""

from __future__ import annotations

import math
from dataclasses import replace

from behaviors.actions import ReportCandidate
from behaviors.detection import Detection, Verdict
from behaviors.geolocation import GeoEstimate
from behaviors.geometry import Box
from behaviors.mission import EarlyStart, MissionState, State, Target
from behaviors.mission_commands import StartMission
from behaviors.telemetry import Telemetry
from cloudtrack.api_models import VehicleStatusIn
from companion.status_report import StatusReport
from tests.mavlink_harness import autopilot, gcs, receive_until, vehicle_link

POSITION = GeoEstimate(47.3977, 8.5456, 10.0, 2.0, 10.2, 14.1, 1.3)
BOX = Box(300, 200, 40, 90)


def confirmed(
    cid: str = "c3", by: str = "supervisor page", position: GeoEstimate = POSITION, seen_s: float = 90.0
) -> ReportCandidate:
    return ReportCandidate(cid, "green shirt", Verdict.YES, position, BOX, "confirmed", by, seen_s)


def following(mode: MissionState = MissionState.AWAITING_SUPERVISOR) -> State:
    telemetry = Telemetry(5.0, 47.3976, 8.5456, 10.0, yaw=math.radians(-90.0), mode="GUIDED", mission_item=7)
    return State(
        mode=mode, telemetry=telemetry, mission=StartMission("a person", "person", True, "7"), reason="why"
    )


def test_fields_validate_against_the_back_ends_model() -> None:
    clock = iter([1_764_000_000.5, 1_764_000_999.0])
    report = StatusReport((1280, 720), 640, wall_clock=lambda: next(clock))
    report.start("7")
    report.on_answer((Detection(BOX, 0.9, candidate_id="c1"), Detection(BOX, 0.8, candidate_id="c3")))
    report.on_answer((Detection(BOX, 0.9, candidate_id="c3"),))
    # Counted as put to the supervisor once each, however often reported; the boxes as detections.
    for cid in ("c1", "c3", "c3"):
        report.on_proposed(cid)
    report.on_rejection()
    report.on_keyframe(4711, Box(-20, 100, 100, 200))  # partly outside the image: clamped
    # Confirmed at event time 100 s, the position seen at 90 s: 10 s old.
    assert report.record_find(confirmed(), "a person in green", "QUJD", now_s=100.0) is not None
    search = {"mode": "GUIDED", "mission_item": 7, "mission_items": 24}
    fields = report.fields(following(), search)
    status = VehicleStatusIn(state="AWAITING_SUPERVISOR", **fields)
    assert status.reason == "why" and status.heading_deg == 270.0
    assert status.track_box == [0.0, 50.0, 40.0, 150.0] and status.frame_id == 4711  # 1280 px sent at 640
    assert status.progress is not None and status.progress.model_dump() == {
        "keyframes": 2,
        "detections": 3,
        "candidates": 2,
        "rejected": 1,
    }
    assert status.track_id is None  # nothing tracked in this state
    assert status.search is not None and status.search.mission_item == 7
    find = status.find
    assert find is not None and find.candidate_id == "c3" and find.position == [47.3977, 8.5456]
    assert find.time == 1_764_000_000.5 and find.confirmed_by == "supervisor page" and find.sigma_m == 1.3
    assert find.prompt == "a person in green" and find.crop_jpeg_b64 == "QUJD"
    assert find.seen_at == 1_764_000_000.5 - 10.0
    # A later confirmed report moves the find; its time, who and crop stay; its position's time is new.
    moved = replace(POSITION, lat_deg=47.39775)
    again = report.record_find(
        confirmed(by="gcs", position=moved, seen_s=120.0), "a person in green", None, now_s=120.5
    )
    assert again is not None and again.lat == 47.39775 and again.time == 1_764_000_000.5
    assert again.seen_at == 1_764_000_999.0 - 0.5
    assert (
        again.confirmed_by == "supervisor page" and again.crop_jpeg_b64 == "QUJD" and len(report.finds) == 1
    )


def test_no_box_while_searching_and_counters_begin_again_with_a_new_mission() -> None:
    report = StatusReport((640, 480))
    report.start("7")
    report.on_answer((Detection(BOX, 0.9, candidate_id="c1"),))
    report.on_keyframe(12, BOX)
    assert "track_box" not in report.fields(following(MissionState.SEARCHING), None)
    assert report.fields(following(), None)["track_box"] == [300.0, 200.0, 340.0, 290.0]
    report.start("7")  # the same mission restarted: kept
    assert report.fields(following(), None)["progress"]["keyframes"] == 1
    report.start("8")
    assert report.fields(following(), None)["progress"] == {
        "keyframes": 0,
        "detections": 0,
        "candidates": 0,
        "rejected": 0,
    }
    no_position = confirmed(position=replace(POSITION, lat_deg=math.nan))
    assert report.record_find(no_position, "p", None, now_s=1.0) is None and "find" not in report.fields(
        following(), None
    )


def test_the_find_reaches_the_gcs_as_a_popup_and_a_geo_status() -> None:
    with autopilot("ardupilot", start_height_m=10.0) as sim, vehicle_link(sim) as link, gcs(sim) as ground:
        link.kick()
        link.announce_find(47.397851, 8.545712, 1.25, 14.0, "a person in a green shirt", "gcs", 45.2)
        text = receive_until(ground, lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("FOUND "))
        assert text is not None and text.text == "FOUND 47.397851,8.545712 +-1.2m" and text.severity == 2
        assert len(text.text) <= 50
        detail = receive_until(ground, lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("FOUND:"))
        assert detail is not None and "green shirt" in detail.text
        # The position's age, in the line's second chunk (66 bytes: two linked STATUSTEXTs).
        rest = receive_until(
            ground, lambda m: m.get_type() == "STATUSTEXT" and m.id == detail.id != 0 and m.chunk_seq == 1
        )
        assert rest is not None and (detail.text + rest.text).endswith("(confirmed by gcs; seen 45 s before)")
        geo = receive_until(ground, lambda m: m.get_type() == "CAMERA_TRACKING_GEO_STATUS")
        assert geo is not None and (geo.lat, geo.lon) == (473978510, 85457120)
        assert geo.get_srcComponent() == 100 and geo.h_acc == 1.25 and geo.dist == 14.0
        assert math.isclose(geo.alt, 488.0, abs_tol=0.01)  # the ground: home's altitude AMSL
        assert math.isnan(geo.vel_n)


def test_the_tracked_box_carries_the_candidates_own_id_once_verified() -> None:
    """Issue 45: the live view names the tracked box as the GCS and the card do (the id the candidate was
    first proposed with), never while only the fast stage chose it (its id may still change)."""
    report = StatusReport((640, 480))
    report.start("7")
    report.on_keyframe(12, BOX)
    target = Target("7be4dec8ac3b", "gray shirt", Verdict.UNCERTAIN, BOX, 12, 1.0)
    state = replace(following(), target=target)
    assert report.fields(state, None)["track_id"] == "7be4dec8ac3b"
    assert (
        VehicleStatusIn(state="AWAITING_SUPERVISOR", **report.fields(state, None)).track_id == "7be4dec8ac3b"
    )
    early = replace(state, target=replace(target, early=EarlyStart(3, BOX, 1.0)))
    assert "track_id" not in report.fields(early, None)
    assert "track_id" not in report.fields(replace(state, mode=MissionState.SEARCHING), None)
