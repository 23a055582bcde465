"""The SITL world, camera renderer, frame transport, simulated detector and metrics."""

from __future__ import annotations

import math
import socket
import struct
import time

import cv2
import numpy as np
import pytest

from behaviors.camera_model import CameraModel
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.geometry import Box
from behaviors.survey_planner import SurveySettings, plan_survey, rectangle
from companion.vision.frame_sources import open_source
from sitl.camera_render import Projector, Renderer, VehiclePose, read_timecode, unoccluded_area
from sitl.camera_server import CameraServer
from sitl.frame_transport import (
    HEADER,
    FrameStreamError,
    FrameStreamReader,
    encode_frame,
    parse_url,
)
from sitl.metrics import (
    FrameSample,
    PoseSample,
    SetpointSample,
    TimedEvent,
    estimate_error,
    last_setpoint_after,
    percentile,
    summarise,
)
from sitl.scenario_runner import MOUNT_PITCH_DEG
from sitl.scenarios import SurveySpec
from sitl.simulated_detector import DetectorNoise, SimulatedPersonDetector
from sitl.world import CLOTHING, Person, distractor_world, search_world

CAMERA = CameraModel.from_hfov(640, 480, 70.0, -45.0)
BEHIND = VehiclePose(8.0, 0.0, -10.0)  # 12 m behind the target's start, 10 m up, facing north


@pytest.fixture(scope="module")
def world_and_renderer():
    world = distractor_world(seed=3, occluder_at_m=15.0)
    return world, Renderer(world, CAMERA)


def test_world_is_deterministic_and_people_walk_at_their_speed() -> None:
    a, b = distractor_world(seed=7), distractor_world(seed=7)
    assert a == b
    assert distractor_world(seed=8).people != a.people
    target = a.person("target")
    n0, e0, _ = target.state_at(0.0)
    n1, e1, heading = target.state_at(10.0)
    assert math.dist((n0, e0), (n1, e1)) == pytest.approx(15.0, abs=1e-6)
    assert heading == pytest.approx(0.0)
    shirts = [p.shirt for p in a.people]
    assert len(set(shirts)) == len(shirts)
    assert {p.pose for p in a.people} == {"standing", "sitting", "lying"}


def test_person_stops_at_end_and_loops() -> None:
    p = Person("p", "red", waypoints=((0.0, 0.0), (3.0, 0.0)), speed=1.0)
    assert p.state_at(100.0)[:2] == (3.0, 0.0)
    looping = Person("q", "red", waypoints=((0.0, 0.0), (3.0, 0.0)), speed=1.0, loop=True)
    assert looping.state_at(6.0)[:2] == pytest.approx((0.0, 0.0))
    assert looping.state_at(4.5)[0] == pytest.approx(1.5)


def test_render_draws_every_person_with_a_box_and_the_shirt_colour_in_it(world_and_renderer) -> None:
    world, renderer = world_and_renderer
    frame = renderer.render(BEHIND, 0.0, 42)
    assert frame.image.shape == (480, 640, 3)
    ids = {tb.person_id for tb in frame.truth}
    assert ids == {p.person_id for p in world.people}
    for tb in frame.truth:
        assert tb.visible > 0.8
        crop = (
            frame.image[int(tb.box.y) : int(tb.box.y2), int(tb.box.x) : int(tb.box.x2)]
            .reshape(-1, 3)
            .astype(int)
        )
        shirt = np.array(CLOTHING[tb.shirt])
        # The torso is painted in the shirt colour: many pixels of the box are that colour.
        close = np.count_nonzero(np.abs(crop - shirt).sum(axis=1) < 40)
        assert close >= 0.1 * len(crop), (tb.person_id, close, len(crop))
    target = next(tb for tb in frame.truth if tb.person_id == "target")
    # The target is straight ahead, so its box straddles the image's vertical centre line.
    assert target.box.x < 320 < target.box.x2


def test_projection_puts_a_point_on_the_optical_axis_in_the_image_centre() -> None:
    pose = VehiclePose(0.0, 0.0, -10.0, yaw=math.radians(30))
    proj = Projector(CAMERA, pose)
    along = 10.0  # 45 degrees down from 10 m: the axis meets the ground 10 m ahead
    pt = np.array([[along * math.cos(math.radians(30)), along * math.sin(math.radians(30)), 0.0]])
    pix, depth = proj.project(pt)
    assert pix[0] == pytest.approx([320.0, 240.0], abs=1e-6)
    assert depth[0] == pytest.approx(math.hypot(10, 10))


def test_target_under_the_roof_is_reported_hidden(world_and_renderer) -> None:
    _, renderer = world_and_renderer
    t = 11.5  # target walked 17 m: under the roof spanning 12.5..17.5 m
    n = 20.0 + 1.5 * t
    frame = renderer.render(VehiclePose(n - 12.0, 0.0, -10.0), t, 1)
    target = next((tb for tb in frame.truth if tb.person_id == "target"), None)
    assert target is not None and target.visible < 0.2


def test_level_camera_sees_sky_above_the_horizon() -> None:
    import dataclasses

    level = dataclasses.replace(CAMERA, mount_pitch=0.0)
    frame = Renderer(distractor_world(seed=1), level).render(VehiclePose(0, 0, -10), 0.0, 1)
    assert tuple(int(c) for c in frame.image[10, 320]) == (215, 190, 160)
    assert tuple(int(c) for c in frame.image[400, 320]) != (215, 190, 160)


def test_timecode_survives_jpeg_and_scaling() -> None:
    frame = Renderer(distractor_world(seed=2), CAMERA).render(BEHIND, 0.0, 0xABCDE)
    assert read_timecode(frame.image) == 0xABCDE
    ok, jpg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, 50])
    assert ok and read_timecode(cv2.imdecode(jpg, cv2.IMREAD_COLOR)) == 0xABCDE
    assert read_timecode(cv2.resize(frame.image, (320, 240)), width=640) == 0xABCDE


def test_simulated_detector_finds_people_scales_boxes_and_refuses_other_classes(world_and_renderer) -> None:
    from backend.supersets import UnknownSupersetError

    _, renderer = world_and_renderer
    frame = renderer.render(BEHIND, 0.0, 9)
    record = frame.record()
    exact = SimulatedPersonDetector(
        lambda fid: record if fid == 9 else None,
        noise=DetectorNoise(miss_rate=0.0, jitter_px=0.0, false_positives=0.0),
    )
    found = exact.detect(frame.image, ["person"])  # no frame id: read from the timecode
    assert len(found) == len(frame.truth)
    assert len(exact.detect(frame.image, ["person"], frame_id=9)) == len(frame.truth)
    half = cv2.resize(frame.image, (320, 240))
    target = next(tb for tb in frame.truth if tb.person_id == "target")
    boxes = [d.box for d in exact.detect(half, ["person"], frame_id=9)]
    assert any(abs(b.cx - target.box.cx / 2) < 1.5 and abs(b.h - target.box.h / 2) < 1.5 for b in boxes)
    with pytest.raises(UnknownSupersetError):
        exact.detect(frame.image, ["boat"])
    # An unknown frame (no truth) gives no boxes rather than an error.
    assert SimulatedPersonDetector(lambda fid: None).detect(frame.image, ["person"]) == []
    noisy = SimulatedPersonDetector(
        lambda fid: record, noise=DetectorNoise(miss_rate=1.0, false_positives=3.0), seed=1
    )
    assert noisy.detect(frame.image, ["person"]) == noisy.detect(
        frame.image, ["person"]
    )  # seeded, repeatable


def test_simulated_detector_places_a_region_of_the_keyframe(world_and_renderer) -> None:
    """The back-end sends only the re-detection ROI: boxes come back in the region's own pixels."""
    _, renderer = world_and_renderer
    frame = renderer.render(BEHIND, 0.0, 11)
    record = frame.record()
    detector = SimulatedPersonDetector(
        lambda fid: record if fid == 11 else None,
        noise=DetectorNoise(miss_rate=0.0, jitter_px=0.0, false_positives=0.0),
    )
    target = next(tb for tb in frame.truth if tb.person_id == "target")
    x1, y1 = int(target.box.cx - 80), int(target.box.cy - 100)
    region = np.ascontiguousarray(frame.image[y1 : y1 + 200, x1 : x1 + 160])
    found = detector.detect(region, ["person"], frame_id=11)
    assert len(found) == 1
    assert found[0].box.cx == pytest.approx(target.box.cx - x1, abs=3)
    assert found[0].box.cy == pytest.approx(target.box.cy - y1, abs=3)
    # A region that is not part of this frame (noise) is not placed: no boxes rather than wrong ones.
    noise = np.random.default_rng(0).integers(0, 255, (200, 160, 3), dtype=np.uint8)
    assert detector.detect(noise, ["person"], frame_id=11) == []


def test_camera_server_streams_frames_with_truth_and_rejects_garbage() -> None:
    server = CameraServer(distractor_world(seed=4), CAMERA, lambda: BEHIND, fps=30.0).start()
    try:
        reader = FrameStreamReader(server.url)
        first = reader.read()
        second = reader.read()
        assert first.image.shape == (480, 640, 3)
        assert second.frame_id > first.frame_id
        assert read_timecode(second.image) == second.frame_id
        record = server.truth(second.frame_id)
        assert record is not None and {tb.person_id for tb in record.truth} >= {"target"}
        reader.close()
        # The companion's source keeps the renderer's frame ids, so keyframes name their ground truth.
        source = open_source(server.url)
        frame = source.read(timeout_s=5.0)
        assert frame is not None and read_timecode(frame.image) == frame.frame_id
        assert source.stats.connected and source.live
        source.close()
    finally:
        server.stop()
    with pytest.raises(ValueError, match="sim\\+tcp://HOST:PORT"):
        parse_url("http://127.0.0.1:80")
    # A peer that speaks something else: a clear FrameStreamError, not a crash or a giant allocation.
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    reader = FrameStreamReader(f"sim+tcp://127.0.0.1:{port}")
    conn, _ = listener.accept()
    conn.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n".ljust(HEADER.size, b"\0"))
    with pytest.raises(FrameStreamError, match="bad magic"):
        reader.read()
    conn.sendall(struct.pack("!4sIddHHI", b"CTF1", 1, 0.0, 0.0, 640, 480, 12))
    with pytest.raises(FrameStreamError, match="bad frame header"):
        reader.read()
    reader.close()
    conn.close()
    listener.close()
    packet = encode_frame(5, 1.0, time.time(), np.zeros((4, 6, 3), np.uint8))
    assert len(packet) == HEADER.size + 72


def test_metrics_summary() -> None:
    events = [
        TimedEvent(1.0, "candidate"),
        TimedEvent(2.0, "state", {"state": "following"}),
        TimedEvent(2.5, "confirmed"),
        TimedEvent(4.0, "state", {"state": "confirmed"}),
        TimedEvent(6.0, "state", {"state": "lost"}),
        TimedEvent(6.0, "hold", {"reason": "test"}),
    ]
    frames = [
        FrameSample(t / 10, 0.0, 0.0, 13.0, 0.0, Box.from_center(330, 240, 10, 30) if t % 4 else None, 1.0)
        for t in range(0, 80)
    ]
    setpoints = [SetpointSample(2.0 + i / 15, 1.0, 1.0, 0.0, 0.0) for i in range(60)]
    m = summarise(frames, setpoints, events, standoff_m=12.0, image_size=(640, 480), end_t=8.0, outcome="ok")
    assert m["time_to_first_candidate_s"] == 1.0
    assert m["time_to_confirmation_s"] == 2.5
    assert m["follow_time_s"] == 4.0
    assert m["target_in_view_ratio"] == pytest.approx(0.75, abs=0.03)
    assert m["pixel_error_mean_px"] == 10.0
    assert m["standoff_rmse_m"] == 1.0
    assert m["max_commanded_speed_m_s"] == pytest.approx(math.sqrt(2), abs=1e-3)
    assert m["setpoint_rate_hz"] == pytest.approx(15.0, abs=0.3)
    assert m["safety_events"] == [{"t": 6.0, "kind": "hold", "reason": "test"}]
    assert last_setpoint_after(setpoints, 5.0) == pytest.approx(2.0 + 59 / 15 - 5.0)
    assert last_setpoint_after(setpoints, 100.0) is None
    assert percentile([1.0, 2.0, 3.0, 4.0], 50) == 2.5


def test_frozen_seconds_count_in_neither_view_nor_standoff() -> None:
    """A stopped companion still reads "following"; the target walking off then is the coast's to judge."""
    events = [TimedEvent(0.0, "state", {"state": "following"})]
    # 13 m off (12 m standoff) and centred, but 20 m off and out of view from 2 s to 3 s.
    frames = [
        FrameSample(
            t / 10,
            0.0,
            0.0,
            20.0 if 20 <= t <= 30 else 13.0,
            0.0,
            None if 20 <= t <= 30 else Box.from_center(320, 240, 10, 30),
            1.0,
        )
        for t in range(0, 50)
    ]
    plain = summarise(frames, [], events, standoff_m=12.0, image_size=(640, 480), end_t=5.0, outcome="ok")
    frozen = summarise(
        frames,
        [],
        events,
        standoff_m=12.0,
        image_size=(640, 480),
        end_t=5.0,
        outcome="ok",
        frozen=[(2.0, 3.0)],
    )
    assert plain["standoff_rmse_m"] > 3.0 and plain["target_in_view_ratio"] < 0.8
    assert frozen["standoff_rmse_m"] == 1.0 and frozen["target_in_view_ratio"] == 1.0
    # The same for seconds the autopilot was not yet flying the companion's setpoints (PX4 before OFFBOARD).
    unflown = summarise(frames, [], events, 12.0, (640, 480), end_t=5.0, outcome="ok", unflown=[(2.0, 3.0)])
    assert unflown["standoff_rmse_m"] == 1.0 and unflown["target_in_view_ratio"] == 1.0


@pytest.mark.parametrize(
    ("estimates", "truth", "expected"),
    [
        # 3 m east and 1 m high, heading 350 against 10: 20 degrees (wrapped), at every matched sample
        (
            [PoseSample(0.0, 0.0, 3.0, -11.0, 350.0), PoseSample(1.0, 0.0, 3.0, -11.0, 350.0)],
            [PoseSample(0.02, 0.0, 0.0, -10.0, 10.0), PoseSample(0.98, 0.0, 0.0, -10.0, 10.0)],
            {
                "horizontal_mean_m": 3.0,
                "horizontal_max_m": 3.0,
                "vertical_max_m": 1.0,
                "heading_max_deg": 20.0,
            },
        ),
        # an estimate with no truth within 0.1 s is not scored
        ([PoseSample(5.0, 1.0, 0.0, 0.0, 0.0)], [PoseSample(0.0, 0.0, 0.0, 0.0, 0.0)], None),
        ([], [], None),
    ],
)
def test_estimate_error_against_the_nearest_truth(
    estimates: list[PoseSample], truth: list[PoseSample], expected: dict[str, float] | None
) -> None:
    result = estimate_error(estimates, truth)
    if expected is None:
        assert result is None
    else:
        assert result is not None and {k: result[k] for k in expected} == expected


@pytest.mark.parametrize("side", [10.0, 99.0, 3000.0, 40000.0])
def test_a_persons_unoccluded_area_is_counted_at_any_size(side: float) -> None:
    """A person right beside a low camera projects to tens of thousands of pixels across: counted on a
    coarser grid (a full-size mask took up to a second and stalled the camera stream)."""
    square = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    overlapping = [(square, (0, 0, 0)), (square + side / 2, (0, 0, 0))]  # two parts, a quarter shared
    exact = 1.75 * side * side
    assert unoccluded_area(overlapping) == pytest.approx(exact, rel=0.25 if side < 50 else 0.01)


@pytest.mark.parametrize("drift", [(0.0, 0.0), (0.6, 0.6), (-0.6, 0.6), (1.0, -1.0), (0.0, 1.5)])
def test_the_search_survey_meets_the_look_alike_first_whatever_the_take_off_drift(
    drift: tuple[float, float],
) -> None:
    """The planner begins at the lane end nearest the vehicle: from anywhere within 1.5 m of home (the real PX4
    drifted 0.6 m in its take-off) the first lane is the west one, which passes the look-alike and then the
    described person within the verifier's reach."""
    home = (47.397742, 8.545594)
    spec = SurveySpec()
    (s_n, w_e), (n_n, e_e) = spec.area_ne
    settings = SurveySettings(
        altitude_m=spec.altitude_m, overlap=spec.overlap,
        camera=CameraModel.from_hfov(640, 480, 70.0, MOUNT_PITCH_DEG, stabilised=True),
        search_range_m=spec.search_range_m, min_altitude_m=5.0, max_altitude_m=60.0,
        start=offset_to_latlon(*home, *drift),
    )  # fmt: skip
    area = rectangle(offset_to_latlon(*home, (s_n + n_n) / 2, (w_e + e_e) / 2), e_e - w_e, n_n - s_n)
    plan = plan_survey(area, settings)
    first, second = (latlon_to_offset(*home, *p) for p in plan.waypoints[:2])
    assert plan.lanes == 3 and second[0] > first[0]  # flown north
    world = search_world(1)
    for name in ("decoy", "target"):
        person = next(p for p in world.people if p.person_id == name)
        off_lane = [abs(east - first[1]) for _, east in person.waypoints]
        assert max(off_lane) <= 7.0, (name, first)
